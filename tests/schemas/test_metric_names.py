"""The torque residual is logged as ``val/eq_residual_N_m`` / ``test/eq_residual_N_m`` (newton metres; the old
``eq_residual_nm`` read as nanometres) and is what its name says: the median over the split of
|-G(q)^T f - tau_bias(q)| of the schema's healthy commands. The old name stays, deprecated, with the same value,
so monitors and dashboards written for it keep working."""
import copy
import glob
import warnings

import lightning as L
import numpy as np
import pytest
import torch
from physics_checks import torque_residual

from lightning_bodyschema.cli import main as cli_main


@pytest.fixture(scope="module")
def metrics(diff60, dm):
    """Validate and test a copy of the 60-epoch diffusion schema: (schema, val metrics, test metrics)."""
    schema = copy.deepcopy(diff60[0])
    trainer = L.Trainer(logger=False, enable_checkpointing=False, enable_progress_bar=False,
                        enable_model_summary=False)
    (val,) = trainer.validate(schema, dm, verbose=False)
    (test,) = trainer.test(schema, dm, verbose=False)
    return schema, val, test


@pytest.mark.parametrize("stage", ["val", "test"])
def test_the_torque_residual_is_named_in_newton_metres_and_is_one(metrics, dm, stage):
    schema, val, test = metrics
    logged = (val if stage == "val" else test)[f"{stage}/eq_residual_N_m"]
    q = dm.splits["val"][0]  # the data module's val and test splits are the same held-out 20 %
    _, f = schema.infer(q)
    expected = float(np.median(torque_residual(schema.robot_model, q.numpy(), f)))
    assert logged == pytest.approx(expected, rel=1e-5)


@pytest.mark.parametrize("stage", ["val", "test"])
def test_the_old_name_is_a_deprecated_alias_with_the_same_value(metrics, stage):
    logged = metrics[1] if stage == "val" else metrics[2]
    assert logged[f"{stage}/eq_residual_nm"] == logged[f"{stage}/eq_residual_N_m"]


def test_a_checkpoint_monitor_on_the_old_name_still_works(tmp_path):
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)  # "monitor ... not found" would be a warning
        cli = cli_main(["fit", "--model=DiffusionSchema", "--data.n_samples=200", "--faults.every_n_epochs=0",
                        "--progress.enabled=false", "--trainer.max_epochs=4", "--trainer.check_val_every_n_epoch=2",
                        "--checkpoint.monitor=val/eq_residual_nm", "--checkpoint.filename=best",
                        f"--trainer.default_root_dir={tmp_path}", f"--data.cache_dir={tmp_path}/cache"])
    best = cli.trainer.checkpoint_callback.best_model_score
    assert best is not None and torch.isfinite(best)
    assert glob.glob(f"{tmp_path}/lightning_logs/version_0/checkpoints/best.ckpt")
