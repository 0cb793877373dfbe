"""Every solvable row solved (issue 50, item 4): myoArm with all eleven elbow flexors cut, along a 200-frame reach.

The remaining muscles hold about 166 of the frames only with activations of several hundred (inside the lifted cap
of 1000): their terms reach 4e4 N m in a torque of 7 N m, so a balance to 1e-12 N m lies below float64's rounding,
and both solvers used to leave some of those frames ``not_converged``. Now each frame is held (MuJoCo's own forces
with the activations balance it) or ``infeasible`` with a separating direction that proves no tension in the box
reaches its torque.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import yaml

from lightning_bodyschema.solvers import BoxQP
from lightning_bodyschema.solvers.solve import separating_direction
from lightning_bodyschema.status import Status

pytest.importorskip("myo_sim")
from lightning_bodyschema.statics import StaticBody  # noqa: E402
from lightning_bodyschema.statics.check import mujoco_residual_nm  # noqa: E402
from lightning_bodyschema.statics.optimize import RELAXED_ACTIVATION  # noqa: E402

# the reach: each free joint from and to these fractions of its range, on a cosine profile over 200 frames
REACH_FROM = np.array([0.323, 0.458, 0.171, 0.413, 0.233, 0.286, 0.725])
REACH_TO = np.array([0.302, 0.487, 0.933, 0.915, 0.702, 0.537, 0.299])
EQUILIBRIUM_TOL_NM = 1e-6  # the statuses' equilibrium tolerance (solvers.EQUILIBRIUM_TOL_NM)


@pytest.fixture(scope="module")
def arm():
    with open("configs/myoarm.yaml") as fh:
        locks = yaml.safe_load(fh)["data"]["locked_joints"]
    return StaticBody("myo:myoarm", locked_joints=locks)


@pytest.fixture(scope="module")
def reach(arm):
    """``(q (200, 7), flexors)``: the reach and every muscle that shortens as the elbow flexes at each frame."""
    lo, hi = arm.model.q_range.T
    s = 0.5 - 0.5 * np.cos(np.pi * np.linspace(0.0, 1.0, 200))[:, None]
    q = lo + (REACH_FROM + s * (REACH_TO - REACH_FROM)) * (hi - lo)
    G = arm.model.kinematics(q)[1][:, :, arm.model.joint_names.index("elbow_flexion_r")]
    flexors = [name for k, name in enumerate(arm.model.muscle_names) if (G[:, k] < 0).all()]
    assert len(flexors) == 11 and {"BIClong_tendon", "BRA_tendon", "BRD_tendon"} <= set(flexors)
    return q, flexors


def _gap_nm(G, tau, lo, hi, u):
    """(B,) ``u . tau - max over the box of u . (-G^T f)``: positive proves that no f in [lo, hi] gives -G^T f = tau
    (written out here, independently of the solvers' own check)."""
    c = -np.einsum("bmn,bn->bm", G, u)
    return np.einsum("bn,bn->b", u, tau) - np.where(c > 0, hi * c, np.where(c < 0, lo * c, 0.0)).sum(1)


@pytest.mark.parametrize("solver", ["newton", "proxqp"])
def test_every_reach_frame_is_held_or_proven_out_of_reach(arm, reach, solver):
    q, flexors = reach
    result = arm.solve(q, {"cut": flexors}, solver=solver)
    status = np.array([s.name for s in result.status])
    held = (status == "OK") | (status == "ACTIVATION_ABOVE_ONE")
    infeasible = status == "INFEASIBLE"
    assert (held | infeasible).all(), dict(zip(*np.unique(status, return_counts=True)))
    assert held.sum() >= 150 and infeasible.sum() >= 20  # the reach passes from holdable to out of reach

    residual, miss = mujoco_residual_nm(arm, result.take(held))
    assert residual.max() <= EQUILIBRIUM_TOL_NM and miss.max() <= 1e-6  # MuJoCo's forces hold every held frame
    assert result.activation[held].max() > 400.0  # the badly scaled frames are among them
    assert result.activation[held].max() <= RELAXED_ACTIVATION * (1 + 1e-12)

    l_geo, G, tau = arm.model.kinematics(q[infeasible])
    faults = arm.fault_batch({"cut": flexors}, int(infeasible.sum()))
    lo, hi, s, p = arm.tension_bounds(l_geo, faults)
    relaxed = np.minimum(hi, p + RELAXED_ACTIVATION * s)  # the widest box any status is decided in
    problem = BoxQP.build(G, tau, 0.0, lo, relaxed)
    u = separating_direction(problem, problem.lo_n).numpy()
    assert np.isfinite(u).all()
    assert (_gap_nm(G, tau, lo, relaxed, u) > math.sqrt(G.shape[2]) * EQUILIBRIUM_TOL_NM).all()


def test_the_statuses_agree_between_the_solvers(arm, reach):
    q, flexors = reach
    newton, proxqp = (arm.solve(q, {"cut": flexors}, solver=solver) for solver in ("newton", "proxqp"))
    assert list(newton.status) == list(proxqp.status)
    held = np.array([s in (Status.OK, Status.ACTIVATION_ABOVE_ONE) for s in newton.status])
    scale = np.abs(newton.activation[held]).max(1, keepdims=True)
    assert (np.abs(newton.activation[held] - proxqp.activation[held]) / scale).max() <= 1e-6
