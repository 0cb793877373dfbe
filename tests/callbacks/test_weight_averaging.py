"""Weight averaging through Lightning's own ``EMAWeightAveraging`` on the structured schema (paper arm, a few real
epochs): the checkpoint holds the exponential average of the trained weights, validation and the project's callbacks
see that average, loading and ``bodyschema test`` use it, the normalizer and torque scale stay the data's, and the
same seed gives the same bytes (the two `bodyschema` runs, about a minute: slow)."""
from __future__ import annotations

import glob
import warnings

import lightning as L
import pytest
import torch
from lightning.pytorch.callbacks import Callback, EMAWeightAveraging, ModelCheckpoint

from lightning_bodyschema.callbacks import FaultBenchmark, ReconstructionFigure
from lightning_bodyschema.callbacks.steps import averaged_weights_now
from lightning_bodyschema.cli import main as cli_main
from lightning_bodyschema.data import EquilibriumDataModule
from lightning_bodyschema.schemas import StructuredSchema, load_schema

DECAY = 0.7  # a short memory: a few steps move the average well away from the last weights
BUFFERS = ("normalizer.x_mean", "normalizer.x_std", "normalizer.q_lo", "normalizer.q_hi", "tau_scale_nm")


class _Recorder(Callback):
    """The schema's weights after every optimizer step, and as validation sees them (listed before the EMA)."""

    def __init__(self):
        self.steps, self.validated = [], None

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
        self.steps.append({k: v.detach().clone() for k, v in pl_module.named_parameters()})

    def on_validation_epoch_end(self, trainer, pl_module):
        self.validated = {k: v.detach().clone() for k, v in pl_module.named_parameters()}


@pytest.mark.parametrize("use_buffers", [False, True])
def test_checkpoint_holds_the_exponential_average_and_the_data_buffers(tmp_path, use_buffers):
    datamodule = EquilibriumDataModule(n_samples=120, seed=0, cache_dir=None, batch_size=32)
    L.seed_everything(0, verbose=False)
    schema = StructuredSchema(robot=datamodule.robot, hidden=32, n_hidden=2, block="residual", norm="layer",
                              batch_size=32)
    ema, recorder = EMAWeightAveraging(decay=DECAY, use_buffers=use_buffers), _Recorder()
    trainer = L.Trainer(max_epochs=3, check_val_every_n_epoch=3, callbacks=[ema, recorder], logger=False,
                        enable_progress_bar=False, enable_model_summary=False, num_sanity_val_steps=0,
                        default_root_dir=tmp_path)
    trainer.fit(schema, datamodule)
    assert trainer.callbacks.index(ema) > trainer.callbacks.index(recorder)  # moved after the scoring callbacks
    checkpoint = torch.load(trainer.checkpoint_callback.best_model_path, weights_only=True)
    state = checkpoint["state_dict"]
    average = dict(recorder.steps[0])  # torch's EMA: the first update copies, then decay * avg + (1 - decay) * new
    for step in recorder.steps[1:]:
        average = {k: DECAY * average[k] + (1 - DECAY) * step[k] for k in average}
    for name, value in average.items():
        torch.testing.assert_close(state[name], value, rtol=1e-6, atol=1e-7)
        torch.testing.assert_close(checkpoint["current_model_state"][name], recorder.steps[-1][name], rtol=0, atol=0)
        torch.testing.assert_close(recorder.validated[name], state[name], rtol=0, atol=0)  # validation saw the average
    gap = max((state[k] - recorder.steps[-1][k]).abs().max().item() for k in average)
    assert gap > 1e-4  # the average is not the last weights: the checks above can tell them apart
    expected = {f"normalizer.{k}": v for k, v in datamodule.normalizer.state_dict().items()}
    expected["tau_scale_nm"] = schema.torque_scale()
    for name in BUFFERS:  # use_buffers=True averages the constant buffers too: the same numbers to the last bit or so
        torch.testing.assert_close(state[name], expected[name], rtol=0 if not use_buffers else 1e-15, atol=0)
    for loaded in (load_schema(trainer.checkpoint_callback.best_model_path),
                   StructuredSchema.load_from_checkpoint(trainer.checkpoint_callback.best_model_path), schema):
        for name, value in loaded.state_dict().items():
            assert torch.equal(value, state[name]), name  # the fitted schema itself ends with the average too
    with torch.no_grad():  # the fault benchmark's and figure's end-of-fit path (EarlyStopping) puts the average in
        for p in schema.parameters():
            p.add_(1.0)
    averaged_weights_now(trainer, schema)
    assert all(torch.equal(value, state[name]) for name, value in schema.state_dict().items())


def _cli(subcommand, root, *extra):
    ema = root.parent / "ema.yaml"
    ema.write_text("trainer:\n  callbacks:\n    - class_path: lightning.pytorch.callbacks.EMAWeightAveraging\n"
                   f"      init_args: {{decay: {DECAY}, use_buffers: false}}\n")
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*LightningCLI's args parameter.*")
        warnings.filterwarnings("ignore", message=".*WeightAveraging callback, but loading a checkpoint.*")
        return cli_main([subcommand, "--config=configs/structured.yaml", f"--config={ema}", "--data.n_samples=120",
                         "--model.hidden=32", "--model.n_hidden=2", "--model.batch_size=32", "--model.block=residual",
                         "--model.norm=layer", f"--trainer.default_root_dir={root}", "--data.cache_dir=null",
                         "--progress.enabled=false", "--faults.n_per_condition=2", "--faults.settle_check=false",
                         "--faults.protocols=[paper]", *extra])


@pytest.fixture(scope="module")
def two_cli_fits(tmp_path_factory):
    """`bodyschema fit` twice with the same seed, the EMA in the config's callbacks and the in-fit fault benchmark."""
    fits = []
    for name in ("a", "b"):
        root = tmp_path_factory.mktemp("ema") / name
        cli = _cli("fit", root, "--trainer.max_epochs=4", "--trainer.check_val_every_n_epoch=2",
                   "--faults.every_n_epochs=2")
        fits.append((cli, glob.glob(f"{root}/lightning_logs/version_*/checkpoints/last.ckpt")[0]))
    return fits


@pytest.mark.slow
def test_cli_config_callbacks_run_after_the_projects_and_the_fit_is_deterministic(two_cli_fits):
    (cli, path), (_, other) = two_cli_fits
    names = [type(cb) for cb in cli.trainer.callbacks]
    assert names.index(EMAWeightAveraging) > max(names.index(FaultBenchmark), names.index(ReconstructionFigure))
    assert names.index(EMAWeightAveraging) < names.index(ModelCheckpoint)
    first, second = (torch.load(p, weights_only=True) for p in (path, other))
    assert "current_model_state" in first and first["averaging_state"]["n_averaged"] > 1
    for name, value in first["state_dict"].items():
        assert value.numpy().tobytes() == second["state_dict"][name].numpy().tobytes(), name
    benchmark = next(cb for cb in cli.trainer.callbacks if isinstance(cb, FaultBenchmark))
    assert benchmark._benchmarked_at is not None  # the in-fit benchmark ran beside the average


@pytest.mark.slow
def test_bodyschema_test_uses_the_averaged_weights(two_cli_fits, tmp_path):
    (_, path), _ = two_cli_fits
    averaged = torch.load(path, weights_only=True)["state_dict"]
    cli = _cli("test", tmp_path / "test", f"--ckpt_path={path}")
    for name, value in cli.model.state_dict().items():
        assert torch.equal(value, averaged[name]), name


def test_cli_refuses_an_unknown_block_in_one_line(tmp_path, capsys):
    with warnings.catch_warnings(), pytest.raises(SystemExit) as exit_info:
        warnings.filterwarnings("ignore", message=".*LightningCLI's args parameter.*")
        cli_main(["fit", "--model=StructuredSchema", "--model.norm=batch", f"--trainer.default_root_dir={tmp_path}"])
    err = [line for line in capsys.readouterr().err.splitlines() if not line.startswith("Seed set")]
    assert exit_info.value.code == 2 and err == ["error: norm='batch'; allowed: ['none', 'layer']"]
    assert not any(tmp_path.iterdir())  # nothing written
