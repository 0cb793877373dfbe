"""The adapter flags a posture near a learned path switch (StructuredSchema.path_switches): the command there is
not exact, and the result says so, with the distance and the muscle."""
import copy

import numpy as np
import pytest
import torch

from physics_checks import fit_structured

from lightning_bodyschema.data import EquilibriumDataModule
from lightning_bodyschema.faults import Faults
from lightning_bodyschema.networks.branches import refresh_branches
from lightning_bodyschema.networks.switches import JUMP_FLOOR_M, SWITCH_REACH_RAD


@pytest.fixture(scope="module")
def arm():
    """The paper arm's per-muscle body (two branches allowed; its smooth paths take none)."""
    return fit_structured(EquilibriumDataModule(n_samples=1000, seed=0, cache_dir=None), length_model="per_muscle",
                          path_degree=8, path_branches=2, torque_model="polynomial", torque_degree=6)[0]


def _switch_at_shoulder(schema, at_rad: float, jump_m: float):
    """Muscle 0's second branch: its polynomial plus ``jump_m``, switched on where the shoulder exceeds ``at_rad``
    (a gate linear in the shoulder's normalized angle: its zero set is the plane shoulder = at_rad)."""
    path, norm = schema.length_net, schema.normalizer
    lo, hi = float(norm.q_lo[0]), float(norm.q_hi[0])
    linear = (path.exponents[:, 0] == 1) & (path.exponents.sum(1) == 1)
    constant = path.exponents.sum(1) == 0
    path.gate[0] = torch.where(linear, 1.0, 0.0) - torch.where(constant, 2 * (at_rad - lo) / (hi - lo) - 1, 0.0)
    path.coef_alt[0] = path.coef[0] + torch.where(constant, jump_m / float(norm.x_std[0]), 0.0)
    path.branched[0] = True
    refresh_branches(path)
    schema.clear_caches()


def test_a_smooth_body_flags_nothing(arm):
    q = arm.robot_model.sample_q(np.random.default_rng(3), 50)
    d = arm.adapt(q, Faults.none(50, arm.n_muscles), check_physics=False).diagnostics
    assert not d["near_path_switch"].any() and np.isinf(d["path_switch_distance_rad"]).all()
    assert (d["path_switch_muscle"] == -1).all()


def test_postures_within_reach_of_a_learned_jump_are_flagged_with_their_distance(arm):
    schema = copy.deepcopy(arm)  # the fixture stays smooth
    lo, hi = schema.robot_model.q_range[0]
    at = 0.5 * (lo + hi)
    _switch_at_shoulder(schema, at, 10 * JUMP_FLOOR_M)
    q = schema.robot_model.sample_q(np.random.default_rng(4), 400)
    q[:200, 0] = at + np.linspace(-4, 4, 200) * SWITCH_REACH_RAD  # across the switch
    result = schema.adapt(q, Faults.none(400, schema.n_muscles), check_physics=False)
    d = result.diagnostics
    truth = np.abs(q[:, 0] - at)
    np.testing.assert_allclose(d["path_switch_distance_rad"], truth, rtol=0, atol=1e-9 * (hi - lo))
    assert (d["near_path_switch"] == (truth <= SWITCH_REACH_RAD)).all() and d["near_path_switch"].sum() > 50
    assert (d["path_switch_muscle"] == 0).all()
    assert (result.status == "ok").all()  # flagged, not withheld: the status is the command's own


def test_few_postures_flag_from_the_body_rows_the_adapter_just_evaluated():
    """A body the snapshot covers (gravity torque): at few postures the adapter's flag reads the whole-box rows its
    body evaluation left (no second evaluation of the gates) and answers as the gates' own terms do, to rounding;
    both within rounding of the true distance to the switch."""
    schema = fit_structured(EquilibriumDataModule(n_samples=1000, seed=0, cache_dir=None), length_model="per_muscle",
                            path_degree=8, path_branches=2, torque_model="gravity")[0]
    lo, hi = schema.robot_model.q_range[0]
    at = 0.5 * (lo + hi)
    _switch_at_shoulder(schema, at, 10 * JUMP_FLOOR_M)
    q = schema.robot_model.sample_q(np.random.default_rng(5), 8)
    q[:, 0] = at + np.linspace(-2, 2, 8) * SWITCH_REACH_RAD  # four within reach
    own = schema.path_switches(q)  # the body not evaluated there yet: the gates on their own terms
    switches = schema.inference_cache.get("switch_snapshot", None)
    switches.gate_terms = None  # a second evaluation of the gates would fail from here on
    d = schema.adapt(q, Faults.none(8, schema.n_muscles), check_physics=False).diagnostics
    np.testing.assert_allclose(d["path_switch_distance_rad"], np.abs(q[:, 0] - at), rtol=0, atol=1e-9 * (hi - lo))
    # to rounding of the posture the body evaluates (normalized in the schema's dtype: float32 here)
    np.testing.assert_allclose(d["path_switch_distance_rad"], own["path_switch_distance_rad"], rtol=0,
                               atol=1e-9 * (hi - lo))
    assert (d["near_path_switch"] == own["near_path_switch"]).all() and d["near_path_switch"].sum() == 4
