"""StructuredSchema(length_model="geometric"): MuJoCo's path topology with numbers fitted to the lengths, on the
packaged OpenSim-style arm (spheres and cylinders with side sites): from a prior 1 mm off, the fitted body answers
as MuJoCo's at held-out postures, holds its commands in MuJoCo, round-trips a checkpoint, flags postures at a
switch of its wrapping, and exports."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from physics_checks import fit_structured as _fit

from lightning_bodyschema.data import EquilibriumDataModule
from lightning_bodyschema.errors import BodySchemaInputError
from lightning_bodyschema.schemas import StructuredSchema, load_schema
from lightning_bodyschema.sim.robot import ModelFreeRobot

GEOMETRIC = dict(length_model="geometric", torque_model="gravity", path_prior_error_mm=1.0, path_fit_postures=500)
F_MAX_N = [200.0, 200.0, 150.0, 150.0, 120.0, 120.0]  # configs/opensim_like-diff.yaml


@pytest.fixture(scope="module")
def opensim_arm():
    data = EquilibriumDataModule(model="opensim_like_arm", n_samples=1000, seed=0, cache_dir=None, f_max_n=F_MAX_N)
    return _fit(data, **GEOMETRIC)


def test_the_fitted_paths_answer_as_mujoco_from_a_prior_a_millimetre_off(opensim_arm):
    schema, _ = opensim_arm
    assert not any(True for _ in schema.parameters())  # fitted, nothing to train
    start = StructuredSchema(robot=schema.hparams.robot, **GEOMETRIC).length_net
    moved = (schema.length_net.numbers - start.numbers).abs().max()
    assert moved > 1e-4  # the fit started 1 mm away and moved the numbers
    q = schema.robot_model.sample_q(np.random.default_rng(11), 500)  # held out: uniform, not the data's
    l_true, G_true, tau_true = schema.robot_model.kinematics(q)
    l_geo, G, tau = schema.body_si(torch.as_tensor(q))
    worst_mm = 1e3 * np.abs(l_geo - l_true).max(axis=1)
    assert np.percentile(worst_mm, 99) < 0.05  # issue 51's length target, every posture's worst muscle
    worst_arm = 1e3 * np.abs(G - G_true).max(axis=(1, 2))
    assert np.percentile(worst_arm, 99) < 1.0  # [mm/rad]
    scale = np.median(np.linalg.norm(tau_true, axis=1))
    assert np.median(np.linalg.norm(tau - tau_true, axis=1)) < 1e-3 * scale


def test_healthy_commands_hold_their_posture_in_mujoco(opensim_arm):
    from lightning_bodyschema.sim.equilibrium import generate_equilibrium_samples
    from lightning_bodyschema.sim.settle import settle

    schema, _ = opensim_arm
    q = generate_equilibrium_samples(schema.robot_model, 12, 7, schema.spring).q
    l_motor, f, status = schema.solve_si(torch.as_tensor(q))
    ok = np.array([s == "ok" for s in status])
    assert ok.sum() >= 10
    rest = settle(schema.robot_model, l_motor[ok], f[ok], q[ok], spring=schema.spring).E_q_rest
    assert np.isfinite(rest).all() and np.percentile(rest, 90) < 1e-3  # issue 51: healthy p90 <= 1 mrad


def test_checkpoint_round_trip_answers_the_same(opensim_arm, tmp_path):
    schema, trainer = opensim_arm
    path = str(tmp_path / "geometric.ckpt")
    trainer.save_checkpoint(path, weights_only=False)
    loaded = load_schema(path)
    q = torch.as_tensor(schema.robot_model.sample_q(np.random.default_rng(6), 20))
    for a, b in zip(schema.body_si(q), loaded.body_si(q)):
        np.testing.assert_array_equal(a, b)


@pytest.fixture(scope="module")
def myoarm_path():
    """myoArm's paths at the MJCF's numbers (a fitted body's numbers differ from these by micrometres)."""
    from lightning_bodyschema.apps.common import robot_from_config
    from lightning_bodyschema.schemas.geometric import geometric_path

    model = robot_from_config("configs/myoarm.yaml")[0]
    return model, geometric_path(model)


def test_the_flag_marks_postures_next_to_a_jump_of_the_paths_and_says_how_far(myoarm_path):
    """On a line through myoArm's joint box DELT1's length (MuJoCo's) jumps by 1.85 mm where the site after its
    sphere enters the sphere; the flag's distance (the margins' first-order distance) is the distance along the line
    to within its curvature, postures within 5 mrad are flagged, postures 0.1 rad away are not."""
    from lightning_bodyschema.schemas.geometric import geometric_switches

    model, path = myoarm_path
    lo, hi = model.q_range.T
    a, b = lo + (hi - lo) * np.random.default_rng(4).random((2, len(lo)))
    q = a + np.linspace(0, 1, 4001)[:, None] * (b - a)
    step = np.abs(np.diff(model.kinematics(q[3700:3901])[0], axis=0)).max(axis=1)
    jump = 3700 + int(np.argmax(step))
    assert step.max() > 1e-3  # the 1.85 mm jump between neighbours 1 mrad apart
    at = np.array([jump - 100, jump - 3, jump + 4])
    distance, muscle = geometric_switches(path, q[at])
    half_step = 0.5 * np.linalg.norm(q[1] - q[0])  # the jump lies somewhere between its two neighbours
    along = np.linalg.norm(q[at] - 0.5 * (q[jump] + q[jump + 1]), axis=1)  # [rad] to the jump, along the line
    assert (muscle[1:] == model.muscle_names.index("DELT1_tendon")).all()
    # the shortest way to the switch is at most the line's; on both sides the same fraction of it (one smooth
    # margin crossing zero, the line at one angle to its gradient)
    assert (distance[1:] <= 1.05 * (along[1:] + half_step)).all() and (distance[1:] > 0).all()
    ratio = distance[1:] / along[1:]
    assert abs(ratio[0] - ratio[1]) < 0.25 * ratio.max() + half_step / along[1:].min()
    flags = path_switch_flags(distance)
    assert flags[1:].all() and not flags[0]  # 3-4 mrad from the jump; 0.1 rad along the line


def test_the_flag_stays_within_its_budget_on_uniform_postures(myoarm_path):
    """Issue 51's flag budget (at most 1 % of postures excepted): margins that do not move with the posture (a side
    site riding its geom's body) never flag; on myoArm's paths at 300 uniform postures the flag takes under 2 %."""
    from lightning_bodyschema.schemas.geometric import geometric_switches

    model, path = myoarm_path
    distance, muscle = geometric_switches(path, model.sample_q(np.random.default_rng(2), 300))
    assert path_switch_flags(distance).mean() < 0.02
    assert (muscle[np.isinf(distance)] == -1).all() and (muscle[np.isfinite(distance)] >= 0).all()


def path_switch_flags(distance_rad):
    from lightning_bodyschema.networks.switches import switch_diagnostics

    return switch_diagnostics(distance_rad, np.zeros(len(distance_rad), int))["near_path_switch"]


def test_geometric_needs_the_mjcf_and_sane_options(opensim_arm):
    spring = opensim_arm[0].hparams.robot["spring"]
    robot = dict(ModelFreeRobot(["shoulder", "elbow"], [[-1, 1], [0, 2]], ["a", "b"]).as_dict(), spring=spring)
    with pytest.raises(BodySchemaInputError, match="needs the robot's MJCF"):
        StructuredSchema(robot=robot, length_model="geometric")
    for bad in (dict(path_prior_error_mm=-1.0), dict(path_fit_postures=0), dict(path_fit_seed=True)):
        with pytest.raises(BodySchemaInputError, match=list(bad)[0]):
            StructuredSchema(robot=opensim_arm[0].hparams.robot, length_model="geometric", **bad)


@pytest.mark.parametrize("batch", [pytest.param("dynamic", marks=pytest.mark.slow), 1])
def test_the_adapter_exports_and_answers_as_in_python(opensim_arm, batch):
    """The package's program (``deploy.package.exported_program``: the geometric paths traced, every wrap case
    selected branch-free) answers as the Python adapter: the same statuses, ok rows to the solver's tolerance."""
    from physics_checks import mixed_faults

    from lightning_bodyschema.deploy.package import exported_program
    from lightning_bodyschema.deploy.structured import StructuredAdapterModule
    from lightning_bodyschema.status import status_array

    schema, trainer = opensim_arm
    q, faults = mixed_faults(schema, trainer.datamodule, n=12)
    ref = schema.adapter(faults, check_physics=False)(q)
    module = StructuredAdapterModule(schema).eval()
    program = exported_program(module, batch).module()
    rows = [np.arange(len(q))] if batch == "dynamic" else [np.array([i]) for i in range(4)]
    for at in rows:
        nan = np.full(faults.cut[at].shape, np.nan)
        band = faults.l_band_m[at] if faults.l_band_m is not None else np.stack([nan, nan], -1)
        arrays = (q[at], faults.cut[at], faults.fix[at], faults.l_fixed_m[at],
                  nan if faults.f_max_n is None else faults.f_max_n[at], band[..., 0], band[..., 1])
        inputs = tuple(torch.from_numpy(np.ascontiguousarray(a, dtype=np.float64)) for a in arrays)
        with torch.no_grad():
            l_motor, f, status = program(*inputs, torch.tensor(0))
        status = status_array(status.numpy().tolist())
        assert (status == ref.status[at]).all()
        ok = status == "ok"
        np.testing.assert_allclose(l_motor.numpy()[ok], ref.l_motor_m[at][ok], rtol=0, atol=1e-6)
        np.testing.assert_allclose(f.numpy()[ok], ref.f_n[at][ok], rtol=0, atol=1e-2)
