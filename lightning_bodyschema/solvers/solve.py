"""``solve_box_qp``: every case of a ``BoxQP`` at once, the dual Newton first and the fallbacks on what it leaves.

1. the batched dual Newton (``solvers.newton``) on every case with an uncrossed box;
2. an equilibrium case it leaves unsettled gets the box least squares (``solvers.least_squares``); the torque-reach
   screen (``solvers.torque_reach``, along the least squares' residual among its directions) proves most of those
   without an equilibrium;
3. proxsuite (``fallback="proxsuite"``) on the rest, to ``EQUILIBRIUM_TOL_NM``;
4. a case without a solution keeps the least-squares tensions and the status ``INFEASIBLE``: crossed bounds, a torque
   the screen puts out of the box's reach, or a least-squares residual too large for any balancing tension to exist
   (``_least_squares_proves_no_balance``). ``NOT_CONVERGED`` (with the least-squares tensions) where neither the
   solvers settle a case nor a proof rules it out. A least-squares problem (``w > 0``) the Newton leaves goes to
   proxsuite.

torch on the problem's device; numpy only inside ``solvers.backends``. Prints nothing.
"""
from __future__ import annotations

import torch

from ..errors import BodySchemaInputError
from ..status import Status
from .backends import LS_MAX_ITER, proxsuite_solve
from .least_squares import LS_REG, least_squares_weight
from .newton import NEWTON_MAX_ITER, NEWTON_TOL_NM, dual_newton
from .problem import BoxQP, Solution
from .torque_reach import outside_torque_reach, residual_direction

EQUILIBRIUM_TOL_NM = 1e-6  # a tension vector is an equilibrium if every joint torque residual is below this
FALLBACKS = ("proxsuite", "none")
FALLBACK_MAX_ITER = 2000  # proxsuite's iteration limit per equilibrium QP (a case without a solution runs to it)
_OK, _INFEASIBLE, _NOT_CONVERGED = Status.OK.code, Status.INFEASIBLE.code, Status.NOT_CONVERGED.code


def solve_box_qp(problem: BoxQP, *, tol: float = NEWTON_TOL_NM, max_iter: int = NEWTON_MAX_ITER,
                 fallback: str = "proxsuite", fallback_max_iter: int = FALLBACK_MAX_ITER, ls_reg: float = LS_REG,
                 num_threads: int = 1) -> Solution:
    """The ``Solution`` of every case of ``problem`` (module docstring).

    Args:
        tol, max_iter: the dual Newton's stop [N m] and step limit.
        fallback: ``"proxsuite"`` or ``"none"`` (the Newton, the screen and the least squares only).
        fallback_max_iter: proxsuite's iteration limit per equilibrium QP.
        ls_reg: the dimensionless weight of ``||f - f_ref||^2`` in the least squares of a case without a solution.
        num_threads: proxsuite's threads (1: one QP per case in turn; more: its ``BatchQP``).
    """
    _check_options(fallback, max_iter, fallback_max_iter, num_threads)
    f = torch.minimum(torch.maximum(problem.f_ref_n, problem.lo_n), problem.hi_n)
    f[problem.bad_input] = torch.nan
    status = torch.full((problem.batch,), _NOT_CONVERGED, dtype=torch.int32, device=f.device)
    status[problem.bad_input] = Status.BAD_INPUT.code
    iterations = torch.zeros_like(status)
    run = ~problem.bad_input & ~problem.crossed
    if bool(run.any()):
        newton = dual_newton(*problem.take(run)[:6], tol=tol, max_iter=max_iter)
        f[run], iterations[run] = newton.f, newton.iterations
        status[run] = torch.where(newton.converged, _OK, _NOT_CONVERGED).to(torch.int32)
    unsettled = status == _NOT_CONVERGED
    for rows, settle in ((unsettled & (problem.w_m2 > 0), _least_squares_rest),
                         (unsettled & (problem.w_m2 == 0), _no_equilibrium_yet)):
        if bool(rows.any()):
            f[rows], status[rows] = settle(problem.take(rows), f[rows], fallback, fallback_max_iter, ls_reg,
                                           num_threads)
    return Solution(f, status, iterations)


def _check_options(fallback, max_iter, fallback_max_iter, num_threads):
    if fallback not in FALLBACKS:
        raise BodySchemaInputError(f"fallback={fallback!r}; allowed: {list(FALLBACKS)}")
    for name, value, least in (("max_iter", max_iter, 0), ("fallback_max_iter", fallback_max_iter, 1),
                               ("num_threads", num_threads, 1)):
        if isinstance(value, bool) or int(value) != value or value < least:
            raise BodySchemaInputError(f"{name}={value!r}; allowed: an integer >= {least}")


def _least_squares_rest(problem: BoxQP, f, fallback, fallback_max_iter, ls_reg, num_threads):
    """``(f, status)`` of least-squares cases the Newton left: proxsuite's answer, OK where it solves."""
    status = torch.full_like(problem.w_m2, _NOT_CONVERGED, dtype=torch.int32)
    if fallback == "proxsuite":
        f, solved = proxsuite_solve(problem, LS_MAX_ITER, num_threads)
        status = torch.where(solved, _OK, _NOT_CONVERGED).to(torch.int32)
    return f, status


def _least_squares(problem: BoxQP, fallback: str, num_threads: int):
    """``(f, settled)`` of the least-squares ``problem``: the dual Newton, proxsuite on what it leaves."""
    result = dual_newton(*problem[:6])
    f, settled = result.f, result.converged
    if fallback == "proxsuite" and not bool(settled.all()):
        f[~settled], settled[~settled] = proxsuite_solve(problem.take(~settled), LS_MAX_ITER, num_threads)
    return f, settled


def _no_equilibrium_yet(problem: BoxQP, f, fallback, fallback_max_iter, ls_reg, num_threads):
    """``(f, status)`` of equilibrium cases the Newton left (crossed ones included): steps 2 to 4 of the module
    docstring."""
    f_ls, settled = _least_squares(problem.with_weight(least_squares_weight(problem.G, ls_reg)), fallback,
                                   num_threads)
    outside = problem.crossed.clone()
    if not bool(outside.all()):  # crossed bounds need no screen
        rows = problem.take(~outside)
        outside[~outside] = outside_torque_reach(rows.G, rows.tau_nm, rows.lo_n, rows.hi_n, EQUILIBRIUM_TOL_NM,
                                                 residual_direction(rows.G, rows.tau_nm, f_ls[~outside]))
    status = torch.where(outside, _INFEASIBLE, _NOT_CONVERGED).to(torch.int32)
    f = f_ls.clone()
    if fallback == "proxsuite" and not bool(outside.all()):
        rows = problem.take(~outside)
        f_qp, solved = proxsuite_solve(rows, fallback_max_iter, num_threads)
        ok = solved & (rows.balance_residual_nm(f_qp) <= EQUILIBRIUM_TOL_NM)
        f[~outside] = torch.where(ok.unsqueeze(1), f_qp, f_ls[~outside])
        status[~outside] = torch.where(ok, _OK, _NOT_CONVERGED).to(torch.int32)
    proven = settled & _least_squares_proves_no_balance(problem, f_ls, least_squares_weight(problem.G, ls_reg))
    status = torch.where((status == _NOT_CONVERGED) & proven, _INFEASIBLE, status).to(torch.int32)
    return f, status


def _least_squares_proves_no_balance(problem: BoxQP, f_ls, w_m2) -> torch.Tensor:
    """(B,) True where the least-squares minimiser ``f_ls`` (weight ``w_m2``) shows that no tension in the box
    balances the torque: a balancing f would give the objective ``||f - f_ref||^2 <= R^2`` (R the farthest point of
    the box from f_ref), so ``||G^T f_ls + tau||^2 <= w R^2`` whenever one exists."""
    reach = torch.maximum(problem.hi_n - problem.f_ref_n, problem.f_ref_n - problem.lo_n)
    radius = torch.linalg.vector_norm(reach, dim=1)
    residual = (problem.G.transpose(1, 2) @ f_ls.unsqueeze(-1)).squeeze(-1) + problem.tau_nm
    return torch.linalg.vector_norm(residual, dim=1) > w_m2.sqrt() * radius + EQUILIBRIUM_TOL_NM
