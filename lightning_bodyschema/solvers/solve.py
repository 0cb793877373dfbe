"""``solve_box_qp(problem, solver)``: every case of a ``BoxQP`` at once, by the back-end ``solver`` (qpsolvers'
``solve_problem`` style): ``"newton"`` (the default, below), ``"proxqp"`` (proxsuite on every case) or any solver
qpsolvers has installed (one call per equilibrium case). The ``Solution`` holds the problem and gives its residuals.

``"newton"``: the dual Newton first and the fallbacks on what it leaves:

1. the batched dual Newton (``solvers.newton``) on every case with an uncrossed box, ``FIRST_PASS`` steps; an
   equilibrium case whose multiplier proves that no tension balances its torque stops there, ``INFEASIBLE``;
2. an equilibrium case it leaves unsettled gets the box least squares (``solvers.least_squares``); that residual and
   the torque-reach screen (``solvers.torque_reach``, along the least squares' residual among its directions) prove
   most of those without an equilibrium;
3. the rest of the Newton's steps (to ``max_iter``, from its start) on the others, then proxsuite
   (``fallback="proxsuite"``) on what they leave, to ``EQUILIBRIUM_TOL_NM``;
4. a case without a solution keeps the least-squares tensions (``least_squares=False``: the Newton's, where step 1
   proved it) and the status ``INFEASIBLE``: crossed bounds, the Newton's proof, a torque
   the screen puts out of the box's reach, or a least-squares residual too large for any balancing tension to exist
   (``_least_squares_proves_no_balance``). ``NOT_CONVERGED`` (with the least-squares tensions) where neither the
   solvers settle a case nor a proof rules it out. A least-squares problem (``w > 0``) the Newton leaves goes to
   proxsuite.
5. every equilibrium case left ``INFEASIBLE`` or ``NOT_CONVERGED`` in an uncrossed box: ``INFEASIBLE`` exactly where
   a Farkas-type certificate is found and checked (``separating_direction``; ``Solution.certificate``), else
   ``NOT_CONVERGED``. So ``INFEASIBLE`` always carries its proof, and ``NOT_CONVERGED`` never hides one.

Another back-end: its answer on every case with valid input (crossed ones in their lowered box); ``OK`` where it
solved the case and, for an equilibrium case, balanced the torque to ``EQUILIBRIUM_TOL_NM`` in an uncrossed box;
else ``INFEASIBLE`` where the box crosses or a checked certificate proves it (step 5), else ``NOT_CONVERGED``.

Both stop at the rounding of the residual they measure where it exceeds their tolerance (``newton._unsettled``,
``backends.UNIT_ROUNDOFF``): a case whose weak muscles pull at a lifted activation cap of 1000 has terms of 4e4 N m
in a torque of 7 and cannot be balanced to 1e-12 N m in float64, only to the last bits of those terms.

torch on the problem's device; numpy only inside ``solvers.backends``. Prints nothing.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import torch

from ..errors import BodySchemaInputError
from ..status import Status
from .backends import LS_MAX_ITER, check_qp_solver, proxsuite_solve, qpsolvers_solve
from .least_squares import LS_REG, box_least_squares, least_squares_weight
from .newton import FEW_CASES, NEWTON_MAX_ITER, NEWTON_TOL_NM, dual_newton, host_count
from .problem import BoxQP, Solution, separation_gap_nm
from .torque_reach import outside_torque_reach, residual_direction, screen_normals

EQUILIBRIUM_TOL_NM = 1e-6  # a tension vector is an equilibrium if every joint torque residual is below this
FALLBACKS = ("proxsuite", "none")
FIRST_PASS = 10  # dual Newton steps before the cases it leaves are screened (holdable ones rarely need more)
FALLBACK_MAX_ITER = 2000  # proxsuite's iteration limit per equilibrium QP (a case without a solution runs to it)
CERTIFY_REGS = (1e-9, 1e-12)  # the box least squares' weights (``least_squares``' reg) tried for a certificate
_OK, _INFEASIBLE, _NOT_CONVERGED = Status.OK.code, Status.INFEASIBLE.code, Status.NOT_CONVERGED.code


class _Options(NamedTuple):
    tol: float
    max_iter: int
    fallback: str
    fallback_max_iter: int
    ls_reg: float
    num_threads: int
    fallback_eps_abs: float | None
    least_squares: bool
    certify: bool


def solve_box_qp(problem: BoxQP, solver: str = "newton", *, tol: float = NEWTON_TOL_NM,
                 max_iter: int = NEWTON_MAX_ITER, fallback: str = "proxsuite",
                 fallback_max_iter: int = FALLBACK_MAX_ITER, ls_reg: float = LS_REG, num_threads: int = 1,
                 fallback_eps_abs: float | None = None, least_squares: bool = True, certify: bool = True) -> Solution:
    """The ``Solution`` of every case of ``problem`` by the back-end ``solver`` (module docstring).

    Args:
        solver: ``"newton"``, ``"proxqp"`` or a qpsolvers solver name (equilibrium cases only); anything else is a
            ``BodySchemaInputError`` naming the installed ones. The options below apply to ``"newton"``; proxsuite
            (``"proxqp"``, the Newton's fallback) takes ``fallback_max_iter``, ``num_threads`` and
            ``fallback_eps_abs``.
        tol, max_iter: the dual Newton's stop [N m] and step limit (a case the screen rules out after
            ``FIRST_PASS`` steps stops there).
        fallback: ``"proxsuite"`` or ``"none"`` (the Newton, the screen and the least squares only).
        fallback_max_iter: proxsuite's iteration limit per equilibrium QP.
        ls_reg: the dimensionless weight of ``||f - f_ref||^2`` in the least squares of a case without a solution.
        num_threads: proxsuite's threads (1: one QP per case in turn; more: its ``BatchQP``).
        fallback_eps_abs: proxsuite's absolute tolerance on an equilibrium QP (None: ``backends.QP_EPS_ABS``); set it
            with a tight ``tol`` so that the cases proxsuite settles are as exact as the Newton's.
        least_squares: False: an equilibrium case proven without a solution keeps the Newton's tensions instead of
            the least squares' (not solved for it: for a caller that discards those rows).
        certify: False: no certificate search (step 5): ``INFEASIBLE`` where the steps above proved it, without
            ``Solution.certificate`` (for a caller that solves those cases again in a wider box, as static
            optimization does above full activation).
    """
    options = _Options(tol, max_iter, fallback, fallback_max_iter, ls_reg, num_threads, fallback_eps_abs,
                       least_squares, certify)
    _check_options(options)
    if check_qp_solver(solver) != "newton":
        return _certified(problem, *_external(problem, solver, options), options.certify)
    f, status, iterations, direction = _solvable_first_pass(problem, tol, max_iter)
    any_least, any_equilibrium, every_equilibrium = _left(status, problem.w_m2)
    if any_least:
        least = (status == _NOT_CONVERGED) & (problem.w_m2 > 0)
        f[least], status[least], iterations[least] = _least_squares_rest(problem.take(least), iterations[least],
                                                                         options)
    if every_equilibrium:  # no gather (a single case that needs more than the first pass)
        return _certified(problem, *_no_equilibrium_yet(problem, f, status == _INFEASIBLE, iterations, options),
                          options.certify, direction)
    if any_equilibrium:  # the least-squares rows above have w > 0: not among these
        rows = ((status == _NOT_CONVERGED) | (status == _INFEASIBLE)) & (problem.w_m2 == 0)
        f[rows], status[rows], iterations[rows] = _no_equilibrium_yet(problem.take(rows), f[rows],
                                                                      status[rows] == _INFEASIBLE, iterations[rows],
                                                                      options)
    # no equilibrium case left unsettled or proven: nothing to certify (the least-squares rows have w > 0)
    return _certified(problem, f, status, iterations, options.certify and any_equilibrium, direction)


def _certified(problem: BoxQP, f, status, iterations, certify: bool, direction=None) -> Solution:
    """The ``Solution`` with ``INFEASIBLE`` only where a checked certificate proves it (``Solution.certificate``,
    ``separating_direction``) or the box crosses: an equilibrium case claimed ``INFEASIBLE`` without one becomes
    ``NOT_CONVERGED`` (nothing proved it), one left ``NOT_CONVERGED`` with one becomes ``INFEASIBLE``.
    ``direction (B, N)``: the Newton's own proofs (``NewtonResult.direction``, NaN where none), tried first.
    ``certify`` False: no case needs a certificate (or none is asked for); every certificate NaN."""
    certificate = torch.full_like(problem.tau_nm, torch.nan)
    claim = _claims(problem, status) if certify else None
    if claim is None:
        return Solution(f, status, iterations, problem, certificate)
    certificate[claim] = separating_direction(problem.take(claim), f[claim],
                                              None if direction is None else direction[claim])
    proven = ~torch.isnan(certificate[:, 0])
    status = torch.where(claim, torch.where(proven, _INFEASIBLE, _NOT_CONVERGED), status).to(torch.int32)
    return Solution(f, status, iterations, problem, certificate)


def _claims(problem: BoxQP, status):
    """(B,) bool: the equilibrium cases in an uncrossed box whose status claims no solution (``INFEASIBLE`` or
    ``NOT_CONVERGED``), the ones ``_certified`` settles by a certificate; None where there is none (a few cases read
    as host lists first, as ``_left``: most rows at batch 1 are crossed boxes or solved ones)."""
    if status.shape[0] <= FEW_CASES and not any(
            code in (_INFEASIBLE, _NOT_CONVERGED) and not crossed and w == 0
            for code, crossed, w in zip(status.tolist(), problem.crossed.tolist(), problem.w_m2.tolist())):
        return None
    claim = ((status == _INFEASIBLE) | (status == _NOT_CONVERGED)) & ~problem.crossed & (problem.w_m2 == 0)
    return claim if _some(claim) else None


def separating_direction(problem: BoxQP, f_n, direction=None) -> torch.Tensor:
    """(B, N) per equilibrium case a unit direction u along which no tension in the box reaches ``tau``: its
    ``separation_gap_nm`` exceeds ``sqrt(N) EQUILIBRIUM_TOL_NM`` (checked here); NaN where none is found. Tried: the
    residual of the case's tensions ``f_n``, the screen's directions, then the residuals of box least squares whose
    balance weighs ever more (``CERTIFY_REGS``): their tensions near the torque zonotope's point nearest ``-tau``, whose
    residual is the sharpest separating direction there is. ``direction (B, N)``: a candidate of the caller's own
    (the Newton's multiplier direction; NaN where none), tried with the others."""
    candidates = [residual_direction(problem.G, problem.tau_nm, f_n).unsqueeze(1), screen_normals(problem.G)]
    if direction is not None:
        candidates.append(torch.nan_to_num(direction, nan=0.0).unsqueeze(1))  # a zero direction proves nothing
    direction, found = _best_direction(problem, torch.cat(candidates, 1))
    for reg in CERTIFY_REGS:
        if _every(found):
            break
        rest = problem.take(~found)
        least = box_least_squares(rest.G, rest.tau_nm, rest.f_ref_n, rest.lo_n, rest.hi_n, reg)
        more, more_found = _best_direction(rest, residual_direction(rest.G, rest.tau_nm, least.f).unsqueeze(1))
        direction[~found], found[~found] = more, more_found
    return torch.where(found.unsqueeze(1), direction, torch.nan)


def _best_direction(problem: BoxQP, normals):
    """``(u (B, N), found (B,))``: of the directions ``normals (B, K, N)`` and their opposites, the one with the
    largest separation gap, and whether that gap proves the case without an equilibrium."""
    normals = torch.cat([normals, -normals], 1)
    gap = separation_gap_nm(problem.G, problem.tau_nm, problem.lo_n, problem.hi_n, normals)
    best = gap.argmax(1)
    u = normals[torch.arange(len(best), device=best.device), best]
    return u, gap.amax(1) > math.sqrt(problem.G.shape[2]) * EQUILIBRIUM_TOL_NM


def _external(problem: BoxQP, solver: str, options: _Options):
    """``(f, status, iterations)`` of another back-end than the Newton (module docstring): proxsuite or qpsolvers'
    ``solver`` on the cases with valid input (NaN and ``BAD_INPUT`` on the others)."""
    f = torch.full_like(problem.f_ref_n, torch.nan)
    status = torch.full_like(problem.crossed, Status.BAD_INPUT.code, dtype=torch.int32)
    good = ~problem.bad_input
    rows = problem.take(good)
    if solver == "proxqp":
        f[good], solved = proxsuite_solve(rows, options.fallback_max_iter, options.num_threads,
                                          options.fallback_eps_abs)
    elif _some(rows.w_m2 > 0):
        raise BodySchemaInputError(f"solver={solver!r} solves equilibrium QPs (w_m2 = 0) only; least squares: "
                                   "'newton' or 'proxqp'")
    else:
        f[good], solved = qpsolvers_solve(rows, solver)
    status[good] = _external_codes(rows, f[good], solved)
    return f, status, torch.zeros_like(status)


def _external_codes(problem: BoxQP, f, solved) -> torch.Tensor:
    """(B,) int32: OK where ``solved`` (and, for an equilibrium case, balanced to ``EQUILIBRIUM_TOL_NM`` in an
    uncrossed box), else INFEASIBLE where the box crosses or the torque-reach screen proves it, else NOT_CONVERGED."""
    equilibrium = problem.w_m2 == 0
    ok = solved & ~problem.crossed & (~equilibrium | (problem.balance_residual_nm(f) <= EQUILIBRIUM_TOL_NM))
    outside = problem.crossed.clone()
    screen = ~ok & equilibrium & ~outside
    if _some(screen):
        rows = problem.take(screen)
        outside[screen] = outside_torque_reach(rows.G, rows.tau_nm, rows.lo_n, rows.hi_n, EQUILIBRIUM_TOL_NM)
    return torch.where(ok, _OK, torch.where(outside, _INFEASIBLE, _NOT_CONVERGED)).to(torch.int32)


def _left(status, w_m2) -> list:
    """``[any_least, any_equilibrium, every_equilibrium]``: whether the first pass left a least-squares case
    unsettled, and an equilibrium case unsettled or proven without a solution (some, every). One host read: a few
    cases' codes and weights as lists (cheaper than the masks' dispatch), else the three reductions stacked."""
    if status.shape[0] <= FEW_CASES:
        pairs = list(zip(status.tolist(), w_m2.tolist()))
        equilibrium = [code in (_NOT_CONVERGED, _INFEASIBLE) and w == 0 for code, w in pairs]
        return [any(code == _NOT_CONVERGED and w > 0 for code, w in pairs), any(equilibrium), all(equilibrium)]
    unsettled = status == _NOT_CONVERGED
    least = unsettled & (w_m2 > 0)
    equilibrium = (unsettled | (status == _INFEASIBLE)) & (w_m2 == 0)
    return torch.stack([least.any(), equilibrium.any(), equilibrium.all()]).tolist()


def _every(mask) -> bool:
    """``bool(mask.all())`` of a (B,) bool tensor (``newton.host_count``: a list read for a few cases)."""
    return host_count(mask) == mask.shape[0]


def _some(mask) -> bool:
    """``bool(mask.any())`` of a (B,) bool tensor (``newton.host_count``)."""
    return host_count(mask) > 0


def _solvable_first_pass(problem: BoxQP, tol: float, max_iter: int):
    """``(f, status, iterations, direction)``: ``_first_pass`` on the cases with valid input and an uncrossed box;
    the others NaN and ``BAD_INPUT``, or the box's point nearest f_ref and ``NOT_CONVERGED`` (crossed: settled
    later), and no direction (NaN)."""
    skip = problem.bad_input | problem.crossed
    if not _some(skip):  # every case: no gather
        return _first_pass(problem, tol, max_iter)
    f = torch.minimum(torch.maximum(problem.f_ref_n, problem.lo_n), problem.hi_n)
    f = torch.where(problem.bad_input.unsqueeze(1), torch.nan, f)
    status = torch.where(problem.bad_input, Status.BAD_INPUT.code, _NOT_CONVERGED).to(torch.int32)
    iterations, direction = torch.zeros_like(status), torch.full_like(problem.tau_nm, torch.nan)
    if not _every(skip):
        run = (~skip).nonzero().squeeze(1)
        f[run], status[run], iterations[run], direction[run] = _first_pass(problem.take(run), tol, max_iter)
    return f, status, iterations, direction


def _first_pass(problem: BoxQP, tol: float, max_iter: int):
    """``(f, status, iterations, direction)`` after the dual Newton's first ``FIRST_PASS`` steps: OK where it
    converged, INFEASIBLE where its multiplier proves an equilibrium case without a solution (``dual_newton``'s
    ``infeasible_tol``, at ``EQUILIBRIUM_TOL_NM``), with that multiplier's direction."""
    newton = dual_newton(*problem[:6], tol=tol, max_iter=min(max_iter, FIRST_PASS),
                         infeasible_tol=max(tol, EQUILIBRIUM_TOL_NM))
    return newton.f, _codes(newton.converged, newton.infeasible), newton.iterations, newton.direction


def _codes(converged, infeasible) -> torch.Tensor:
    """(B,) int32: OK where ``converged``, else INFEASIBLE where ``infeasible``, else NOT_CONVERGED (a few cases
    from host lists: one small copy instead of two selections and a cast)."""
    if converged.shape[0] <= FEW_CASES:
        codes = [_OK if ok else _INFEASIBLE if no else _NOT_CONVERGED
                 for ok, no in zip(converged.tolist(), infeasible.tolist())]
        return torch.tensor(codes, dtype=torch.int32, device=converged.device)
    status = torch.where(converged, _OK, torch.where(infeasible, _INFEASIBLE, _NOT_CONVERGED))
    return status.to(torch.int32)


def _check_options(options: _Options):
    if options.fallback not in FALLBACKS:
        raise BodySchemaInputError(f"fallback={options.fallback!r}; allowed: {list(FALLBACKS)}")
    for name, least in (("max_iter", 0), ("fallback_max_iter", 1), ("num_threads", 1)):
        value = getattr(options, name)
        if isinstance(value, bool) or int(value) != value or value < least:
            raise BodySchemaInputError(f"{name}={value!r}; allowed: an integer >= {least}")


def _newton_rest(problem: BoxQP, options: _Options):
    """``(f, converged, iterations)``: the dual Newton to ``max_iter`` on cases its first ``FIRST_PASS`` steps left
    (from the same start: the answer of one run to ``max_iter``)."""
    result = dual_newton(*problem[:6], tol=options.tol, max_iter=options.max_iter)
    return result.f, result.converged, result.iterations


def _least_squares_rest(problem: BoxQP, iterations, options: _Options):
    """``(f, status, iterations)`` of least-squares cases the Newton's first pass left: the rest of its steps,
    proxsuite on what they leave."""
    f, settled, iterations = _newton_rest(problem, options)
    if options.fallback == "proxsuite" and not _every(settled):
        f[~settled], settled[~settled] = proxsuite_solve(problem.take(~settled), LS_MAX_ITER, options.num_threads)
    return f, torch.where(settled, _OK, _NOT_CONVERGED).to(torch.int32), iterations


def _least_squares(problem: BoxQP, options: _Options):
    """``(f, settled)`` of the least-squares ``problem``: the dual Newton, proxsuite on what it leaves."""
    result = dual_newton(*problem[:6])
    f, settled = result.f, result.converged
    if options.fallback == "proxsuite" and not _every(settled):
        f[~settled], settled[~settled] = proxsuite_solve(problem.take(~settled), LS_MAX_ITER, options.num_threads)
    return f, settled


def _proofs(problem: BoxQP, f_first, proven, options: _Options):
    """``(f_ls, outside)``: the least-squares tensions (``f_first`` on proven cases with ``least_squares=False``)
    and where no equilibrium exists: crossed, ``proven``, or shown by the least squares."""
    outside = problem.crossed | proven
    if options.least_squares:
        return _least_squares_proof(problem, options, outside)
    f_ls, need = f_first.clone(), ~outside
    if _some(need):
        f_ls[need], outside[need] = _least_squares_proof(problem.take(need), options, outside[need])
    return f_ls, outside


def _least_squares_proof(problem: BoxQP, options: _Options, outside):
    """``(f_ls, outside | shown)``: the least-squares tensions and where no equilibrium exists: ``outside`` (B,)
    (known already), or shown by the least squares."""
    w_ls = least_squares_weight(problem.G, options.ls_reg)
    f_ls, settled = _least_squares(problem.with_weight(w_ls), options)
    if _every(outside):  # nothing left to prove
        return f_ls, outside
    return f_ls, outside | (settled & _least_squares_proves_no_balance(problem, f_ls, w_ls))


def _no_equilibrium_yet(problem: BoxQP, f_first, proven, iterations, options: _Options):
    """``(f, status, iterations)`` of equilibrium cases the Newton's first pass left or ``proven`` without a
    solution (crossed ones included): steps 2 to 4 of the module docstring, the rest of the Newton's steps on the
    cases nothing rules out first."""
    f_ls, outside = _proofs(problem, f_first, proven, options)
    if _every(outside):  # every case proven without a solution (crossed ones, one at batch 1): nothing to solve
        return f_ls, torch.full_like(iterations, _INFEASIBLE), iterations
    rows = problem.take(~outside)
    outside[~outside] = outside_torque_reach(rows.G, rows.tau_nm, rows.lo_n, rows.hi_n, EQUILIBRIUM_TOL_NM,
                                             residual_direction(rows.G, rows.tau_nm, f_ls[~outside]))
    status = torch.where(outside, _INFEASIBLE, _NOT_CONVERGED).to(torch.int32)
    f, todo = f_ls.clone(), ~outside
    if _some(todo):
        f_newton, converged, iterations[todo] = _newton_rest(problem.take(todo), options)
        f[todo] = torch.where(converged.unsqueeze(1), f_newton, f[todo])
        status[todo] = torch.where(converged, _OK, _NOT_CONVERGED).to(torch.int32)
        todo[todo.clone()] = ~converged
    if options.fallback == "proxsuite" and _some(todo):
        rows = problem.take(todo)
        f_qp, solved = proxsuite_solve(rows, options.fallback_max_iter, options.num_threads, options.fallback_eps_abs)
        ok = solved & (rows.balance_residual_nm(f_qp) <= EQUILIBRIUM_TOL_NM)
        f[todo] = torch.where(ok.unsqueeze(1), f_qp, f_ls[todo])
        status[todo] = torch.where(ok, _OK, _NOT_CONVERGED).to(torch.int32)
    return f, status, iterations


def _least_squares_proves_no_balance(problem: BoxQP, f_ls, w_m2) -> torch.Tensor:
    """(B,) True where the least-squares minimiser ``f_ls`` (weight ``w_m2``) shows that no tension in the box
    balances the torque: a balancing f would give the objective ``||f - f_ref||^2 <= R^2`` (R the farthest point of
    the box from f_ref), so ``||G^T f_ls + tau||^2 <= w R^2`` whenever one exists."""
    reach = torch.maximum(problem.hi_n - problem.f_ref_n, problem.f_ref_n - problem.lo_n)
    radius = torch.linalg.vector_norm(reach, dim=1)
    residual = (problem.G.transpose(1, 2) @ f_ls.unsqueeze(-1)).squeeze(-1) + problem.tau_nm
    return torch.linalg.vector_norm(residual, dim=1) > w_m2.sqrt() * radius + EQUILIBRIUM_TOL_NM
