"""The torque residual is logged as ``val/eq_residual_N_m`` / ``test/eq_residual_N_m`` (newton metres; the old
``eq_residual_nm`` read as nanometres) and is what its name says: the median over the split of
|-G(q)^T f - tau_bias(q)| of the schema's healthy commands. One name per quantity: the old name is no longer
logged, and a checkpoint monitor on it is refused with the new name."""
import copy

import lightning as L
import numpy as np
import pytest
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
def test_one_name_per_quantity_the_old_one_is_gone(metrics, stage):
    logged = metrics[1] if stage == "val" else metrics[2]
    assert f"{stage}/eq_residual_N_m" in logged and not [name for name in logged if name.endswith("_nm")]


def test_a_checkpoint_monitor_on_the_old_name_is_refused_with_the_new_one(tmp_path, capsys):
    with pytest.raises(SystemExit) as stop:
        cli_main(["fit", "--model=DiffusionSchema", "--trainer.max_epochs=4", "--checkpoint.monitor=val/eq_residual_nm",
                  f"--trainer.default_root_dir={tmp_path}", f"--data.cache_dir={tmp_path}/cache"])
    err = capsys.readouterr().err.strip()
    assert stop.value.code == 2 and "\n" not in err and "now val/eq_residual_N_m" in err, err
    assert not list(tmp_path.iterdir())  # refused before anything is written
