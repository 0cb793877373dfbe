"""The torch dual Newton solves the box QPs exactly: proxsuite's answers to 1e-8 N, KKT conditions, unholdable cases,
the same answer with a fixed iteration count, float64 on CPU from arrays."""
import numpy as np
import pytest
import torch

from lightning_bodyschema.solvers import BoxQP, dual_newton, least_squares_weight, proxsuite_solve

TIGHT = 1e-12  # proxsuite's eps_abs for the reference answers: its own error far below 1e-8 N


def _body(batch, m=12, n=4, seed=0):
    rng = np.random.default_rng(seed)
    G = rng.normal(scale=0.02, size=(batch, m, n))  # moment arms ~2 cm
    f_true = rng.uniform(0.0, 200.0, size=(batch, m))
    tau = -np.einsum("bmn,bm->bn", G, f_true)  # holdable by construction
    return rng, G, tau, np.zeros((batch, m)), np.full((batch, m), 200.0)


def kkt_residuals(problem: BoxQP, f):
    """(stationarity [N], complementarity [N^2], primal infeasibility [N m]) of the equilibrium QP per case: the
    multiplier ``lam`` fitted on the free tensions, ``r = f - f_ref + G lam`` must vanish there, be >= 0 at lower
    and <= 0 at upper bounds; ``|r_i| * distance to the bound`` is the complementarity gap."""
    G, f_ref, lo, hi = problem.G, problem.f_ref_n, problem.lo_n, problem.hi_n
    free = ((f > lo + 1e-7) & (f < hi - 1e-7)).to(G.dtype)
    lam = torch.linalg.lstsq(free.unsqueeze(-1) * G, (free * (f_ref - f)).unsqueeze(-1)).solution.squeeze(-1)
    r = f - f_ref + (G @ lam.unsqueeze(-1)).squeeze(-1)
    wrong_sign = torch.where(f <= lo + 1e-7, (-r).clamp_min(0), torch.where(f >= hi - 1e-7, r.clamp_min(0), r.abs()))
    gap = (r.abs() * torch.minimum(f - lo, hi - f)).amax(1)
    primal = torch.maximum(problem.balance_residual_nm(f), torch.maximum(lo - f, f - hi).amax(1).clamp_min(0))
    return wrong_sign.amax(1), gap, primal


def test_equilibrium_matches_proxsuite_with_active_bounds_and_meets_kkt():
    rng, G, tau, lo, hi = _body(64)
    f_ref = rng.uniform(-100.0, 300.0, size=lo.shape)  # far out of the box: many bounds active
    problem = BoxQP.build(G, tau, f_ref, lo, hi)
    result = dual_newton(*problem[:6])
    f_qp, ok_qp = proxsuite_solve(problem, 10000, eps_abs=TIGHT)
    assert result.converged.all() and ok_qp.all() and result.f.dtype == torch.float64
    assert ((result.f <= problem.lo_n) | (result.f >= problem.hi_n)).sum() > 64  # the active set is exercised
    torch.testing.assert_close(result.f, f_qp, rtol=0.0, atol=1e-8)
    stationarity, complementarity, primal = kkt_residuals(problem, result.f)
    assert stationarity.max() <= 1e-8 and complementarity.max() <= 1e-6 and primal.max() <= 1e-9


def test_a_torque_the_box_cannot_hold_does_not_converge():
    _, G, tau, lo, hi = _body(8, seed=1)
    result = dual_newton(G, 100.0 * tau + 50.0, np.full(lo.shape, 100.0), lo, hi)
    f = result.f.numpy()
    assert not result.converged.any() and np.all((f >= lo) & (f <= hi)) and (result.iterations == 30).all()


def test_least_squares_meets_its_kkt_conditions_and_matches_proxsuite():
    rng, G, tau, lo, hi = _body(32, seed=2)
    tau = 50.0 * tau + rng.normal(scale=20.0, size=tau.shape)  # mostly out of reach
    problem = BoxQP.build(G, tau, 100.0, lo, hi)
    problem = problem.with_weight(least_squares_weight(problem.G, 1e-2))
    result = dual_newton(*problem[:6])
    assert result.converged.all()
    f, f_ref, w = result.f.numpy(), 100.0, problem.w_m2.numpy()
    grad = (f - f_ref) + np.einsum("bmn,bn->bm", G, np.einsum("bmn,bm->bn", G, f) + tau) / w[:, None]
    free = (f > lo + 1e-9) & (f < hi - 1e-9)
    scale = np.abs(grad).max()
    assert np.abs(grad[free]).max() <= 1e-6 * scale  # stationary on the free tensions
    assert grad[f <= lo + 1e-9].min() >= -1e-6 * scale and grad[f >= hi - 1e-9].max() <= 1e-6 * scale
    f_qp, solved = proxsuite_solve(problem, 10000, eps_abs=1e-10)
    assert solved.all()
    torch.testing.assert_close(result.f, f_qp, rtol=0.0, atol=1e-6)  # proxsuite's tolerance on the scaled objective


def test_fixed_iterations_give_the_eager_answer():
    rng, G, tau, lo, hi = _body(48, seed=3)
    tau[:5] = 100.0 * tau[:5] + 50.0  # some never converge
    f_ref = rng.uniform(-100.0, 300.0, size=lo.shape)
    eager = dual_newton(G, tau, f_ref, lo, hi)
    fixed = dual_newton(G, tau, f_ref, lo, hi, fixed_iterations=True)
    torch.testing.assert_close(fixed.f, eager.f, rtol=0.0, atol=1e-9)
    assert torch.equal(fixed.converged, eager.converged) and torch.equal(fixed.iterations, eager.iterations)
    assert not eager.converged[:5].any() and eager.converged[5:].all()


def test_an_empty_batch_and_a_zero_body():
    empty = dual_newton(np.zeros((0, 3, 2)), np.zeros((0, 2)), np.zeros((0, 3)), np.zeros((0, 3)), np.ones((0, 3)))
    assert empty.f.shape == (0, 3) and empty.converged.shape == (0,)
    zero = dual_newton(np.zeros((1, 3, 2)), np.zeros((1, 2)), np.full((1, 3), 0.5), np.zeros((1, 3)), np.ones((1, 3)))
    assert zero.converged.all() and torch.allclose(zero.f, torch.full((1, 3), 0.5, dtype=torch.float64))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_the_newton_runs_on_cuda_and_gives_the_cpu_answer():
    rng, G, tau, lo, hi = _body(64, seed=4)
    f_ref = rng.uniform(-100.0, 300.0, size=lo.shape)
    cpu = dual_newton(G, tau, f_ref, lo, hi)
    cuda = dual_newton(*(torch.as_tensor(x, device="cuda") for x in (G, tau, f_ref, lo, hi)))
    assert cuda.f.device.type == "cuda" and cuda.f.dtype == torch.float64
    torch.testing.assert_close(cuda.f.cpu(), cpu.f, rtol=0.0, atol=1e-8)


def test_the_multiplier_certificate_proves_unholdable_cases_and_never_a_holdable_one():
    rng, G, tau, lo, hi = _body(64, seed=5)
    out = rng.random(64) < 0.5
    tau[out] = 30.0 * tau[out] + rng.normal(scale=5.0, size=tau[out].shape)  # far outside the torque zonotope
    problem = BoxQP.build(G, tau, 100.0, lo, hi)
    result = dual_newton(*problem[:6], infeasible_tol=1e-6)
    f_qp, ok_qp = proxsuite_solve(problem, 10000, eps_abs=TIGHT)
    holdable = ok_qp & (problem.balance_residual_nm(f_qp) <= 1e-6)
    assert holdable.sum() >= 20 and (~holdable).sum() >= 20
    assert not (result.infeasible & holdable).any() and torch.equal(result.converged, holdable)
    assert torch.equal(result.infeasible, ~holdable)  # every unholdable one proven, not run to the step limit
    assert result.iterations[~holdable].max() < 30
    plain = dual_newton(*problem[:6])  # without the test: the same answers where it converges
    assert not plain.infeasible.any()
    torch.testing.assert_close(result.f[holdable], plain.f[holdable], rtol=0.0, atol=0.0)


def test_a_tight_stop_is_met_below_the_rounding_of_the_dual_value():
    """Tensions near 1e5 N: the dual value's rounding (~1e-6) swamps the last steps' gain, yet the Newton reaches a
    stop at the rounding of the residual itself, ~1e-10 N m (a full step on an unchanged free set is taken where it
    lowers the residual). A stop below that rounding is one no solver can promise: the residual ``G^T f + tau`` is a
    sum of M products of up to ~2e4 N m, computed to ``M eps sum_i |G_ij f_i|``, whatever the BLAS kernel."""
    rng, G, tau, lo, hi = _body(32, seed=6)
    problem = BoxQP.build(G, 500.0 * tau, rng.uniform(-5e4, 2e5, size=lo.shape), lo, 500.0 * hi)
    terms_nm = (problem.G.abs() * torch.maximum(problem.lo_n.abs(), problem.hi_n.abs()).unsqueeze(-1)).sum(1).max()
    stop_nm = G.shape[1] * torch.finfo(torch.float64).eps * terms_nm.item()  # ~8e-11 N m, 1e-4 of the dual's rounding
    result = dual_newton(*problem[:6], tol=stop_nm)
    stationarity, _, primal = kkt_residuals(problem, result.f)
    assert result.converged.all() and primal.max() <= stop_nm and stationarity.max() <= 1e-6  # of 1e5 N


def test_the_exact_step_maximises_the_dual_along_the_newton_direction():
    """The closed-form step (sorted kink times) against a fine grid of the dual value along the same rays, with and
    without the least-squares weight and with unbounded box sides."""
    from lightning_bodyschema.solvers import newton

    rng, G, tau, lo, hi = _body(64, seed=7)
    lo[:8] = -np.inf  # an unbounded side: that tension never meets it
    f_ref = rng.uniform(-100.0, 300.0, size=lo.shape)
    grid = torch.logspace(-6, 3, 3001, dtype=torch.float64)
    for w in (0.0, 1e-4):
        problem = tuple(torch.as_tensor(x) for x in (G, tau, f_ref, lo, hi)) + (torch.full((64,), w, dtype=torch.float64),)
        state = newton._evaluate(*problem, torch.as_tensor(rng.normal(scale=1e3, size=(64, 4))))
        step = torch.as_tensor(rng.normal(scale=1e3, size=(64, 4)))
        step = torch.where(((newton._residual(state, problem[5]) * step).sum(1) < 0).unsqueeze(1), -step, step)
        t = newton._exact_step(problem, state, step)
        along = torch.stack([newton._evaluate(*problem, state.lam + s * step).value for s in grid], 1)
        found = ~t.isnan()
        assert found.sum() >= 32 and (t[found] > 0).all()
        at_t = newton._evaluate(*problem, state.lam + torch.nan_to_num(t).unsqueeze(1) * step).value
        best = along.max(1).values
        assert (at_t[found] >= best[found] - 1e-9 * best[found].abs().clamp_min(1.0)).all()
        assert (at_t[found] > state.value[found]).all()  # an ascent


def test_the_traceable_cholesky_solve_is_as_good_as_lu():
    """Newton systems with every tension free: the same solution as LU; with few free tensions (condition ~1e12, the
    ridge alone holds some directions): a residual no worse than LU's backward error allows."""
    from lightning_bodyschema.solvers.newton import _solve_spd

    rng = np.random.default_rng(8)
    G = rng.normal(scale=0.02, size=(32, 12, 7))
    b = torch.as_tensor(rng.normal(size=(32, 7)))
    for free, rtol in ((np.ones((32, 12)), 1e-10), (rng.random((32, 12)) < 0.4, None)):
        gram = np.einsum("bmi,bm,bmj->bij", G, free, G)
        ridge = 1e-12 * np.trace(gram, axis1=1, axis2=2)[:, None, None] / 7 + 1e-300
        A = torch.as_tensor(gram + ridge * np.eye(7))
        x, x_lu = _solve_spd(A, b, traceable=True), _solve_spd(A, b, traceable=False)
        assert torch.isfinite(x).all()
        if rtol is not None:
            torch.testing.assert_close(x, x_lu, rtol=rtol, atol=0.0)
        else:
            residual, residual_lu = ((A @ y.unsqueeze(-1)).squeeze(-1) - b for y in (x, x_lu))
            allowed = 7e-14 * (A.abs().amax((1, 2)) * x_lu.abs().amax(1))  # n eps |A| |x| (some A = 1e-300 I)
            assert (residual.abs().amax(1) <= allowed).all()
            assert (residual_lu.abs().amax(1) <= allowed).all()
