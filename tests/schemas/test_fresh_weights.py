"""Validation, benchmarks, infer and adapt always use the weights of the moment (the stale-weights bug).

Fused optimizers (the default fused Adam) update parameters in place without bumping their version counters, so
a cache keyed on ``_version`` served the weights of its first use for the rest of a process. The schema's
inference cache is now cleared on every mode switch, load and dtype/device move, and keeps nothing in training.
"""
import glob
import warnings

import numpy as np
import pytest
import torch
from physics_checks import train_schema
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from lightning_bodyschema.cli import main as cli_main
from lightning_bodyschema.faults import Faults
from lightning_bodyschema.schemas import AutoEncoderSchema, DiffusionSchema, VAESchema, load_schema

SCHEMAS = {"DiffusionSchema": DiffusionSchema, "AutoEncoderSchema": AutoEncoderSchema, "VAESchema": VAESchema}


def _cli(*args):
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*LightningCLI's args parameter.*")
        return cli_main(list(args))


def _scalars(log_dir, tag):
    events = EventAccumulator(log_dir)
    events.Reload()
    return [e.value for e in events.Scalars(tag)]


@pytest.mark.parametrize("model", list(SCHEMAS))
def test_each_validation_sees_the_current_weights_and_matches_bodyschema_validate(tmp_path, model):
    common = [f"--model={model}", f"--data.cache_dir={tmp_path}/cache", f"--trainer.default_root_dir={tmp_path}",
              "--faults.every_n_epochs=0", "--progress.enabled=false"]
    _cli("fit", *common, "--trainer.max_epochs=40", "--trainer.check_val_every_n_epoch=20")
    log_dir = glob.glob(f"{tmp_path}/lightning_logs/version_0")[0]
    first, second = _scalars(log_dir, "val/eq_residual_N_m")
    assert first != second  # the second validation ran on trained-further weights
    ckpt = glob.glob(f"{log_dir}/checkpoints/last.ckpt")[0]
    cli = _cli("validate", *common, f"--ckpt_path={ckpt}")
    assert float(cli.trainer.callback_metrics["val/eq_residual_N_m"]) == pytest.approx(second, rel=1e-6)
    # it logged beside the checkpoint's run: no version_1 that would shift the next fit's version
    assert cli.trainer.log_dir == f"{log_dir}/validate" and _scalars(cli.trainer.log_dir, "val/eq_residual_N_m")
    assert [p.name for p in (tmp_path / "lightning_logs").iterdir()] == ["version_0"]


@pytest.mark.parametrize("cls", list(SCHEMAS.values()), ids=list(SCHEMAS))
@pytest.mark.parametrize("switch_to_eval", [True, False])
def test_adapt_after_further_training_uses_the_new_weights(dm, cls, switch_to_eval):
    schema, _, _ = train_schema(cls, 10, dm)
    q = dm.splits["val"][0][:4].numpy()
    faults = Faults.from_names(schema.robot_model.muscle_names, cut=[["shoulder_flexor"]] * 4)
    before = schema.adapt(q, faults, check_physics=False, n_steps=20) if cls is DiffusionSchema else \
        schema.adapt(q, faults, check_physics=False)
    import lightning as L

    L.Trainer(max_epochs=10, logger=False, enable_checkpointing=False, enable_progress_bar=False,
              enable_model_summary=False, check_val_every_n_epoch=10 ** 6, num_sanity_val_steps=0).fit(schema, dm)
    if switch_to_eval:
        schema.eval()
    options = {"n_steps": 20} if cls is DiffusionSchema else {}
    after = schema.adapt(q, faults, check_physics=False, **options)
    fresh = cls(robot=dm.robot, **{k: v for k, v in schema.hparams.items() if k != "robot"})
    fresh.load_state_dict(schema.state_dict())
    expected = fresh.eval().adapt(q, faults, check_physics=False, **options)
    np.testing.assert_array_equal(after.f_n, expected.f_n)
    assert not np.allclose(after.f_n, before.f_n)


def test_the_cache_is_cleared_by_a_dtype_move_and_by_hand(dm, diff60):
    schema = load_schema_copy(diff60[0], dm)
    q = dm.splits["val"][0][:2].numpy()
    schema.infer(q)
    assert len(schema.inference_cache) > 0
    schema.double()
    assert len(schema.inference_cache) == 0
    schema.infer(q)
    with torch.no_grad():
        for p in schema.parameters():
            p.mul_(1.01)
    stale = schema.infer(q)[1]
    schema.clear_caches()
    assert not np.array_equal(schema.infer(q)[1], stale)


def load_schema_copy(schema, dm):
    copy = DiffusionSchema(robot=dm.robot)
    copy.load_state_dict(schema.state_dict())
    return copy.eval()
