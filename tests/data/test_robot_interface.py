"""One declared robot interface, and a data module that owns its minibatch size.

``sim.robot.RobotModel`` is what the package asks of a robot; the MuJoCo model and the recorded-data robot both
implement it, declare ``has_physics`` themselves, refuse bad postures the same way and round-trip through the one
factory (``robot_model_from_dict``). The data module serves minibatches of its own ``batch_size``; the CLI links
``--model.batch_size`` to it, and a fit refuses a schema and a data module that disagree.
"""
from __future__ import annotations

import math

import lightning as L
import numpy as np
import pytest
import torch
from physics_checks import fit_tiny_checkpoint

from lightning_bodyschema.data import EquilibriumDataModule
from lightning_bodyschema.errors import BodySchemaInputError
from lightning_bodyschema.schemas import DiffusionSchema
from lightning_bodyschema.sim import MusculoskeletalModel
from lightning_bodyschema.sim.robot import ModelFreeRobot, RobotModel, robot_model_from_dict


@pytest.fixture(scope="module")
def robots(arm):
    recorded = ModelFreeRobot(arm.joint_names, arm.q_range, arm.muscle_names)
    return arm, recorded


def test_both_robots_implement_the_interface_and_declare_physics(robots):
    arm, recorded = robots
    assert isinstance(arm, RobotModel) and isinstance(recorded, RobotModel)
    assert arm.has_physics is True and recorded.has_physics is False
    assert MusculoskeletalModel.has_physics and not ModelFreeRobot.has_physics  # declared on the class


def test_both_robots_refuse_a_bad_posture_alike(robots):
    arm, recorded = robots
    lo, hi = arm.q_range[0]
    for robot in robots:
        np.testing.assert_array_equal(robot.check_q([0.1, -0.2]), [[0.1, -0.2]])
        with pytest.raises(BodySchemaInputError, match="NaN or inf"):
            robot.check_q([[np.nan, 0.0]])
        with pytest.raises(BodySchemaInputError, match=f"joint {arm.joint_names[0]!r} is .*outside its range"):
            robot.check_q([[hi + 0.1, 0.0]], within_range=True)
        with pytest.raises(BodySchemaInputError, match="expected \\(B, 2\\)"):
            robot.check_q(np.zeros((1, 3)))


def test_the_factory_rebuilds_each_robot_with_its_hash(robots, dm):
    arm, recorded = robots
    rebuilt = robot_model_from_dict(dm.robot)
    assert isinstance(rebuilt, MusculoskeletalModel) and rebuilt.xml_hash == dm.robot_model.xml_hash
    again = robot_model_from_dict(recorded.as_dict())
    assert isinstance(again, ModelFreeRobot) and again.xml_hash == recorded.xml_hash
    with pytest.raises(BodySchemaInputError, match="lacks \\['q_range'\\]"):
        robot_model_from_dict({"joints": ["a"], "muscles": ["m"]})


def test_a_schema_reads_has_physics_from_its_robot(dm, robots):
    schema = DiffusionSchema(robot=dm.robot)
    assert schema.has_physics is schema.robot_model.has_physics is True
    schema.robot_model = robots[1]
    assert schema.has_physics is False


def test_the_data_module_serves_its_own_batch_size(dm):
    small = EquilibriumDataModule(cache_dir=None, batch_size=48)
    small.setup("fit")
    n_train = len(small.splits["train"][0])
    batches = list(small.train_dataloader())
    assert [len(q) for q, _ in batches[:-1]] == [48] * (len(batches) - 1)
    assert len(batches) == small.train_batches_per_epoch() == math.ceil(n_train / 48)
    assert sum(len(q) for q, _ in batches) == n_train
    with pytest.raises(BodySchemaInputError, match="batch_size=0 must be a positive integer"):
        EquilibriumDataModule(cache_dir=None, batch_size=0)


def test_a_fit_refuses_a_schema_and_data_that_disagree_on_the_batch_size(dm):
    schema = DiffusionSchema(robot=dm.robot, batch_size=32)
    trainer = L.Trainer(max_epochs=1, logger=False, enable_checkpointing=False, enable_progress_bar=False,
                        enable_model_summary=False)
    with pytest.raises(BodySchemaInputError, match="batch_size=32 differs from the data module's batch_size=64"):
        trainer.fit(schema, dm)


def test_the_cli_links_the_schema_batch_size_to_the_data(tmp_path):
    ckpt = fit_tiny_checkpoint(tmp_path, "--model.batch_size=16", "--data.n_samples=100", "--faults.every_n_epochs=0",
                               epochs=1)
    checkpoint = torch.load(ckpt, weights_only=True)
    assert checkpoint["hyper_parameters"]["batch_size"] == checkpoint["datamodule_hyper_parameters"]["batch_size"] == 16
    assert checkpoint["global_step"] == math.ceil(80 / 16)  # 100 samples, 20 % held out, batches of 16
