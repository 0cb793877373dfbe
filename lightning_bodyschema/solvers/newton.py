"""Batched dual semismooth Newton for the box QPs: every case at once in torch (float64, any device).

Per case (``G (M, N)`` [m/rad], ``tau (N,)`` [N m], tensions ``f (M,)`` [N] in the box ``lo <= f <= hi``)::

    min_f  1/2 ||f - f_ref||^2 + 1/(2 w) ||G^T f + tau||^2        w > 0: the least-squares answer
    min_f  1/2 ||f - f_ref||^2   s.t.  G^T f + tau = 0             w = 0: the equilibrium / command QP

The Hessian in f is the identity, so for a multiplier ``lam (N,)`` [N rad/m] the box minimiser is a clip:

    (1) f(lam) = clip(f_ref - G lam, lo, hi)
    (2) F(lam) = G^T f(lam) + tau - w lam = 0        (the gradient of the concave dual; its root is the optimum)
    (3) F'(lam) = -(G^T D G + w I),  D = diag(lo <= f_ref - G lam <= hi)   (the tensions the clip leaves)

Newton steps on (2) with (3) and a line search on the dual value, a concave piecewise-quadratic function: the first
of the trial steps ``t = 1``, the exact maximiser along the step, ``1/2, ..., 2^(1 - LINE_SEARCH_HALVINGS)`` that
meets Armijo's condition (or, for ``t = 1``, keeps the free set and lowers ``max |F|``: there the dual is the
quadratic the step maximises, and Armijo's test may fail on the rounding of the dual value alone), else a gradient
step ``F / L`` (``L`` a bound on the dual gradient's Lipschitz constant), which always ascends.
A case whose residual is not below ``tol`` after ``max_iter`` steps (an equilibrium that the box
cannot hold has no root) is reported as not converged; after the last step, a residual within the rounding of
computing it counts as below ``tol`` (``_unsettled``: on a badly scaled case no iterate can do better).

``fixed_iterations=True`` runs the steps on every case at once, masked where a case has converged, in a
``torch.while_loop`` that ends when every case has converged or after ``max_iter`` steps; the trials after ``t = 1``
run on every case under a ``torch.cond``, in the steps where some running case does not take the full step: no host
synchronisation and no data-dependent shape, so ``torch.export`` can trace it (and AOTInductor compiles it without
its proxy executor: the Newton systems are solved by a Cholesky factor made of elementwise operations); the answers
are the eager ones to rounding. torch only.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import torch

from .problem import separation_gap_nm

NEWTON_MAX_ITER = 30
# the stop [N m] of the equilibrium solves: far below EQUILIBRIUM_TOL_NM, a converged row is an equilibrium
NEWTON_TOL_NM = 1e-9
# trial steps 1, 1/2, ..., 1/2048 (after the exact maximiser); where none is accepted, the gradient step (ascent)
LINE_SEARCH_HALVINGS = 12
_ARMIJO = 1e-4
_UNIT_ROUNDOFF = torch.finfo(torch.float64).eps / 2
_RIDGE = 1e-12  # of the mean eigenvalue of G^T G, added to the Newton system (G may be 0)
# the steps before which the infeasibility test runs (and after the last): from the fourth on a batch, where a proof
# spares the proven cases' steps; from the sixth on a few cases, where each test costs about a step's overhead
_CERTIFY_STEPS, _CERTIFY_STEPS_FEW, FEW_CASES = frozenset(range(3, 64, 2)), frozenset(range(5, 64, 2)), 8


class NewtonResult(NamedTuple):
    """``f (B, M)`` [N] in the box; ``converged (B,)`` bool: every ``|F_n(lam)| <= tol``, or after the last step
    within the rounding of computing it (``_unsettled``; then f balances ``tau`` to that plus ``w |lam|``);
    ``iterations (B,)`` int32: the Newton steps each case took; ``infeasible (B,)`` bool: proven to have no tension
    in the box that balances ``tau`` to ``infeasible_tol`` (``dual_newton``); ``direction (B, N)``: the unit
    multiplier direction that proved it (a Farkas-type certificate, ``problem.separation_gap_nm``), NaN elsewhere."""

    f: torch.Tensor
    converged: torch.Tensor
    iterations: torch.Tensor
    infeasible: torch.Tensor
    direction: torch.Tensor


class _State(NamedTuple):
    """The iterate of a (sub)batch: multiplier, tensions, free mask, dual value, ``G^T f + tau``."""

    lam: torch.Tensor
    f: torch.Tensor
    free: torch.Tensor
    value: torch.Tensor
    balance: torch.Tensor


def host_count(mask: torch.Tensor) -> int:
    """``int(mask.sum())`` of a (B,) bool tensor: at most ``FEW_CASES`` flags are read to the host as a list (about a
    tenth of the sum's and the read's dispatch at batch 1; one read either way)."""
    return sum(mask.tolist()) if mask.shape[0] <= FEW_CASES else int(mask.sum())


def _f64(x, device=None) -> torch.Tensor:
    if isinstance(x, torch.Tensor) and x.dtype == torch.float64 and (device is None or x.device == device):
        return x  # what as_tensor returns, without a dispatch
    return torch.as_tensor(x, dtype=torch.float64, device=device)


class _Views(NamedTuple):
    """The views of a problem that every evaluation takes, made once by an eager run (each view is a dispatch, a
    few microseconds at batch 1): ``G^T (B, N, M)``, ``f_ref (B, M, 1)``, ``tau (B, N, 1)``, ``w (B, 1)``."""

    Gt: torch.Tensor
    f_ref: torch.Tensor
    tau: torch.Tensor
    w: torch.Tensor


def _views(G, tau, f_ref, w) -> _Views:
    return _Views(G.transpose(1, 2), f_ref.unsqueeze(-1), tau.unsqueeze(-1), w.unsqueeze(1))


def _evaluate(G, tau, f_ref, lo, hi, w, lam, views: _Views | None = None) -> _State:
    """The state at ``lam``: (1), the free mask of (3) and the dual value (the Lagrangian at f(lam)); ``views``
    (``_views`` of the same problem) made here when not given."""
    Gt, f_ref_col, tau_col, w_col = _views(G, tau, f_ref, w) if views is None else views
    free_f = torch.baddbmm(f_ref_col, G, lam.unsqueeze(-1), alpha=-1.0).squeeze(-1)
    f = torch.clamp(free_f, lo, hi)
    balance = torch.baddbmm(tau_col, Gt, f.unsqueeze(-1)).squeeze(-1)
    gap = f - f_ref
    value = 0.5 * torch.linalg.vecdot(gap, gap) + torch.linalg.vecdot(lam, torch.addcmul(balance, w_col, lam,
                                                                                         value=-0.5))
    return _State(lam, f, f == free_f, value, balance)  # free: the clip left it (a tension at a bound is either)


def _select(take, new: _State, old: _State) -> _State:
    """Per case ``new`` where ``take`` (B,) else ``old``."""
    return _State(*(torch.where(take.view(-1, *([1] * (a.dim() - 1))), a, b) for a, b in zip(new, old)))


def _trials(problem, state: _State, step, slope, t):
    """``(accepted (B,), trial state)``: the first of the steps ``t (B, K)`` along ``step`` that meets Armijo's
    condition on the dual value, all trials evaluated at once."""
    G, tau, f_ref, lo, hi, w = problem
    lam = state.lam.unsqueeze(1) + t.unsqueeze(-1) * step.unsqueeze(1)  # (B, K, N)
    free_f = torch.baddbmm(f_ref.unsqueeze(1), lam, G.transpose(1, 2), alpha=-1.0)  # (B, K, M)
    f = torch.clamp(free_f, lo.unsqueeze(1), hi.unsqueeze(1))
    balance = torch.baddbmm(tau.unsqueeze(1), f, G)  # (B, K, N)
    gap = f - f_ref.unsqueeze(1)
    value = 0.5 * (gap * gap).sum(2) + (lam * (balance - 0.5 * w.view(-1, 1, 1) * lam)).sum(2)
    take = value >= state.value.unsqueeze(1) + _ARMIJO * t * slope.unsqueeze(1)  # (B, K)
    take[:, 0] |= _settled_step(state, f[:, 0] == free_f[:, 0], balance[:, 0] - w.unsqueeze(1) * lam[:, 0], w)
    first = torch.argmax(take.to(torch.int32), dim=1)  # the largest accepted step (0 where none is)
    return take.any(1), _State(*(_pick(x, first) for x in (lam, f, f == free_f, value, balance)))


def _settled_step(state: _State, free, residual, w) -> torch.Tensor:
    """(B,) True where a full step kept the free set and lowered the residual ``max |F|``: on an unchanged free set
    the dual is the quadratic the step maximises, so it ascends even where its gain is below the rounding of the
    dual value (Armijo's test then fails on rounding alone)."""
    return (free == state.free).all(1) & (residual.abs().amax(1) < _residual(state, w).abs().amax(1))


def _pick(x: torch.Tensor, first: torch.Tensor) -> torch.Tensor:
    """``x[b, first[b]]`` for ``x (B, K, ...)``."""
    index = first.view(-1, 1, *([1] * (x.dim() - 2))).expand(-1, 1, *x.shape[2:])
    return x.gather(1, index).squeeze(1)


def _exact_step(problem, state: _State, step) -> torch.Tensor:
    """(B,) the maximiser ``t > 0`` of the dual along ``step`` (NaN where it is not positive). Along the ray the dual
    is a concave piecewise quadratic: its derivative ``d(t) = step . F(lam + t step)`` is piecewise linear and
    decreasing (``_derivative_at_kinks``); the root lies on the first piece where d falls to 0 (past the last kink,
    the slope is ``-w |step|^2``: no root where ``w = 0``)."""
    G, tau, f_ref, lo, hi, w = problem
    u = torch.baddbmm(f_ref.unsqueeze(-1), G, state.lam.unsqueeze(-1), alpha=-1.0).squeeze(-1)  # (B, M)
    v = (G @ step.unsqueeze(-1)).squeeze(-1)
    curvature = w * (step * step).sum(1)  # of the last piece
    slope0 = (step * tau).sum(1) - w * (step * state.lam).sum(1)
    start, d = _derivative_at_kinks(u, v, lo, hi, state.f, curvature, slope0)
    falls = torch.isfinite(start) & (d <= 0)
    k1 = torch.argmax(falls.to(torch.int32), 1, keepdim=True)  # the first kink where d <= 0
    last = torch.isfinite(start).sum(1, keepdim=True) - 1
    k0 = torch.where(falls.any(1, keepdim=True), (k1 - 1).clamp_min(0), last)
    t0, t1 = start.gather(1, k0).squeeze(1), start.gather(1, k1).squeeze(1)
    # d at the bracket's ends summed over the tensions (not the cumulative sums): the root to the last bit
    d0, d1 = ((torch.clamp(u - v * t.unsqueeze(1), lo, hi) * v).sum(1) + slope0 - curvature * t for t in (t0, t1))
    inside = t0 + d0 * (t1 - t0) / (d0 - d1)
    beyond = t0 + d0 / curvature  # past the last kink (inf where w = 0: rejected below)
    root = torch.where(falls.any(1), torch.where(d0 > d1, inside, t0), beyond)
    return torch.where((root > 0) & torch.isfinite(root), root, torch.full_like(root, torch.nan))


def _derivative_at_kinks(u, v, lo, hi, f, curvature, slope0):
    """``(start, d)`` (B, 2M + 1): ``t = 0`` and the kinks along the ray sorted (+inf past the last), and the dual's
    derivative ``d`` there. Tension m is ``clamp(u_m - v_m t, lo_m, hi_m)`` (``f`` at t = 0): free, adding
    ``-v_m^2`` to the slope of d, between the two times it meets a bound; sorting those times gives each piece's
    slope (a cumulative sum of the changes) and d at each kink (a cumulative sum of slope times length)."""
    moving = v != 0
    at_lo, at_hi = (u - lo) / v, (u - hi) / v  # where tension m meets each bound (+-inf at an infinite bound)
    enter = torch.where(moving, torch.minimum(at_lo, at_hi), -torch.inf)  # free on (enter, leave)
    leave = torch.where(moving, torch.maximum(at_lo, at_hi), torch.inf)
    v2 = v * v
    slope = -(v2 * ((enter <= 0) & (leave > 0))).sum(1, keepdim=True) - curvature.unsqueeze(1)
    times = torch.cat([enter, leave], 1)  # (B, 2M): entering lowers the slope by v^2, leaving raises it
    events = (times > 0) & torch.isfinite(times)
    times, order = torch.sort(torch.where(events, times, torch.inf), 1)
    change = torch.where(events, torch.cat([-v2, v2], 1), torch.zeros_like(times)).gather(1, order)
    before = torch.cat([slope, slope + torch.cumsum(change, 1)], 1)  # the slope on each piece
    start = torch.cat([torch.zeros_like(slope), times], 1)  # each piece's first time
    length = torch.where(torch.isfinite(start[:, 1:]), start[:, 1:] - start[:, :-1], torch.zeros_like(times))
    d = (f * v).sum(1, keepdim=True) + slope0.unsqueeze(1)
    return start, torch.cat([d, d + torch.cumsum(before[:, :-1] * length, 1)], 1)


def _lipschitz(problem) -> torch.Tensor:
    """(B,) a bound on the dual gradient's Lipschitz constant, the largest eigenvalue of ``G^T G`` plus ``w``: the
    Frobenius norm of ``G^T G`` (at least its largest eigenvalue; elementwise, so it traces without a solver call)."""
    G, w = problem[0], problem[5]
    return torch.linalg.matrix_norm(G.transpose(1, 2) @ G) + w


def _gradient_step(problem, state: _State, residual, lipschitz=None) -> _State:
    """The state after the ascent step ``residual / L``, ``L`` the dual gradient's Lipschitz constant (computed
    here when not given)."""
    lipschitz = _lipschitz(problem) if lipschitz is None else lipschitz
    return _evaluate(*problem, state.lam + residual / lipschitz.unsqueeze(1))


def _line_search(problem, state: _State, residual, step, views=None) -> _State:
    """Armijo's condition on the dual value along the Newton ``step``: the first accepted of ``t = 1``, the exact
    maximiser along the step (``_exact_step``), ``1/2, ..., 2^(1 - LINE_SEARCH_HALVINGS)``: ``t = 1`` on every case,
    the others on the cases it fails. Where no trial is accepted (a nearly singular Newton system), a gradient step,
    which always ascends (the dual is concave with a Lipschitz-continuous gradient). ``views``: the problem's
    ``_Views`` (every case of the run)."""
    slope = (residual * step).sum(1)  # the dual's directional derivative: ascent for a Newton step
    out = _evaluate(*problem, state.lam + step, views)
    fails = out.value < state.value + _ARMIJO * slope  # the cases the full step fails
    failing = host_count(fails)
    if failing == 0:
        return out
    every = failing == step.shape[0]  # every case (one, at batch 1): no gather, no indices
    rows = None if every else fails.nonzero().squeeze(1)
    items = (problem, state, step, slope, residual, out)
    sub_problem, sub_state, sub_step, sub_slope, sub_residual, sub_out = items if every else _rows(items, rows)
    w = sub_problem[5]
    settled = _settled_step(sub_state, sub_out.free, _residual(sub_out, w), w)
    if host_count(settled) == settled.shape[0]:
        return out
    accepted, trial = _trials(sub_problem, sub_state, sub_step, sub_slope,
                              _trial_steps(sub_problem, sub_state, sub_step))
    trial = _select(settled, sub_out, trial)
    if host_count(accepted | settled) < accepted.shape[0]:
        trial = _select(accepted | settled, trial, _gradient_step(sub_problem, sub_state, sub_residual))
    return trial if every else _State(*(x.index_copy(0, rows, y) for x, y in zip(out, trial)))


def _traced_newton_step(problem, state: _State, residual, shift, lipschitz, active) -> _State:
    """``_newton_step``'s answers without a host read, for ``torch.export``: the full step where it meets Armijo's
    condition or settles (``_settled_step``), else the other trials and the gradient step; those are evaluated under
    ``torch.cond`` only when some ``active`` case needs them (near the answer a Newton step is taken whole)."""
    w = problem[5]
    step = _newton_direction(problem, state, residual, shift, True)
    slope = (residual * step).sum(1)
    out = _evaluate(*problem, state.lam + step)
    whole = (out.value >= state.value + _ARMIJO * slope) | _settled_step(state, out.free, _residual(out, w), w)
    tensors = (*problem, *state, step, slope, residual, lipschitz, whole, *out)
    return _State(*torch.cond((whole | ~active).all(), _whole_step, _searched_step, tensors))


def _whole_step(*tensors):
    return tuple(t.clone() for t in tensors[-5:])  # a branch's outputs may not alias its inputs


def _searched_step(*tensors):
    """``_traced_newton_step``'s line search: the exact and halved trials, else the gradient step, where the full
    step ``out`` is not ``whole``."""
    problem, state, (step, slope, residual, lipschitz, whole), out = tensors[:6], _State(*tensors[6:11]), \
        tensors[11:16], _State(*tensors[16:])
    accepted, trial = _trials(problem, state, step, slope, _trial_steps(problem, state, step))
    trial = _select(accepted, trial, _gradient_step(problem, state, residual, lipschitz))
    return tuple(_select(whole, out, trial))


def _trial_steps(problem, state: _State, step) -> torch.Tensor:
    """(B, K) the trial steps after ``t = 1`` in order: the exact maximiser, ``1/2, 1/4, ...``."""
    halvings = 0.5 ** torch.arange(1, LINE_SEARCH_HALVINGS, dtype=step.dtype, device=step.device)
    batch = step.shape[0]  # not len(): a symbolic batch size stays symbolic under torch.export
    return torch.cat([_exact_step(problem, state, step).unsqueeze(1), halvings.expand(batch, -1)], 1)


def _rows(items, rows):
    """Each tensor, tuple of tensors or ``_State`` of ``items`` at the cases ``rows``."""
    return tuple(x[rows] if isinstance(x, torch.Tensor) else _State(*(y[rows] for y in x)) if isinstance(x, _State)
                 else tuple(y[rows] for y in x) for x in items)


def _residual(state: _State, w, w_col=None) -> torch.Tensor:
    """(2): ``F(lam) = G^T f + tau - w lam`` (B, N) [N m] (``w_col``: w as (B, 1), made here when not given)."""
    return torch.addcmul(state.balance, w.unsqueeze(1) if w_col is None else w_col, state.lam, value=-1.0)


def _newton_step(problem, state: _State, residual, shift, views=None) -> _State:
    """One Newton step on (2) (``residual``) with (3) (``shift``: ``w I`` and the ridge) and the line search, for
    the (sub)batch ``problem`` (``views``: the problem's ``_Views``, made once on every case)."""
    step = _newton_direction(problem, state, residual, shift, False, None if views is None else views.Gt)
    return _line_search(problem, state, residual, step, views)


def _newton_direction(problem, state: _State, residual, shift, traceable: bool, Gt=None) -> torch.Tensor:
    """(B, N) the Newton step of (2) with (3) (``Gt``: ``G^T``, made here when not given)."""
    G = problem[0]
    Gt = G.transpose(1, 2) if Gt is None else Gt
    hessian = torch.baddbmm(shift, Gt, G * state.free.unsqueeze(-1))  # (3); a bool factor is 0 or 1
    return _solve_spd(hessian, residual, traceable)


def _solve_spd(A: torch.Tensor, b: torch.Tensor, traceable: bool) -> torch.Tensor:
    """``A^-1 b`` (B, N) for symmetric positive definite ``A (B, N, N)``: an LU solve, or (``traceable``) a Cholesky
    factor built column by column and its two triangular substitutions, all elementwise operations on (B,) columns
    (N is static), which AOTInductor fuses into a few kernels: ``linalg`` solvers have no C shim (its proxy executor
    would run them), and ``torch.cholesky_solve`` is a library call that copies its operands and checks its factor."""
    if not traceable:
        return torch.linalg.solve_ex(A, b.unsqueeze(-1))[0].squeeze(-1)
    n = A.shape[-1]
    rows = torch.arange(n, device=A.device)
    columns = []  # columns[j] (B, N): column j of the factor L, zero above the diagonal
    for j in range(n):
        v = A[:, :, j]
        for k in range(j):
            v = v - columns[k] * columns[k][:, j:j + 1]
        pivot = torch.sqrt(torch.clamp(v[:, j:j + 1], min=1e-300))
        columns.append(torch.where(rows >= j, v / pivot, torch.zeros_like(v)))
    y = []  # L y = b, forward
    for j in range(n):
        y.append((b[:, j] - sum((columns[k][:, j] * y[k] for k in range(j)), torch.zeros_like(b[:, j])))
                 / columns[j][:, j])
    x = [None] * n  # L^T x = y, backward
    for j in reversed(range(n)):
        x[j] = (y[j] - sum((columns[j][:, k] * x[k] for k in range(j + 1, n)), torch.zeros_like(y[j])))
        x[j] = x[j] / columns[j][:, j]
    return torch.stack(x, 1)


def _start(G, tau, f_ref, w, traceable: bool = False, views: _Views | None = None):
    """``(lam_0, shift)``: the unconstrained multiplier and ``w I`` plus a tiny ridge (G may be 0); ``views``
    (``_views``) made here when not given."""
    n = G.shape[2]
    views = _views(G, tau, f_ref, w) if views is None else views
    gram = torch.bmm(views.Gt, G)  # what @ dispatches to for (B, N, M) @ (B, M, N), without its reshapes
    eye = torch.eye(n, dtype=G.dtype, device=G.device)
    trace = torch.diagonal(gram, dim1=1, dim2=2).sum(1)
    ridge = _RIDGE * torch.clamp(trace / n, min=1e-30).view(-1, 1, 1) * eye
    rhs = torch.bmm(views.Gt, views.f_ref).squeeze(-1) + tau
    lam = _solve_spd(gram + ridge, rhs, traceable)
    return lam, ridge + w.view(-1, 1, 1) * eye


def _separated(problem, lam, tol_nm: float):
    """``(separated (B,), u (B, N))``: True where the multiplier's direction ``u = lam / |lam|`` proves that no
    tension in the box balances ``tau`` to ``tol_nm`` on every joint (an equilibrium case, ``w = 0``). Along u the
    dual grows by ``u . tau - max_f u . (-G^T f)`` per unit of ``|lam|``: where that is positive the dual is unbounded
    and the QP has no solution (``problem.separation_gap_nm``; exact, a case with a solution is never marked)."""
    G, tau, _, lo, hi, w = problem
    u = lam / torch.clamp(torch.linalg.vector_norm(lam, dim=1, keepdim=True), min=1e-300)
    gap = separation_gap_nm(G, tau, lo, hi, u.unsqueeze(1)).squeeze(1)
    return (gap > math.sqrt(G.shape[2]) * tol_nm) & (w == 0), u


def _unsettled(problem, state: _State, residual, tol: float) -> torch.Tensor:
    """(B,) True where some joint's residual ``|F_n|`` exceeds both ``tol`` and the rounding floor of evaluating it
    in float64 (u the unit roundoff): a free tension ``f_m = f_ref_m - sum_n G_mn lam_n`` errs by up to ``(N + 1) u
    (|f_ref_m| + sum_n |G_mn lam_n|)``, and ``F_n = sum_m G_mn f_m + tau_n - w lam_n`` adds ``(M + 2) u (sum_m |G_mn
    f_m| + |tau_n| + w |lam_n|)``. A smaller residual is zero to the arithmetic. On a badly scaled case (activations
    near a lifted cap of 1000 on moment arms of 40 N m, the multiplier large where the free muscles are weak) that
    floor lies above a tolerance of 1e-12 N m, which no iterate can then meet: the steps run to their limit (they
    do not leave the floor) and the case counts as converged. Tested once, after the last step."""
    G, tau, f_ref, _, _, w = problem
    m, n = G.shape[1], G.shape[2]
    abs_G = G.abs()
    abs_Gt = abs_G.transpose(1, 2)
    free_f = torch.baddbmm(f_ref.abs().unsqueeze(-1), abs_G, state.lam.abs().unsqueeze(-1)).squeeze(-1)
    error_f = (n + 1) * _UNIT_ROUNDOFF * free_f * state.free  # a clipped tension is a bound: exact
    terms = torch.baddbmm(tau.abs().unsqueeze(-1), abs_Gt, state.f.abs().unsqueeze(-1)).squeeze(-1)
    floor = (m + 2) * _UNIT_ROUNDOFF * torch.addcmul(terms, w.unsqueeze(1), state.lam.abs())
    floor = torch.baddbmm(floor.unsqueeze(-1), abs_Gt, error_f.unsqueeze(-1)).squeeze(-1)
    return ((residual.abs() > tol) & (residual.abs() > floor)).any(1)


def dual_newton(G, tau, f_ref, lo, hi, w=0.0, tol: float = NEWTON_TOL_NM, max_iter: int = NEWTON_MAX_ITER,
                fixed_iterations: bool = False, infeasible_tol: float | None = None) -> NewtonResult:
    """The problem of the module docstring for ``G (B, M, N)``, ``tau (B, N)``, ``f_ref, lo, hi (B, M)`` (float64
    tensors on one device, or arrays), ``w`` a scalar or ``(B,)`` (0: the equilibrium QP), ``lo <= hi``.
    ``fixed_iterations``: masked steps in a ``torch.while_loop`` (traceable by ``torch.export``) until every case
    settles or ``max_iter``; the eager answer to rounding. ``infeasible_tol`` [N m]: before steps 4, 6, 8, ... (6,
    8, ... on at most ``FEW_CASES`` cases; with ``fixed_iterations`` not before) and after the last, an equilibrium case
    whose multiplier proves that no tension balances ``tau`` to it (``_separated``) stops, ``infeasible`` (None: no
    such test, ``infeasible`` all False)."""
    G = _f64(G)
    tau, f_ref, lo, hi = (_f64(x, G.device) for x in (tau, f_ref, lo, hi))
    batch = G.shape[0]
    w = _f64(w, G.device)
    w = w if w.shape == (batch,) else w.expand(batch)  # a BoxQP's (B,) weight as it is: no expand to dispatch
    infeasible = torch.zeros(batch, dtype=torch.bool, device=G.device)
    direction = torch.full_like(tau, torch.nan)
    if batch == 0 and not fixed_iterations:
        return NewtonResult(f_ref.clone(), infeasible, torch.zeros(0, dtype=torch.int32, device=G.device), infeasible,
                            direction)
    problem = (G, tau, f_ref, lo, hi, w)
    views = None if fixed_iterations else _views(G, tau, f_ref, w)  # the traced graph as it was: views per use
    w_col = None if views is None else views.w
    lam, shift = _start(G, tau, f_ref, w, fixed_iterations, views)
    state = _evaluate(*problem, lam, views)
    iterations = torch.zeros(batch, dtype=torch.int32, device=G.device)
    if fixed_iterations:
        state, iterations = _masked_steps(problem, state, shift, iterations, tol, max_iter)
    for k in range(0 if fixed_iterations else max_iter):
        residual = _residual(state, w, w_col)
        size = residual.abs().amax(1)
        active = size > tol
        if infeasible_tol is not None and k in (_CERTIFY_STEPS if batch > FEW_CASES else _CERTIFY_STEPS_FEW):
            infeasible, direction = _proven(problem, state, active, infeasible, direction, infeasible_tol)
            active = active & ~infeasible
        running = host_count(active)  # one host read; the indices only where some cases have stopped
        if running == 0:
            return NewtonResult(state.f, size <= tol, iterations, infeasible, direction)
        if running == batch:  # every case still runs: no gather
            state = _newton_step(problem, state, residual, shift, views)
        else:
            idx = active.nonzero().squeeze(1)
            sub = _newton_step(tuple(x[idx] for x in problem), _State(*(x[idx] for x in state)), residual[idx],
                               shift[idx])
            state = _State(*(x.index_copy(0, idx, y) for x, y in zip(state, sub)))
        iterations += active
    unsettled = _unsettled(problem, state, _residual(state, w, w_col), tol)
    if infeasible_tol is not None:  # what the last step leaves
        infeasible, direction = _proven(problem, state, unsettled, infeasible, direction, infeasible_tol)
    return NewtonResult(state.f, ~unsettled, iterations, infeasible, direction)


def _proven(problem, state: _State, running, infeasible, direction, tol_nm: float):
    """``(infeasible, direction)`` with the ``running`` cases that ``_separated`` proves added, each with its u."""
    separated, u = _separated(problem, state.lam, tol_nm)
    new = running & separated & ~infeasible
    return infeasible | new, torch.where(new.unsqueeze(1), u, direction)


def _masked_steps(problem, state: _State, shift, iterations, tol: float, max_iter: int):
    """``(state, iterations)`` after Newton steps on every case at once, each case masked from the step after it
    settles (``max |F| <= tol``), until every case has settled or ``max_iter`` steps: a ``torch.while_loop``, so an
    exported graph has no host synchronisation, no data-dependent shape, and stops early as eager code does."""
    w = problem[5]
    lipschitz = _lipschitz(problem)  # every step may take a gradient step: made once

    def running(state: _State) -> torch.Tensor:
        return _residual(state, w).abs().amax(1) > tol

    def go_on(k, iterations, *state):
        return (k < max_iter) & running(_State(*state)).any()

    def step(k, iterations, *state):
        state = _State(*state)
        residual, active = _residual(state, w), running(state)
        new = _select(active, _traced_newton_step(problem, state, residual, shift, lipschitz, active), state)
        return (k + 1, iterations + active.to(iterations.dtype), *new)

    k = torch.zeros((), dtype=torch.int64, device=iterations.device)
    out = torch.while_loop(go_on, step, (k, iterations, *state))
    return _State(*out[2:]), out[1]
