"""The command QPs (``fault_command`` on ``solvers.solve_box_qp``): proxsuite's answers on one thread or its BatchQP,
the closed form where no bound is active, and least-squares answers that are optimal within their box where no
tension holds the posture."""
from __future__ import annotations

import numpy as np

from lightning_bodyschema.faults.qp import INFEASIBLE_LEARNED, OK, balance_residual_nm, fault_command
from lightning_bodyschema.sim import SpringParams
from lightning_bodyschema.sim.equilibrium import solve_equilibrium_qp

SPRING = SpringParams()  # f_max 150 N
M, N = 8, 3


def _body(batch, seed):
    """Random moment arms (B, M, N) of +-1..3 cm, lengths 0.2 m, and the torque of tensions drawn in [f_lo, f_hi]
    (so every case can be held): returns l_geo, G, tau, the tensions that hold it."""
    rng = np.random.default_rng(seed)
    G = rng.choice([-1.0, 1.0], (batch, M, N)) * rng.uniform(0.01, 0.03, (batch, M, N))
    f_hold = rng.uniform(20.0, 130.0, (batch, M))
    return np.full((batch, M), 0.2), G, -np.einsum("bmn,bm->bn", G, f_hold), f_hold


def _free(batch):
    return np.zeros((batch, M)), np.full((batch, M), 150.0), np.full((batch, M), -np.inf), np.full((batch, M), np.inf)


def test_proxsuite_on_one_or_two_threads_matches_the_newton():
    _, G, tau, _ = _body(64, seed=0)
    f_ref = np.random.default_rng(1).uniform(0.0, 150.0, (64, M))  # many bounds active
    f_newton, ok_newton = solve_equilibrium_qp(G, tau, f_ref, f_hi_n=150.0)
    assert ok_newton.all() and ((f_newton < 1e-6) | (f_newton > 150 - 1e-6)).sum() > 16  # the box shapes the answers
    for threads in (1, 2):  # one QP set up per case in turn; proxsuite's BatchQP + solve_in_parallel
        f_qp, ok_qp = solve_equilibrium_qp(G, tau, f_ref, f_hi_n=150.0, solver="proxqp", num_threads=threads)
        assert ok_qp.all()
        np.testing.assert_allclose(f_qp, f_newton, atol=1e-6, rtol=0)  # proxsuite's eps_abs 1e-9 N m on the balance
        assert (balance_residual_nm(G, tau, f_qp) <= 1e-6).all()


def test_no_active_bound_gives_the_projection_onto_the_balance():
    l_geo, G, tau, f_hold = _body(32, seed=2)
    f_ref = f_hold + np.random.default_rng(3).normal(0.0, 2.0, f_hold.shape)
    # min ||f - f_ref||^2 s.t. -G^T f = tau:  f = f_ref - G (G^T G)^-1 (G^T f_ref + tau)
    lam = np.linalg.solve(np.swapaxes(G, 1, 2) @ G, (np.einsum("bmn,bm->bn", G, f_ref) + tau)[..., None])[..., 0]
    expected = f_ref - np.einsum("bmn,bn->bm", G, lam)
    assert (expected > 1.0).all() and (expected < 149.0).all()  # no bound active
    _, f, status = fault_command(l_geo, G, tau, f_ref, *_free(32), SPRING)
    assert (status == OK).all()
    np.testing.assert_allclose(f, expected, atol=1e-8, rtol=0)


def test_unholdable_cases_get_optimal_least_squares_within_their_box():
    l_geo, G, tau, _ = _body(12, seed=4)
    tau[:6] *= 3.0  # three times the torque of tensions below 130 N: beyond 150 N on these arms
    f_lo, f_hi, l_lo, l_hi = _free(12)
    l_hi[6:, 0] = 0.2 - 0.05  # a jam whose spring pulls k (e^1 - 1) = 1.7 kN > 150 N: bounds cross
    f_ref = np.full((12, M), 75.0)
    l_motor, f, status = fault_command(l_geo, G, tau, f_ref, f_lo, f_hi, l_lo, l_hi, SPRING, reg=1e-6)
    assert (status == INFEASIBLE_LEARNED).all()
    assert np.isfinite(f).all() and np.isfinite(l_motor).all() and (f >= 0).all() and (f <= 150.0).all()
    assert (l_motor <= l_hi).all() and (balance_residual_nm(G[:6], tau[:6], f[:6]) > 1e-3).all()
    assert np.allclose(f[6:, 0], 150.0)  # the crossed jam at the tension closest to its bound
    # KKT of min ||G^T f + tau||^2 / (reg s) + ||f - f_ref||^2 over the box: the gradient [N] points out of the box
    s = np.einsum("bmn,bmn->b", G, G) / M
    grad = np.einsum("bmn,bn->bm", G, np.einsum("bmn,bm->bn", G, f) + tau) / (1e-6 * s)[:, None] + f - f_ref
    box_lo = np.where(np.arange(12)[:, None] >= 6, np.eye(M)[0] * 150.0, 0.0)  # the crossed jam: lo = hi = 150
    pinned = box_lo >= 150.0
    at_lo, at_hi = (f <= box_lo + 1e-3) & ~pinned, (f >= 150.0 - 1e-3) & ~pinned  # at a bound to 1 mN
    assert (at_lo | at_hi)[:6].any(1).all()  # the unholdable torques press tensions against the box
    assert (np.abs(grad[~at_lo & ~at_hi & ~pinned]) <= 1.0).all()  # 1 N of stationarity; bound rows reach 1e5..1e8 N
    assert (grad[at_lo] >= -1.0).all() and (grad[at_hi] <= 1.0).all()


def test_threads_give_the_same_answers():
    """Two threads (proxsuite's BatchQP) answer as one (the dataset's loop) to the QPs' tolerance; run to run only the
    least-squares rows may move, in the last bits, as proxsuite's dense solve of them already did."""
    l_geo, G, tau, _ = _body(40, seed=5)
    tau[::4] *= 3.0  # some unholdable
    args = (l_geo, G, tau, np.full((40, M), 75.0), *_free(40), SPRING)
    one, again, two = fault_command(*args), fault_command(*args), fault_command(*args, num_threads=2)
    ok = one[2] == OK
    assert (one[2] == INFEASIBLE_LEARNED).any() and ok.any()
    np.testing.assert_array_equal(again[2], one[2])
    np.testing.assert_array_equal(two[2], one[2])
    for a, b, c in zip(one[:2], again[:2], two[:2]):
        np.testing.assert_array_equal(b[ok], a[ok])
        np.testing.assert_allclose(b, a, atol=1e-9, rtol=0)
        np.testing.assert_allclose(c, a, atol=1e-7, rtol=0)  # the QPs' tolerance: each preconditioned on its own
