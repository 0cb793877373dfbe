"""The pieces that make inverse dynamics fast give the whole problem's answers: the QP cut into independent blocks
(myoLegs' two legs) and chunks of rows (``statics.qp_blocks``), the moment arms built from MuJoCo's sparse tendon
Jacobian (``statics.dynamics._ArmPlan``) on a body with locked and coupled joints (myoArm)."""
from __future__ import annotations

import numpy as np
import pytest
import yaml
from physics_checks import rounding_tol

from lightning_bodyschema.solvers import uncrossed_box
from lightning_bodyschema.status import Status

pytest.importorskip("myo_sim")
from lightning_bodyschema.statics import StaticBody  # noqa: E402
from lightning_bodyschema.statics import qp_blocks  # noqa: E402
from lightning_bodyschema.statics.dynamics import InverseBody  # noqa: E402
from lightning_bodyschema.statics.optimize import STATIC_TOL_NM, _solve_piece  # noqa: E402

# tensions [N] of two solves of one QP, each to a torque residual of STATIC_TOL_NM: the residual over the smallest
# moment arm that can take it up (~1e-3 m) bounds their gap far below this
TENSION_TOL_N = 1e-6


@pytest.fixture(scope="module")
def legs():
    return StaticBody("myo:myolegs", fixed_base=True)


@pytest.fixture(scope="module")
def legs_qp(legs):
    """The activation QP of 300 seeded postures (``_held``'s arrays, capped at full activation)."""
    q = legs.model.sample_q(np.random.default_rng(0), 300)
    l_geo, G, tau = legs.model.kinematics(q)
    faults = legs.fault_batch(None, len(q))
    lo, hi, s, p = legs.tension_bounds(l_geo, faults)
    hi = np.minimum(hi, p + s)
    positive = s > 0  # a muscle outside its force-length range has no active force: its activation is free in [0, 0]
    x_lo, x_hi = (np.where(positive, (bound - p) / np.where(positive, s, 1.0), 0.0) for bound in (lo, hi))
    x_lo, crossed = uncrossed_box(x_lo, x_hi)
    keep = ~crossed
    return (G[keep], np.where(positive, s, 0.0)[keep], (tau + np.einsum("bmn,bm->bn", G, p))[keep],
            np.zeros_like(lo)[keep], x_lo[keep], x_hi[keep])


def test_the_legs_are_two_blocks(legs, legs_qp):
    """Each leg's 40 muscles span only its own 7 joints: two blocks, each one side's muscles and joints."""
    parts = qp_blocks.blocks(legs_qp[0])
    assert len(parts) == 2
    muscles, joints = legs.model.muscle_names, legs.model.joint_names
    for block_muscles, block_joints in parts:
        assert len(block_muscles) == 40 and len(block_joints) == 7
        sides = {muscles[k].removesuffix("_tendon")[-1] for k in block_muscles}
        assert len(sides) == 1
        side = sides.pop()
        assert all(joints[j].endswith("_" + side) for j in block_joints)


def solve(*arrays):
    return _solve_piece(*arrays, "newton")


def test_pieces_give_the_whole_qps_answer(legs_qp, monkeypatch):
    """Blocks and chunks of 64 rows and more: the same tensions as one solve of the whole (within both solves'
    tolerance), the same statuses; each row balances its torque."""
    G, scale, tau, x_ref, x_lo, x_hi = legs_qp
    whole_x, whole_code = solve(G * scale[..., None], tau, x_ref, x_lo, x_hi)
    monkeypatch.setattr(qp_blocks, "MIN_CHUNK_ROWS", 64)
    monkeypatch.setattr(qp_blocks, "CHUNK_BYTES", 64 * 8 * 40 * 7)  # 64 rows of a leg's block
    assert len(qp_blocks.chunks(len(G), 40 * 7)) == len(G) // 64
    x, code = qp_blocks.solve_in_pieces(solve, G, scale, tau, x_ref, x_lo, x_hi)
    assert (code == whole_code).all() and (code == Status.OK.code).sum() >= 100  # the rest infeasible on both
    ok = code == Status.OK.code
    assert np.abs((x - whole_x) * scale)[ok].max() <= TENSION_TOL_N
    residual = np.einsum("bmn,bm->bn", G * scale[..., None], x) + tau
    assert np.abs(residual[ok]).max() <= STATIC_TOL_NM + rounding_tol(64, np.abs(G * scale[..., None] * x[..., None]))


def test_a_row_is_as_bad_as_its_worst_block(legs, legs_qp):
    """A torque on the left knee beyond what its muscles can give makes the row infeasible although the right leg's
    block holds."""
    G, scale, tau, x_ref, x_lo, x_hi = (a[:8].copy() for a in legs_qp)
    tau[0, legs.model.joint_names.index("knee_angle_l")] = 1e5  # N m: beyond any leg
    x, code = qp_blocks.solve_in_pieces(solve, G, scale, tau, x_ref, x_lo, x_hi)
    assert code[0] == Status.INFEASIBLE.code
    right = qp_blocks.blocks(G)[0][0]
    assert np.isfinite(x[0, right]).all()  # the right leg's block was solved; the row's status says why it fails


def test_chunks_cover_every_row_once():
    for rows in (0, 1, 1023, 1024, 5000, 100001):
        pieces = qp_blocks.chunks(rows, 40 * 7)
        covered = np.concatenate([np.arange(rows)[p] for p in pieces])
        assert np.array_equal(covered, np.arange(rows))
        sizes = [p.stop - p.start for p in pieces]
        assert rows < qp_blocks.MIN_CHUNK_ROWS or min(sizes) >= qp_blocks.MIN_CHUNK_ROWS
    assert len(qp_blocks.chunks(100001, 40 * 7, device="cuda")) == 1  # a GPU takes the whole batch


def test_moment_arms_from_the_sparse_jacobian_are_the_models(legs):
    """myoArm (locked fingers, a shoulder of coupled joints) and myoLegs: G from MuJoCo's sparse ``ten_J`` and E
    equals the static model's dense ``J E`` at the same postures, to the roundings of their sums."""
    with open("configs/myoarm.yaml") as fh:
        locks = yaml.safe_load(fh)["data"]["locked_joints"]
    for body in (StaticBody("myo:myoarm", locked_joints=locks), legs):
        q = body.model.sample_q(np.random.default_rng(1), 50)
        _, G, _, _, _ = InverseBody(body).inverse(q, np.zeros_like(q), np.zeros_like(q))
        expected = body.model.kinematics(q)[1]
        assert np.abs(expected).max() > 0.01  # moment arms of centimetres
        assert np.abs(G - expected).max() <= rounding_tol(64, expected)
