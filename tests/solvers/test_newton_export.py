"""The torch dual Newton traces: ``torch.export`` of a module calling it with ``fixed_iterations`` answers as eager."""
import numpy as np
import torch

from lightning_bodyschema.solvers.newton import dual_newton
from physics_checks import rounding_tol


class _Command(torch.nn.Module):
    def forward(self, G, tau, f_ref, lo, hi):
        return dual_newton(G, tau, f_ref, lo, hi, 0.0, max_iter=4, fixed_iterations=True)


def _problem(batch, m=6, n=2, seed=0):
    rng = np.random.default_rng(seed)
    G = rng.normal(scale=0.02, size=(batch, m, n))
    tau = -np.einsum("bmn,bm->bn", G, rng.uniform(0.0, 100.0, (batch, m)))
    tau[0] = 50.0  # no tension in the box holds this one: it must stay not converged
    f_ref = rng.uniform(-50.0, 150.0, (batch, m))  # many active bounds
    return tuple(torch.tensor(x) for x in (G, tau, f_ref, np.zeros((batch, m)), np.full((batch, m), 100.0)))


def test_exported_fixed_iteration_newton_gives_the_eager_answer():
    args = _problem(16)
    program = torch.export.export(_Command(), args)
    exported = program.module()(*_problem(16, seed=1))
    eager = dual_newton(*_problem(16, seed=1), 0.0, max_iter=4)
    torch.testing.assert_close(exported.f, eager.f, rtol=0.0, atol=1e-9)
    assert torch.equal(exported.converged, eager.converged) and torch.equal(exported.iterations, eager.iterations)
    assert eager.converged[1:].all() and not eager.converged[0]
    assert len(set(eager.iterations.tolist())) > 2  # cases stop at different steps: the masking is exercised
    assert exported.f.dtype == torch.float64


def test_the_exported_newton_stops_early_and_calls_no_linalg_solver():
    """The traced graph is one while_loop (it ends once every case has settled) whose line search runs its trials
    after t = 1 under a cond, and whose Newton systems are solved by a Cholesky factor and substitutions of
    elementwise operations: no linalg solver, eigensolver or cholesky_solve (AOTInductor would run the first through
    its proxy executor; the last costs more than the arithmetic at these sizes)."""
    program = torch.export.export(_Command(), _problem(16))
    text = program.graph_module.print_readable(print_output=False)
    assert "higher_order.while_loop" in text and "higher_order.cond" in text
    assert not any(name in text for name in ("linalg_solve", "solve_ex", "lu_factor", "eigvalsh", "cholesky"))


_SOLVE_ROUNDINGS = 4096  # the traced Newton step against the eager one (condition of the dual Hessian ~1e3)


def test_the_traced_step_searches_where_the_full_step_is_rejected():
    """The first Newton step of the traced path (the trials after t = 1 under a cond) equals the eager one on every
    case, among them cases whose full step is rejected (the cond's searched branch)."""
    from lightning_bodyschema.solvers import newton

    G, tau, f_ref, lo, hi = _problem(16)
    w = torch.zeros(16, dtype=torch.float64)
    problem = (G, tau, f_ref, lo, hi, w)
    lam, shift = newton._start(G, tau, f_ref, w, traceable=True)
    state = newton._evaluate(*problem, lam)
    residual = newton._residual(state, w)
    step = newton._newton_direction(problem, state, residual, shift, traceable=True)
    full = newton._evaluate(*problem, state.lam + step)
    rejected = full.value < state.value + newton._ARMIJO * (residual * step).sum(1)
    assert 0 < int(rejected.sum()) < 16
    active = torch.ones(16, dtype=torch.bool)
    traced = newton._traced_newton_step(problem, state, residual, shift, newton._lipschitz(problem), active)
    eager = newton._newton_step(problem, state, residual, shift)
    assert not torch.equal(traced.lam[rejected], full.lam[rejected])  # searched, not the full step
    scale = state.lam.abs().amax() + step.abs().amax()  # [N rad/m] the size of the multipliers in play
    # the Newton system solved by another kernel (elementwise substitutions vs cholesky_solve): its roundings,
    # amplified by the system's condition, at the multipliers' scale; a wrong trial or branch moves lam by O(scale)
    torch.testing.assert_close(traced.lam, eager.lam, rtol=0.0, atol=rounding_tol(_SOLVE_ROUNDINGS, scale))
    torch.testing.assert_close(traced.f, eager.f, rtol=0.0, atol=1e-9)
