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


def test_warm_started_frames_are_the_solvers_answers(legs):
    """A 3 s squat (1500 frames, the left soleus cut): every frame warm-started from seeds 32 frames apart is the
    cold solve's answer (tensions within both stops' tolerance, the same statuses), and the solver ran on the seeds
    and on no more than a few other frames."""
    from lightning_bodyschema.statics import inverse_dynamics, warm_start

    t = np.arange(0.0, 3.0, 0.002)
    names = legs.model.joint_names
    q = np.zeros((len(t), len(names)))
    for joint, depth in (("hip_flexion", 0.9), ("knee_angle", 1.2), ("ankle_angle", 0.3)):
        for side in "rl":
            q[:, names.index(f"{joint}_{side}")] = depth * 0.5 * (1 - np.cos(2 * np.pi * t / 3.0))
    qvel, qacc = np.gradient(q, t, axis=0), np.gradient(np.gradient(q, t, axis=0), t, axis=0)
    calls = []
    solve_warm = warm_start.solve_warm

    def counting(solve, *arrays):
        return solve_warm(lambda *a: (calls.append(len(a[0])), solve(*a))[1], *arrays)

    faults = {"cut": ["soleus_l_tendon"]}
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr("lightning_bodyschema.statics.qp_blocks.solve_warm", counting)
        warm = inverse_dynamics(legs, q, qvel, qacc, t=t, faults=faults)
        patch.setattr("lightning_bodyschema.statics.qp_blocks.SEED_EVERY", len(t) + 1)  # no chunk warm-started
        cold = inverse_dynamics(legs, q, qvel, qacc, t=t, faults=faults)
    assert (warm.status == cold.status).all() and warm.ok.all()
    assert np.abs(warm.tension_n - cold.tension_n).max() <= TENSION_TOL_N
    seeds = 2 * -(-len(t) // warm_start.SEED_EVERY)  # two legs
    assert seeds <= sum(calls) <= seeds + 0.02 * 2 * len(t)


def test_the_exact_step_takes_only_the_optimum(legs_qp):
    """On the optimum's active set the exact step is the solver's answer and is taken; on a guess with every muscle
    free it is not, wherever the optimum holds some muscle at a bound."""
    from lightning_bodyschema.statics.warm_start import exact_step

    G, scale, tau, x_ref, x_lo, x_hi = (a[:40] for a in legs_qp)
    Gx = G * scale[..., None]
    x, code = solve(Gx, tau, x_ref, x_lo, x_hi)
    ok = code == Status.OK.code
    step, held = exact_step(Gx[ok], tau[ok], x_ref[ok], x_lo[ok], x_hi[ok], x[ok], STATIC_TOL_NM)
    assert held.all() and np.abs((step - x[ok]) * scale[ok]).max() <= TENSION_TOL_N
    inside = np.clip(x[ok], x_lo[ok] + 1e-3, x_hi[ok] - 1e-3)
    _, held = exact_step(Gx[ok], tau[ok], x_ref[ok], x_lo[ok], x_hi[ok], inside, STATIC_TOL_NM)
    bound = ((x[ok] <= x_lo[ok]) | (x[ok] >= x_hi[ok])) & (x_lo[ok] < x_hi[ok])
    assert bound.any(1).sum() >= 10 and not held[bound.any(1)].any()
