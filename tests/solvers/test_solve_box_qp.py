"""``solve_box_qp``: statuses from the one vocabulary, proxsuite's answers on OK rows, least-squares KKT conditions on
INFEASIBLE rows, the fallbacks, bad input."""
import numpy as np
import pytest
import torch
from physics_checks import rounding_tol

from lightning_bodyschema.errors import BodySchemaInputError
from lightning_bodyschema.solvers import BoxQP, least_squares_weight, proxsuite_solve, solve_box_qp
from lightning_bodyschema.status import Status

OK, INFEASIBLE, NOT_CONVERGED = Status.OK.code, Status.INFEASIBLE.code, Status.NOT_CONVERGED.code
M, N = 8, 3


def _body(batch, seed):
    """Moment arms (B, M, N) of +-1..3 cm and the torque of tensions in [20, 130] N (holdable in [0, 150])."""
    rng = np.random.default_rng(seed)
    G = rng.choice([-1.0, 1.0], (batch, M, N)) * rng.uniform(0.01, 0.03, (batch, M, N))
    return rng, G, -np.einsum("bmn,bm->bn", G, rng.uniform(20.0, 130.0, (batch, M)))


def _least_squares_kkt(problem: BoxQP, f, reg):
    """Max wrong-signed gradient [N] of ``||G^T f + tau||^2 / (reg s) + ||f - f_ref||^2`` over the box (0 at its
    minimiser): stationary where free, pointing out of the box at a bound (to 1 mN)."""
    w = least_squares_weight(problem.G, reg)
    residual = (problem.G.transpose(1, 2) @ f.unsqueeze(-1)).squeeze(-1) + problem.tau_nm
    grad = (problem.G @ residual.unsqueeze(-1)).squeeze(-1) / w.unsqueeze(1) + f - problem.f_ref_n
    at_lo, at_hi = f <= problem.lo_n + 1e-3, f >= problem.hi_n - 1e-3
    pinned = problem.lo_n >= problem.hi_n
    wrong = torch.where(pinned, 0.0, torch.where(at_lo, (-grad).clamp_min(0),
                                                 torch.where(at_hi, grad.clamp_min(0), grad.abs())))
    return wrong.amax(1)


def test_ok_rows_equal_proxsuite_and_unholdable_rows_are_infeasible_least_squares():
    rng, G, tau = _body(96, seed=0)
    tau[:12] *= 3.0  # three times the torque of tensions below 130 N: beyond 150 N on these arms
    hi = np.full((96, M), 150.0)
    hi[12:18, 0], lo = -1.0, np.zeros((96, M))  # crossed bounds
    problem = BoxQP.build(G, tau, rng.uniform(0.0, 150.0, (96, M)), lo, hi)
    solution = solve_box_qp(problem)
    assert solution.f_n.dtype == torch.float64 and solution.status.dtype == torch.int32
    ok = solution.status == OK
    assert (solution.status[12:18] == INFEASIBLE).all() and ok[18:].all()  # crossed; holdable
    assert (solution.status[:12] == INFEASIBLE).sum() >= 8 and set(solution.status[:12].tolist()) <= {OK, INFEASIBLE}
    infeasible = solution.status == INFEASIBLE
    f_qp, solved = proxsuite_solve(problem.take(ok), 10000, eps_abs=1e-12)
    assert solved.all()
    torch.testing.assert_close(solution.f_n[ok], f_qp, rtol=0.0, atol=1e-8)
    assert (problem.balance_residual_nm(solution.f_n)[ok] <= 1e-9).all()
    assert (problem.balance_residual_nm(solution.f_n)[infeasible[:12].nonzero()] > 1e-3).all()
    assert (solution.f_n >= problem.lo_n).all() and (solution.f_n <= problem.hi_n).all()
    # 1 N of stationarity where the gradient's terms reach 1e5..1e8 N
    assert (_least_squares_kkt(problem.take(infeasible), solution.f_n[infeasible], 1e-6) <= 1.0).all()


def test_without_proxsuite_an_unsettled_holdable_case_is_not_converged_and_proxsuite_settles_it():
    rng, G, tau = _body(16, seed=1)
    problem = BoxQP.build(G, tau, rng.uniform(-50.0, 200.0, (16, M)), 0.0, 150.0)
    newton_only = solve_box_qp(problem, max_iter=0, fallback="none")  # the Newton does not move
    assert (newton_only.status != INFEASIBLE).all() and (newton_only.status == NOT_CONVERGED).any()
    assert (newton_only.iterations == 0).all()
    settled = solve_box_qp(problem, max_iter=0)
    assert (settled.status == OK).all()
    torch.testing.assert_close(settled.f_n, solve_box_qp(problem).f_n, rtol=0.0, atol=1e-6)  # proxsuite's eps


def test_the_screen_settles_unholdable_cases_without_proxsuite():
    _, G, tau = _body(24, seed=2)
    problem = BoxQP.build(G, 5.0 * tau, 75.0, 0.0, 150.0)
    screened, full = solve_box_qp(problem, fallback="none"), solve_box_qp(problem)
    assert torch.equal(screened.status, full.status) and (screened.status == INFEASIBLE).sum() > 20
    assert set(screened.status.tolist()) <= {OK, INFEASIBLE}
    assert (screened.f_n >= 0.0).all() and (screened.f_n <= 150.0).all()


def test_without_least_squares_unholdable_rows_keep_the_newtons_tensions_and_the_same_statuses(monkeypatch):
    rng, G, tau = _body(48, seed=4)
    tau[::3] *= 4.0
    problem = BoxQP.build(G, tau, rng.uniform(0.0, 150.0, (48, M)), 0.0, 150.0)
    full = solve_box_qp(problem)
    import lightning_bodyschema.solvers.solve as solve_module

    calls = []
    monkeypatch.setattr(solve_module, "_least_squares", lambda *a: calls.append(a))  # must not be needed
    lean = solve_box_qp(problem, least_squares=False)
    assert not calls and torch.equal(lean.status, full.status) and (full.status == INFEASIBLE).sum() >= 10
    ok = full.status == OK
    assert torch.equal(lean.f_n[ok], full.f_n[ok])
    assert (lean.f_n >= 0.0).all() and (lean.f_n <= 150.0).all()
    assert (problem.balance_residual_nm(lean.f_n)[~ok] > 1e-3).all()


def test_least_squares_problems_and_threads():
    rng, G, tau = _body(40, seed=3)
    tau[::4] *= 3.0
    problem = BoxQP.build(G, tau, 75.0, 0.0, 150.0)
    one, two = solve_box_qp(problem), solve_box_qp(problem, num_threads=2)
    assert torch.equal(one.status, two.status) and (one.status == INFEASIBLE).any() and (one.status == OK).any()
    torch.testing.assert_close(two.f_n, one.f_n, rtol=0.0, atol=1e-7)
    weighted = problem.with_weight(least_squares_weight(problem.G, 1e-6))
    least_squares = solve_box_qp(weighted)
    assert (least_squares.status == OK).all()  # a least-squares problem always has its answer
    assert (_least_squares_kkt(weighted, least_squares.f_n, 1e-6) <= 1.0).all()


def test_bad_rows_and_bad_arguments():
    _, G, tau = _body(4, seed=4)
    G[1, 0, 0] = np.nan
    solution = solve_box_qp(BoxQP.build(G, tau, 75.0, 0.0, 150.0))
    assert solution.status[1] == Status.BAD_INPUT.code and torch.isnan(solution.f_n[1]).all()
    assert (solution.status[[0, 2, 3]] == OK).all()
    with pytest.raises(BodySchemaInputError, match="tau_nm has shape"):
        BoxQP.build(G, tau[:, :2], 75.0, 0.0, 150.0)
    with pytest.raises(BodySchemaInputError, match="G has shape"):
        BoxQP.build(G[0], tau, 75.0, 0.0, 150.0)
    with pytest.raises(BodySchemaInputError, match="w_m2"):
        BoxQP.build(G, tau, 75.0, 0.0, 150.0, w_m2=-1.0)
    with pytest.raises(BodySchemaInputError, match="fallback='cvxpy'"):
        solve_box_qp(BoxQP.build(G, tau, 75.0, 0.0, 150.0), fallback="cvxpy")


def test_the_planar_screen_is_exact_on_known_zonotopes():
    """Two joints: every facet normal is a muscle's torque vector turned by 90 degrees. Torques just inside and just
    outside a box's reach (its zonotope's support along a random direction, plus or minus a margin) are told apart,
    and a holdable torque (the image of a box point) is never called unreachable."""
    from lightning_bodyschema.solvers import outside_torque_reach
    from lightning_bodyschema.solvers.torque_reach import _facet_normals

    rng = np.random.default_rng(4)
    G = torch.as_tensor(rng.normal(0.0, 0.03, (64, 6, 2)))
    lo, hi = torch.zeros(64, 6, dtype=torch.float64), torch.as_tensor(rng.uniform(50.0, 300.0, (64, 6)))
    normals = _facet_normals(G)
    # orthogonal to each torque vector: (-g1 g0 + g0 g1) / |g| (a division, two products, a sum): a few roundings
    # at |G| (~2e-16); a normal turned off the facet by 1 degree is off by |G| / 60 ~ 5e-4
    assert torch.allclose((normals * G).sum(-1), torch.zeros_like(lo), rtol=0, atol=rounding_tol(8, G))
    assert torch.allclose(torch.linalg.vector_norm(normals, dim=-1), torch.ones_like(lo))
    f = lo + (hi - lo) * torch.as_tensor(rng.random((64, 6)))
    held = -(G.transpose(1, 2) @ f.unsqueeze(-1)).squeeze(-1)
    assert not outside_torque_reach(G, held, lo, hi, 1e-6).any()
    # the farthest torque of the box along each case's first facet normal, then 1 N m beyond it
    u = normals[:, 0, :]
    c = -(G @ u.unsqueeze(-1)).squeeze(-1)
    extreme = torch.where(c > 0, hi, lo)
    edge = -(G.transpose(1, 2) @ extreme.unsqueeze(-1)).squeeze(-1)
    assert not outside_torque_reach(G, edge, lo, hi, 1e-6).any()
    assert outside_torque_reach(G, edge + 1.0 * u, lo, hi, 1e-6).all()


@pytest.mark.parametrize("solver", ["proxqp", "qpsolvers"])
def test_another_back_end_agrees_with_the_newton_by_name(solver):
    """``solve_box_qp(problem, solver)``: proxsuite on every case, or a qpsolvers back-end by name (the one installed
    here), gives the Newton's statuses (holdable OK, unholdable and crossed INFEASIBLE) and its tensions on OK rows
    to proxsuite's tolerance; the Solution's residuals are its own."""
    import qpsolvers

    name = "proxqp" if solver == "proxqp" else qpsolvers.available_solvers[0]
    rng, G, tau = _body(24, seed=3)
    tau[:6] *= 3.0  # beyond 150 N on these arms
    hi = np.full((24, M), 150.0)
    hi[6:9, 0] = -1.0  # crossed bounds
    problem = BoxQP.build(G, tau, rng.uniform(0.0, 150.0, (24, M)), 0.0, hi)
    newton, other = solve_box_qp(problem), solve_box_qp(problem, name)
    assert torch.equal(other.status, newton.status) and (other.status[6:9] == INFEASIBLE).all()
    ok = other.status == OK
    assert ok[9:].all() and (other.iterations == 0).all()
    torch.testing.assert_close(other.f_n[ok], newton.f_n[ok], rtol=0.0, atol=1e-6)  # proxsuite's eps 1e-9 N m
    assert (other.balance_residual_nm()[ok] <= 1e-6).all() and (other.box_residual_n() == 0).all()
    assert (newton.balance_residual_nm()[:6][newton.status[:6] == INFEASIBLE] > 1e-3).all()


def test_an_unknown_back_end_is_refused_by_name():
    problem = BoxQP.build(*_body(2, seed=4)[1:], 75.0, 0.0, 150.0)
    with pytest.raises(BodySchemaInputError, match="unknown QP solver 'gurobi'; allowed: 'newton', 'proxqp'"):
        solve_box_qp(problem, "gurobi")


@pytest.mark.parametrize("solver", ["newton", "proxqp"])
def test_every_infeasible_case_carries_a_checked_certificate(solver):
    """An uncrossed INFEASIBLE case holds a unit direction u along which the box's torques fall short of tau by more
    than sqrt(N) times the equilibrium tolerance (checked here by the support function, written out); OK and crossed
    cases hold NaN."""
    rng, G, tau = _body(64, seed=4)
    tau[:24] *= np.linspace(1.2, 4.0, 24)[:, None]  # from barely to far out of reach of tensions up to 150 N
    hi = np.full((64, M), 150.0)
    hi[24:28, 1] = -1.0  # crossed
    problem = BoxQP.build(G, tau, 0.0, 0.0, hi)
    solution = solve_box_qp(problem, solver)
    status, u = solution.status.numpy(), solution.certificate.numpy()
    infeasible = (status == INFEASIBLE) & ~problem.crossed.numpy()
    assert infeasible.sum() >= 12 and (status[24:28] == INFEASIBLE).all() and (status[28:] == OK).all()
    assert set(status.tolist()) <= {OK, INFEASIBLE}  # every case decided: held, or proven out of reach
    assert np.isnan(u[~infeasible]).all() and np.allclose(np.linalg.norm(u[infeasible], axis=1), 1.0)
    c = -np.einsum("bmn,bn->bm", G[infeasible], u[infeasible])
    support = np.where(c > 0, 150.0 * c, 0.0).sum(1)  # max over [0, 150] of u . (-G^T f)
    gap = np.einsum("bn,bn->b", u[infeasible], tau[infeasible]) - support
    assert (gap > np.sqrt(N) * 1e-6).all()
