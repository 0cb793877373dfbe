"""Schemas through the real CLI, Lightning and TensorBoard, at small sizes."""
import glob
import os
import sys

import numpy as np
import pytest
import torch

from lightning_bodyschema.cli import main as cli_main
from lightning_bodyschema.schemas import load_schema
from lightning_bodyschema.sim import elongation_from_tension

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
CONFIGS = ["ae-3", "ae-10", "ae-30", "vae-3", "vae-10", "vae-30", "diff"]
# the default run trains one config of each kind; the other latent sizes run the same code (slow)
DEFAULT_CONFIGS = {"ae-3", "vae-10", "diff"}


def fit(tmp_path, config_args, epochs=3, val_every=1, extra=()):
    """Run ``bodyschema fit`` in-process; return the last checkpoint and the log folder."""
    root = str(tmp_path / "run")
    cli_main(["fit", *config_args, f"--trainer.max_epochs={epochs}", f"--trainer.check_val_every_n_epoch={val_every}",
              f"--trainer.default_root_dir={root}", f"--data.cache_dir={tmp_path / 'cache'}", *extra])
    ckpts = sorted(glob.glob(f"{root}/lightning_logs/version_*/checkpoints/*.ckpt"))
    assert ckpts, "fit wrote no checkpoint"
    return ckpts[-1], os.path.dirname(os.path.dirname(ckpts[-1]))


def healthy_residuals(schema, q):
    l_motor, f = schema.infer(q)
    l_geo, G, tau = schema.robot_model.kinematics(q)
    eq = np.linalg.norm(np.einsum("bmn,bm->bn", -G, f) - tau, axis=1)
    length = np.abs(l_motor + elongation_from_tension(f, schema.spring) - l_geo)
    return np.median(eq), np.median(length)


@pytest.mark.parametrize("name", [n if n in DEFAULT_CONFIGS else pytest.param(n, marks=pytest.mark.slow)
                                  for n in CONFIGS])
def test_every_paper_config_trains_through_the_cli(tmp_path, name):
    ckpt, _ = fit(tmp_path, ["--config", f"{ROOT}/configs/{name}.yaml"], epochs=3)
    schema = load_schema(ckpt)
    l_motor, f = schema.infer(np.zeros((4, 2)))
    assert np.all(np.isfinite(l_motor)) and np.all(np.isfinite(f))
    n_params = sum(p.numel() for p in schema.parameters())
    print(f"{name}: {n_params} parameters")


def test_checkpoint_round_trip_is_bit_identical_and_self_contained(tmp_path):
    ckpt, _ = fit(tmp_path, ["--model=DiffusionSchema"], epochs=4)
    q = np.random.default_rng(0).uniform(-1, 1, (16, 2))
    first, second = load_schema(ckpt), load_schema(ckpt)
    for a, b in zip(first.infer(q), second.infer(q)):
        np.testing.assert_array_equal(a, b)
    checkpoint = torch.load(ckpt, map_location="cpu", weights_only=True)
    robot = checkpoint["hyper_parameters"]["robot"]
    assert "<mujoco" in robot["model_xml"] and robot["spring"]["f_max_n"] == 150.0
    assert "normalizer.x_mean" in checkpoint["state_dict"]


def test_training_learns_the_equilibrium_manifold(tmp_path):
    """A short VAE-10 run already cuts the healthy equilibrium residual several-fold vs the untrained net."""
    ckpt, _ = fit(tmp_path, ["--config", f"{ROOT}/configs/vae-10.yaml"], epochs=150, val_every=150)
    trained = load_schema(ckpt)
    untrained = type(trained)(**{k: v for k, v in trained.hparams.items() if not k.startswith("_")})
    untrained.normalizer.load_state_dict(trained.normalizer.state_dict())
    q = trained.robot_model.sample_q(np.random.default_rng(5), 100)
    eq_trained, len_trained = healthy_residuals(trained, q)
    eq_untrained, len_untrained = healthy_residuals(untrained, q)
    print(f"median eq residual {eq_untrained:.3f} -> {eq_trained:.3f} N m, length {len_untrained:.2e} -> {len_trained:.2e} m")
    assert eq_trained < 0.3 * eq_untrained and len_trained < 0.3 * len_untrained
    assert eq_trained < 1.5  # N m, after only 150 epochs


def test_tensorboard_has_scalars_and_the_figure(tmp_path):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    _, logdir = fit(tmp_path, ["--model=AutoEncoderSchema", "--trainer.log_every_n_steps=1",
                               "--figures.every_n_validations=1"], epochs=2)
    events = EventAccumulator(logdir, size_guidance={"images": 0, "scalars": 0})
    events.Reload()
    scalars = set(events.Tags()["scalars"])
    for tag in ("train/loss", "train/lr", "val/loss", "val/eq_residual_N_m", "val/length_residual_mm",
                "val/f_err_n", "val/l_motor_err_mm"):
        assert tag in scalars, f"{tag} missing from {sorted(scalars)}"
    assert "val/reconstruction" in events.Tags()["images"]
    assert np.isfinite(events.Scalars("val/eq_residual_N_m")[-1].value)


def test_subclass_example_trains_through_the_cli(tmp_path):
    sys.path.insert(0, os.path.join(ROOT, "examples"))
    try:
        ckpt, _ = fit(tmp_path, ["--model=regression_schema.RegressionSchema"], epochs=60, val_every=60)
    finally:
        sys.path.remove(os.path.join(ROOT, "examples"))
    assert sum(1 for _ in open(os.path.join(ROOT, "examples", "regression_schema.py"))) <= 60
    schema = load_schema(ckpt)
    eq, _ = healthy_residuals(schema, schema.robot_model.sample_q(np.random.default_rng(1), 50))
    assert eq < 5.0


def test_print_config_and_rerun_in_same_folder(tmp_path, monkeypatch, capsys):
    """In-process (the console script's own process is tested in tests/cli/test_cli_usability.py)."""
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as printed:
        cli_main(["fit", "--config", f"{ROOT}/configs/diff.yaml", "--print_config"])
    out = capsys.readouterr().out
    assert printed.value.code in (0, None) and "DiffusionSchema" in out and "n_timesteps: 200" in out
    for _ in range(2):  # the second run must not fail on the saved config.yaml of the first
        cli_main(["fit", "--model=VAESchema", "--trainer.max_epochs=1", "--trainer.default_root_dir=run",
                  "--trainer.logger=false", "--data.cache_dir=cache"])
    assert len(glob.glob("run/**/config.yaml", recursive=True)) >= 1


# Bad CLI input (exit 2, one line, no traceback, nothing written; real subprocesses too): tests/cli/test_bad_input.py


@pytest.mark.slow
def test_full_paper_diffusion_run_meets_healthy_targets(tmp_path):
    """The acceptance run: configs/diff.yaml, 10000 epochs; healthy commands at the test postures."""
    ckpt, _ = fit(tmp_path, ["--config", f"{ROOT}/configs/diff.yaml"], epochs=10000, val_every=500)
    schema = load_schema(ckpt)
    from lightning_bodyschema.data import EquilibriumDataModule

    dm = EquilibriumDataModule(cache_dir=None)
    dm.setup("test")
    eq, length = healthy_residuals(schema, dm.splits["val"][0].numpy())
    assert eq <= 0.2 and length <= 1e-3
