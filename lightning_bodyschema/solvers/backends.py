"""The external QP solvers behind the dual Newton: proxsuite (the fallback and the reference) and qpsolvers.

The one numpy boundary of ``solvers``: every function here takes a ``BoxQP`` (tensors on any device), moves what
it solves to the CPU and returns float64 tensors on the problem's device. proxsuite sets its QPs up one at a time
(one per case on one thread; through its ``BatchQP`` and ``solve_in_parallel`` on more); its answers agree with
each other to its tolerance and may differ in the last bits from run to run.
"""
from __future__ import annotations

import numpy as np
import proxsuite
import torch

from ..errors import BodySchemaInputError
from .problem import BoxQP

QP_EPS_ABS = 1e-9  # proxsuite's tolerance on the equilibrium QP [N m]: far below the equilibrium tolerance
# the least-squares QP: stationarity to 1 mN of its scaled objective (the rows are best efforts, never commands)
LS_EPS_N, LS_MAX_ITER = 1e-3, 1000
_SOLVED = proxsuite.proxqp.QPSolverOutput.PROXQP_SOLVED
# proxsuite's relative tolerance on an equilibrium QP of M tensions: (M + 2) u of the residuals' own terms, the
# rounding of evaluating them. Its absolute one alone (1e-12 N m) lies below that rounding where the terms are large
# (activations near a lifted cap of 1000 on moment arms of 40 N m: terms of 4e4 N m), and no iterate then meets it.
UNIT_ROUNDOFF = np.finfo(np.float64).eps / 2


def _dense_qp(n, n_eq, eps_abs, max_iter, qps=None, eps_rel=0.0):
    """A proxsuite dense QP of n variables, n_eq equalities and an n-row box (built in the BatchQP ``qps`` if given),
    with the tolerances and iteration limit set. ``eps_rel`` > 0 also tightens proxsuite's primal infeasibility
    test to it: at its default (1e-4) a feasible case whose weak muscles must pull at a lifted cap of 1000 is called
    infeasible within ten iterations (an infeasible one runs to ``max_iter`` instead; it is never trusted here)."""
    qp = proxsuite.proxqp.dense.QP(n, n_eq, n) if qps is None else qps.init_qp_in_place(n, n_eq, n)
    qp.settings.eps_abs, qp.settings.eps_rel = eps_abs, eps_rel
    if eps_rel > 0:
        qp.settings.eps_primal_inf = eps_rel
    qp.settings.max_iter, qp.settings.verbose = max_iter, False
    return qp


def _proxsuite(H, g, A, b, lo, hi, eps_abs: float, max_iter: int, num_threads: int, eps_rel: float = 0.0):
    """``argmin 0.5 x^T H x + g^T x  s.t.  A x = b,  lo <= x <= hi`` per case (arrays: H (B, n, n), g (B, n), A
    (B, n_eq, n) and b (B, n_eq) or both None, lo, hi (B, n)): ``x (B, n)`` as proxsuite returns it and
    ``solved (B,)`` (proxsuite's status SOLVED)."""
    batch, n = g.shape
    n_eq = 0 if A is None else A.shape[1]
    eye, x, solved = np.eye(n), np.zeros((batch, n)), np.zeros(batch, dtype=bool)
    parallel = proxsuite.proxqp.dense.BatchQP(batch) if num_threads > 1 else None
    qp = _dense_qp(n, n_eq, eps_abs, max_iter, eps_rel=eps_rel) if parallel is None else None
    for k in range(batch):  # proxsuite sets its QPs up one at a time; the box as n inequality rows
        case = qp if qp is not None else _dense_qp(n, n_eq, eps_abs, max_iter, parallel, eps_rel)
        case.init(H[k], g[k], None if A is None else A[k], None if A is None else b[k], eye, lo[k], hi[k])
        if parallel is None:
            case.solve()
            x[k], solved[k] = case.results.x, case.results.info.status == _SOLVED
    if parallel is not None and batch:
        proxsuite.proxqp.dense.solve_in_parallel(num_threads=int(num_threads), qps=parallel)
        for k in range(batch):
            results = parallel.get(k).results
            x[k], solved[k] = results.x, results.info.status == _SOLVED
    return x, solved


def _cpu(problem: BoxQP) -> tuple[np.ndarray, ...]:
    """G, tau, f_ref, lo, hi, w as float64 arrays (the boundary: ``.cpu()`` first)."""
    return tuple(x.detach().cpu().numpy() for x in problem[:6])


def _back(problem: BoxQP, x: np.ndarray, solved: np.ndarray):
    """``(f (B, M) clipped into the box, solved (B,))`` as tensors on the problem's device."""
    f = torch.as_tensor(x, dtype=torch.float64, device=problem.G.device)
    return torch.minimum(torch.maximum(f, problem.lo_n), problem.hi_n), torch.as_tensor(solved, device=f.device)


def proxsuite_solve(problem: BoxQP, max_iter: int, num_threads: int = 1, eps_abs: float | None = None):
    """``(f (B, M), solved (B,))`` of every case by proxsuite: the equilibrium QP where ``w = 0`` (to
    ``QP_EPS_ABS``) within ``max_iter`` iterations, else the least squares, its objective divided by w (to
    ``LS_EPS_N`` within ``LS_MAX_ITER``); ``eps_abs`` replaces either tolerance.
    A problem mixing both kinds is solved as two batches."""
    least_squares = problem.w_m2 > 0
    f, solved = problem.f_ref_n.clone(), torch.zeros_like(least_squares)
    for rows, solve in ((~least_squares, _equilibrium), (least_squares, _least_squares)):
        if bool(rows.any()):
            f[rows], solved[rows] = solve(problem.take(rows), max_iter, num_threads, eps_abs)
    return f, solved


def _equilibrium(problem: BoxQP, max_iter: int, num_threads: int, eps_abs):
    G, tau, f_ref, lo, hi, _ = _cpu(problem)
    m = G.shape[1]
    x, solved = _proxsuite(np.broadcast_to(np.eye(m), (len(G), m, m)), -f_ref, -np.swapaxes(G, 1, 2), tau, lo, hi,
                           QP_EPS_ABS if eps_abs is None else eps_abs, max_iter, num_threads,
                           eps_rel=(m + 2) * UNIT_ROUNDOFF)
    return _back(problem, x, solved)


def _least_squares(problem: BoxQP, max_iter: int, num_threads: int, eps_abs):
    G, tau, f_ref, lo, hi, w = _cpu(problem)
    H = G @ np.swapaxes(G, 1, 2) / w[:, None, None] + np.eye(G.shape[1])  # (B, M, M)
    g = np.einsum("bmn,bn->bm", G, tau) / w[:, None] - f_ref
    x, solved = _proxsuite(H, g, None, None, lo, hi, LS_EPS_N if eps_abs is None else eps_abs,
                           LS_MAX_ITER, num_threads)
    return _back(problem, x, solved)


def check_qp_solver(solver: str) -> str:
    """``solver``, or the error naming it: neither ``"newton"``, ``"proxqp"`` nor installed in qpsolvers."""
    if solver in ("newton", "proxqp"):
        return solver
    import qpsolvers

    if solver not in qpsolvers.available_solvers:
        raise BodySchemaInputError(
            f"unknown QP solver {solver!r}; allowed: 'newton', 'proxqp' or one qpsolvers has installed: "
            f"{sorted(qpsolvers.available_solvers)}")
    return solver


def qpsolvers_solve(problem: BoxQP, solver: str):
    """``(f (B, M), solved (B,))`` of the equilibrium QP of every case through qpsolvers' ``solver`` (one call
    per case), so a user can plug in any QP solver it knows."""
    import qpsolvers

    G, tau, f_ref, lo, hi, _ = _cpu(problem)
    x, solved = np.zeros(f_ref.shape), np.zeros(len(G), dtype=bool)
    for b in range(len(G)):
        answer = qpsolvers.solve_qp(np.eye(G.shape[1]), -f_ref[b], A=-G[b].T, b=tau[b], lb=lo[b], ub=hi[b],
                                    solver=check_qp_solver(solver))
        if answer is not None:
            x[b], solved[b] = answer, True
    return _back(problem, x, solved)
