"""What a new user of ``bodyschema`` sees: short errors with a "did you mean", a help text that says what the
tool is, no ``predict`` subcommand, a clean exit code, outputs under runs/, and physical metrics at the end
of every fit whatever the validation interval.

Every check runs the real CLI (``lightning_bodyschema.cli.main``, in-process; one subprocess for the
console-script exit code).
"""
from __future__ import annotations

import glob
import subprocess
import sys
import warnings

import numpy as np
import pytest
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from lightning_bodyschema.cli import main as cli_main

TINY = ["--model=DiffusionSchema", "--data.n_samples=200", "--faults.every_n_epochs=0", "--progress.enabled=false"]


def run_cli(args, capsys) -> tuple[int, str, str]:
    """(exit code, stdout, stderr) of ``bodyschema args`` run in-process."""
    capsys.readouterr()
    with pytest.raises(SystemExit) as info:
        cli_main(args)
    out, err = capsys.readouterr()
    return info.value.code, out, err


def error_lines(err: str) -> list[str]:
    return [line for line in err.splitlines() if line.strip()]


# ---------------------------------------------------------------------------- errors: one line, did you mean
@pytest.mark.parametrize("args, bad, suggestion", [
    (["fit", "--trainer.max_epoch=3"], "--trainer.max_epoch", "did you mean --trainer.max_epochs?"),
    (["fit", "--trainer.check_val_every_n_epochs", "5"], "--trainer.check_val_every_n_epochs",
     "did you mean --trainer.check_val_every_n_epoch?"),
    (["fit", "--data.n_sample=100"], "--data.n_sample", "did you mean --data.n_samples?"),
    (["fit", "--model.hiden=32"], "'hiden'", "did you mean --model.hidden?"),
    (["fit", "--model=DifusionSchema"], "DifusionSchema", "did you mean DiffusionSchema?"),
])
def test_a_typo_is_one_error_line_with_a_suggestion_then_a_pointer_to_help(args, bad, suggestion, capsys):
    model = [] if any(a.startswith("--model=") for a in args) else ["--model=DiffusionSchema"]
    code, _, err = run_cli([args[0], *model, *args[1:]], capsys)
    lines = error_lines(err)
    assert code == 2
    assert "usage:" not in err and "Traceback" not in err
    assert len(lines) == 2, err  # was ~90 lines of usage before the error
    assert lines[0].startswith("error: ") and bad in lines[0] and lines[0].endswith(suggestion), lines[0]
    assert lines[1] == "(bodyschema fit --help lists every option)"


def test_an_option_nothing_resembles_gets_no_suggestion(capsys):
    code, _, err = run_cli(["fit", "--model=DiffusionSchema", "--zzz.qqq=1"], capsys)
    lines = error_lines(err)
    assert code == 2 and len(lines) == 2 and "--zzz.qqq" in lines[0] and "did you mean" not in lines[0]


def test_help_describes_the_tool_and_lists_no_predict(capsys):
    code, out, _ = run_cli(["--help"], capsys)
    assert code == 0
    assert "Lightning Trainer command line tool" not in out
    assert "body schema" in out and "musculoskeletal" in out and "tools/predict.py" in out
    assert "{fit,validate,test}" in out  # the subcommands, without predict


def test_predict_is_refused_naming_the_tool_that_serves_requests(capsys):
    code, _, err = run_cli(["predict", "--model=DiffusionSchema"], capsys)
    lines = error_lines(err)
    assert code == 2 and "Traceback" not in err and len(lines) == 2, err
    assert "'predict'" in lines[0] and "python tools/predict.py" in lines[0]


def test_main_with_args_never_reads_sys_argv(monkeypatch, capsys):
    """pytest's own argv used to reach LightningCLI (a warning per call); a bogus argv must change nothing."""
    monkeypatch.setattr(sys, "argv", ["pytest", "--this-is-not-a-bodyschema-option", "tests/"])
    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)  # "args and sys.argv both given" would fail here
        code, out, _ = run_cli(["--help"], capsys)
    assert code == 0 and "bodyschema" in out


# ---------------------------------------------------------------------------- a short fit
@pytest.fixture(scope="module")
def short_fit(tmp_path_factory):
    """A 7-epoch fit validating every 5 epochs, run from an empty folder with no output option at all."""
    folder = tmp_path_factory.mktemp("short_fit")
    with pytest.MonkeyPatch.context() as patch:
        patch.chdir(folder)
        cli = cli_main(["fit", *TINY, "--trainer.max_epochs=7", "--trainer.check_val_every_n_epoch=5"])
    return folder, cli


def test_outputs_land_under_runs(short_fit):
    folder, cli = short_fit
    written = sorted(str(p.relative_to(folder)) for p in folder.rglob("*") if p.is_file())
    assert written and all(path.startswith("runs/") for path in written), written
    assert any(path.startswith("runs/cache/") for path in written)  # the dataset cache, was data/cache
    assert glob.glob(str(folder / "runs/lightning_logs/version_0/checkpoints/last.ckpt"))


def test_every_fit_validates_at_its_end(short_fit):
    """Validation at epoch 5 (the interval) and at epoch 7 (the end), with the end weights' metrics."""
    folder, cli = short_fit
    events = EventAccumulator(str(folder / "runs/lightning_logs/version_0"))
    events.Reload()
    scalars = events.Scalars("val/eq_residual_N_m")
    steps_per_epoch = cli.trainer.global_step // 7  # logged at the optimizer step count, one per minibatch
    assert cli.trainer.global_step == 7 * steps_per_epoch
    assert [s.step for s in scalars] == [5 * steps_per_epoch - 1, 7 * steps_per_epoch - 1]  # ends of epochs 5 and 7
    batch = cli.datamodule.splits["val"]
    final = cli.model.physical_errors(batch[0], batch[1])["eq_residual_N_m"]
    assert scalars[-1].value == pytest.approx(final, rel=1e-5)  # the last weights, not epoch 5's
    assert scalars[0].value != pytest.approx(scalars[-1].value, rel=1e-6)
    assert cli.trainer.check_val_every_n_epoch == 5  # the user's interval is back after the fit


def test_a_fit_shorter_than_the_interval_still_validates(tmp_path, capsys):
    cli = cli_main(["fit", *TINY, "--trainer.max_epochs=2", "--trainer.check_val_every_n_epoch=500",
                    f"--trainer.default_root_dir={tmp_path}", f"--data.cache_dir={tmp_path}/cache"])
    metric = float(cli.trainer.callback_metrics["val/eq_residual_N_m"])
    assert np.isfinite(metric) and metric > 0


def test_final_validation_can_be_turned_off(tmp_path):
    cli = cli_main(["fit", *TINY, "--trainer.max_epochs=2", "--trainer.check_val_every_n_epoch=500",
                    "--final_validation.enabled=false", f"--trainer.default_root_dir={tmp_path}",
                    f"--data.cache_dir={tmp_path}/cache"])
    assert "val/eq_residual_N_m" not in cli.trainer.callback_metrics


def test_the_console_script_exits_0_after_a_fit(tmp_path):
    """``sys.exit(main())`` is what the installed ``bodyschema`` script runs: a returned object exits 1."""
    script = ("import sys; from lightning_bodyschema.cli import main; "
              f"sys.argv = ['bodyschema', 'fit', *{TINY!r}, '--trainer.max_epochs=1', "
              f"'--trainer.default_root_dir={tmp_path}', '--data.cache_dir={tmp_path}/cache']; sys.exit(main())")
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "BodySchemaCLI object" not in done.stderr
    # it ends by saying where its outputs are, and those paths exist; no advertisement for a cloud logger
    run = tmp_path / "lightning_logs" / "version_0"
    assert f"checkpoint:   {run / 'checkpoints' / 'last.ckpt'}" in done.stdout and (run / "checkpoints").is_dir()
    assert f"tensorboard --logdir {run}" in done.stdout and list(run.glob("events.out.tfevents.*"))
    assert "litlogger" not in done.stdout + done.stderr
    # the seed line held back while the classes are built (a bad option prints its error alone) is still said
    assert "Seed set to 0" in done.stdout + done.stderr


def test_a_misspelt_option_is_refused_before_torch_and_lightning_are_imported():
    """The quick check against ``cli_options``' copy of the parser's options: the typo costs no heavy import."""
    from importlib.metadata import version

    from lightning_bodyschema import cli_options

    if version("lightning") != cli_options.LIGHTNING_VERSION:
        pytest.skip(f"cli_options was copied from Lightning {cli_options.LIGHTNING_VERSION}: the quick check is off")
    script = ("import sys; from lightning_bodyschema.cli import main\ntry: main(['fit', '--trainer.max_epoch', '5'])\n"
              "except SystemExit as stop: print(stop.code, 'torch' in sys.modules, 'lightning' in sys.modules)")
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert done.stdout.split() == ["2", "False", "False"], done.stdout + done.stderr
    assert done.stderr.splitlines() == ["error: unrecognized arguments: --trainer.max_epoch; did you mean "
                                        "--trainer.max_epochs?", "(bodyschema fit --help lists every option)"]


def test_the_quick_option_copy_is_the_parsers():
    """``cli_options.options(subcommand)`` is what each subcommand's parser accepts (remake: python -m
    lightning_bodyschema.cli_options); options of a class chosen on the command line pass the quick check."""
    from importlib.metadata import version

    from lightning_bodyschema import cli_options
    from lightning_bodyschema.cli import refuse_unknown_options
    from lightning_bodyschema.cli_app import known_options

    if version("lightning") != cli_options.LIGHTNING_VERSION:
        pytest.skip(f"cli_options was copied from Lightning {cli_options.LIGHTNING_VERSION}: the quick check is off")
    assert {name: sorted(options) for name, options in known_options().items()} == {
        name: sorted(cli_options.options(name)) for name in cli_options.ONLY}
    refuse_unknown_options(["fit", "--model=DiffusionSchema", "--model.n_timesteps=5", "--data.n_samples", "9",
                            "--trainer.logger.init_args.save_dir=x", "--trainer.callbacks+=EarlyStopping"])


def test_a_fit_ended_by_max_steps_validates_at_its_end(tmp_path):
    """However many optimizer steps an epoch takes, the epoch that reaches max_steps validates."""
    common = [*TINY, "--trainer.check_val_every_n_epoch=500", f"--data.cache_dir={tmp_path}/cache",
              "--final_validation.enabled=false"]
    one = cli_main(["fit", *common, "--trainer.max_epochs=1", f"--trainer.default_root_dir={tmp_path}/one"])
    steps_per_epoch = one.trainer.global_step
    cli = cli_main(["fit", *TINY, "--trainer.check_val_every_n_epoch=500", f"--data.cache_dir={tmp_path}/cache",
                    "--trainer.max_epochs=50", f"--trainer.max_steps={3 * steps_per_epoch}",
                    f"--trainer.default_root_dir={tmp_path}/three"])
    assert cli.trainer.current_epoch == 3 and cli.trainer.global_step == 3 * steps_per_epoch  # stopped by max_steps
    assert "val/eq_residual_N_m" in cli.trainer.callback_metrics


def test_trainer_enable_progress_bar_false_turns_the_bar_off(tmp_path, capsys):
    """Lightning's own flag works: it used to exit 2 ("found EpochProgressBar in callbacks list")."""
    tiny = [arg for arg in TINY if not arg.startswith("--progress.")]
    cli = cli_main(["fit", *tiny, "--trainer.max_epochs=3", "--trainer.enable_progress_bar=false",
                    f"--trainer.default_root_dir={tmp_path}", f"--data.cache_dir={tmp_path}/cache"])
    assert cli.trainer.current_epoch == 3
    assert not cli.trainer.progress_bar_callback.is_enabled
    assert "Epoch" not in capsys.readouterr().err  # no bar drawn


def test_trainer_enable_checkpointing_false_writes_no_checkpoint(tmp_path):
    """Lightning's own flag works: it used to exit 2 ("found ModelCheckpoint in callbacks list")."""
    cli_main(["fit", *TINY, "--trainer.max_epochs=2", "--trainer.enable_checkpointing=false",
              f"--trainer.default_root_dir={tmp_path}", f"--data.cache_dir={tmp_path}/cache"])
    assert not glob.glob(f"{tmp_path}/**/*.ckpt", recursive=True)
    # and the default still keeps last.ckpt beside the epoch file
    cli_main(["fit", *TINY, "--trainer.max_epochs=2", f"--trainer.default_root_dir={tmp_path}/on",
              f"--data.cache_dir={tmp_path}/cache"])
    assert {p.rsplit("/", 1)[1] for p in glob.glob(f"{tmp_path}/on/**/*.ckpt", recursive=True)} >= {"last.ckpt"}


def test_endless_epochs_bounded_by_max_steps_anneal_over_those_steps(tmp_path):
    """``--trainer.max_epochs=-1 --trainer.max_steps=N`` is how Lightning bounds a fit by steps; it was refused
    whenever lr_final was set. The cosine spans the epochs the steps take and ends at lr_final."""
    cli = cli_main(["fit", *TINY, "--trainer.max_epochs=-1", "--trainer.max_steps=6",
                    f"--trainer.default_root_dir={tmp_path}", f"--data.cache_dir={tmp_path}/cache"])
    steps_per_epoch = cli.trainer.num_training_batches  # 160 train samples in batches of 64: 3
    assert cli.trainer.global_step == 6 and cli.trainer.current_epoch == 6 // steps_per_epoch
    (config,) = cli.trainer.lr_scheduler_configs
    assert config.scheduler.T_max == 6 // steps_per_epoch
    assert cli.trainer.optimizers[0].param_groups[0]["lr"] == pytest.approx(cli.model.hparams.lr_final)


@pytest.mark.parametrize("every", [4, 6])  # inside an epoch (3 steps each), and at an epoch's last batch
def test_a_cli_fit_resumed_from_a_step_checkpoint_ends_with_the_uninterrupted_weights(tmp_path, every):
    """``--ckpt_path`` of an ``every_n_train_steps`` checkpoint: FinalValidation crashed on the resumed epoch
    (it had seen no epoch start), and the resumed epoch used to replay its first batches."""
    import torch

    common = [*TINY, "--trainer.max_steps=9", "--trainer.max_epochs=100", f"--data.cache_dir={tmp_path}/cache"]
    full = cli_main(["fit", *common, f"--checkpoint.every_n_train_steps={every}", "--checkpoint.save_top_k=-1",
                     f"--trainer.default_root_dir={tmp_path}/full"])
    (step_ckpt,) = glob.glob(f"{tmp_path}/full/**/*step={every}.ckpt", recursive=True)
    resumed = cli_main(["fit", *common, f"--ckpt_path={step_ckpt}", f"--trainer.default_root_dir={tmp_path}/resumed"])
    assert resumed.trainer.global_step == 9 and "val/eq_residual_N_m" in resumed.trainer.callback_metrics
    expected = full.model.state_dict()
    assert all(torch.equal(expected[k], v) for k, v in resumed.model.state_dict().items())
    assert float(resumed.trainer.callback_metrics["val/eq_residual_N_m"]) == float(
        full.trainer.callback_metrics["val/eq_residual_N_m"])


def test_ckpt_path_last_resumes_from_the_newest_last_ckpt_under_the_root(tmp_path, capsys):
    """Lightning looks for ``last`` only in the new run's version folder: it found nothing and silently trained from
    scratch (and ``validate --ckpt_path last`` scored random weights)."""
    common = [*TINY, f"--data.cache_dir={tmp_path}/cache", f"--trainer.default_root_dir={tmp_path}/runs"]
    first = cli_main(["fit", *common, "--trainer.max_epochs=2"])
    (last,) = glob.glob(f"{tmp_path}/runs/**/checkpoints/last.ckpt", recursive=True)
    resumed = cli_main(["fit", *common, "--trainer.max_epochs=3", "--ckpt_path=last"])
    assert f"--ckpt_path last: {last}" in capsys.readouterr().out
    assert resumed.trainer.ckpt_path == last and resumed.trainer.global_step == 3 * first.trainer.global_step // 2
    validated = cli_main(["validate", *common, "--ckpt_path=last"])  # now the resumed fit's last.ckpt: the newest
    assert validated.trainer.ckpt_path != last and validated.trainer.ckpt_path.endswith("last.ckpt")
    assert float(validated.trainer.callback_metrics["val/eq_residual_N_m"]) == pytest.approx(
        float(resumed.trainer.callback_metrics["val/eq_residual_N_m"]), rel=1e-6)
