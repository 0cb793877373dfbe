"""Batched dual semismooth Newton for the box QPs: every case at once in torch (float64, any device).

Per case (``G (M, N)`` [m/rad], ``tau (N,)`` [N m], tensions ``f (M,)`` [N] in the box ``lo <= f <= hi``)::

    min_f  1/2 ||f - f_ref||^2 + 1/(2 w) ||G^T f + tau||^2        w > 0: the least-squares answer
    min_f  1/2 ||f - f_ref||^2   s.t.  G^T f + tau = 0             w = 0: the equilibrium / command QP

The Hessian in f is the identity, so for a multiplier ``lam (N,)`` [N rad/m] the box minimiser is a clip:

    (1) f(lam) = clip(f_ref - G lam, lo, hi)
    (2) F(lam) = G^T f(lam) + tau - w lam = 0        (the gradient of the concave dual; its root is the optimum)
    (3) F'(lam) = -(G^T D G + w I),  D = diag(lo < f_ref - G lam < hi)   (the free tensions)

Newton steps on (2) with (3) and a backtracking (Armijo) line search on the dual value, a strictly concave
piecewise-quadratic function, with a gradient step ``F / L`` (``L`` the dual gradient's Lipschitz constant) where no
trial is accepted. A case whose residual is not below ``tol`` after ``max_iter`` steps (an equilibrium that the box
cannot hold has no root) is reported as not converged.

``fixed_iterations=True`` runs exactly ``max_iter`` steps and ``LINE_SEARCH_HALVINGS`` trials each on every case,
masked where a case has converged: no host synchronisation and no data-dependent shape, so ``torch.export`` can
trace it; the answers are the eager ones. torch only.
"""
from __future__ import annotations

from typing import NamedTuple

import torch

NEWTON_MAX_ITER = 30
# the stop [N m] of the equilibrium solves: far below EQUILIBRIUM_TOL_NM, a converged row is an equilibrium
NEWTON_TOL_NM = 1e-9
LINE_SEARCH_HALVINGS = 12
_ARMIJO = 1e-4


class NewtonResult(NamedTuple):
    """``f (B, M)`` [N] in the box; ``converged (B,)`` bool: ``max |F(lam)| <= tol`` (then f balances ``tau`` to
    ``tol`` plus ``w |lam|``); ``iterations (B,)`` int32: the Newton steps each case took."""

    f: torch.Tensor
    converged: torch.Tensor
    iterations: torch.Tensor


class _State(NamedTuple):
    """The iterate of a (sub)batch: multiplier, tensions, free mask, dual value, ``G^T f + tau``."""

    lam: torch.Tensor
    f: torch.Tensor
    free: torch.Tensor
    value: torch.Tensor
    balance: torch.Tensor


def _f64(x, device=None) -> torch.Tensor:
    return torch.as_tensor(x, dtype=torch.float64, device=device)


def _evaluate(G, tau, f_ref, lo, hi, w, lam) -> _State:
    """The state at ``lam``: (1), the free mask of (3) and the dual value (the Lagrangian at f(lam))."""
    free_f = f_ref - (G @ lam.unsqueeze(-1)).squeeze(-1)
    f = torch.minimum(torch.maximum(free_f, lo), hi)
    balance = (G.transpose(1, 2) @ f.unsqueeze(-1)).squeeze(-1) + tau
    value = (0.5 * ((f - f_ref) ** 2).sum(1) + (lam * balance).sum(1) - 0.5 * w * (lam ** 2).sum(1))
    return _State(lam, f, (free_f > lo) & (free_f < hi), value, balance)


def _select(take, new: _State, old: _State) -> _State:
    """Per case ``new`` where ``take`` (B,) else ``old``."""
    return _State(*(torch.where(take.view(-1, *([1] * (a.dim() - 1))), a, b) for a, b in zip(new, old)))


def _line_search(problem, state: _State, residual, step, lipschitz, eager: bool) -> _State:
    """Backtracking on the dual value (Armijo) along the Newton ``step``, every case at once; where no trial is
    accepted (a nearly singular Newton system), a gradient step ``residual / lipschitz``, which always ascends (the
    dual is concave with a ``lipschitz``-continuous gradient). ``eager``: stop once every case has accepted."""
    t = torch.ones_like(state.value)
    slope = (residual * step).sum(1)  # the dual's directional derivative: ascent for a Newton step
    best, todo = state, torch.ones_like(t, dtype=torch.bool)
    for _ in range(LINE_SEARCH_HALVINGS):
        trial = _evaluate(*problem, state.lam + t.unsqueeze(1) * step)
        take = todo & (trial.value >= state.value + _ARMIJO * t * slope)
        best, todo = _select(take, trial, best), todo & ~take
        if eager and not bool(todo.any()):
            return best
        t = torch.where(todo, 0.5 * t, t)
    gradient_step = _evaluate(*problem, state.lam + residual / lipschitz.unsqueeze(1))
    return _select(todo, gradient_step, best)


def _newton_step(problem, state: _State, ridge, lipschitz, eager: bool) -> _State:
    """One Newton step on (2) with (3) and the line search, for the (sub)batch ``problem``."""
    G, w = problem[0], problem[5]
    residual = state.balance - w.unsqueeze(1) * state.lam  # (2)
    n = G.shape[2]
    hessian = G.transpose(1, 2) @ (state.free.to(G.dtype).unsqueeze(-1) * G)  # (3)
    hessian = hessian + w.view(-1, 1, 1) * torch.eye(n, dtype=G.dtype, device=G.device) + ridge
    step = torch.linalg.solve_ex(hessian, residual.unsqueeze(-1))[0].squeeze(-1)
    return _line_search(problem, state, residual, step, lipschitz, eager)


def _start(G, tau, f_ref, w):
    """``(lam_0, ridge, lipschitz)``: the unconstrained multiplier, a tiny ridge (G may be 0) and the dual
    gradient's Lipschitz constant."""
    n = G.shape[2]
    gram = G.transpose(1, 2) @ G
    eye = torch.eye(n, dtype=G.dtype, device=G.device)
    trace = torch.diagonal(gram, dim1=1, dim2=2).sum(1)
    ridge = 1e-12 * torch.clamp(trace / n, min=1e-30).view(-1, 1, 1) * eye
    lipschitz = torch.linalg.eigvalsh(gram)[:, -1] + w
    rhs = (G.transpose(1, 2) @ f_ref.unsqueeze(-1)).squeeze(-1) + tau
    lam = torch.linalg.solve_ex(gram + ridge, rhs.unsqueeze(-1))[0].squeeze(-1)
    return lam, ridge, lipschitz


def _residual_norm(state: _State, w) -> torch.Tensor:
    return (state.balance - w.unsqueeze(1) * state.lam).abs().amax(1)


def dual_newton(G, tau, f_ref, lo, hi, w=0.0, tol: float = NEWTON_TOL_NM, max_iter: int = NEWTON_MAX_ITER,
                fixed_iterations: bool = False) -> NewtonResult:
    """The problem of the module docstring for ``G (B, M, N)``, ``tau (B, N)``, ``f_ref, lo, hi (B, M)`` (float64
    tensors on one device, or arrays), ``w`` a scalar or ``(B,)`` (0: the equilibrium QP), ``lo <= hi``.
    ``fixed_iterations``: exactly ``max_iter`` masked steps (traceable by ``torch.export``), the eager answer."""
    G = _f64(G)
    tau, f_ref, lo, hi = (_f64(x, G.device) for x in (tau, f_ref, lo, hi))
    batch = G.shape[0]
    w = _f64(w, G.device).expand(batch)
    if batch == 0 and not fixed_iterations:
        return NewtonResult(f_ref.clone(), torch.zeros(0, dtype=torch.bool, device=G.device),
                            torch.zeros(0, dtype=torch.int32, device=G.device))
    problem = (G, tau, f_ref, lo, hi, w)
    lam, ridge, lipschitz = _start(G, tau, f_ref, w)
    state = _evaluate(*problem, lam)
    iterations = torch.zeros(batch, dtype=torch.int32, device=G.device)
    for _ in range(max_iter):
        active = _residual_norm(state, w) > tol
        if fixed_iterations:
            state = _select(active, _newton_step(problem, state, ridge, lipschitz, False), state)
        else:
            idx = active.nonzero().squeeze(1)
            if idx.numel() == 0:
                break
            sub = _newton_step(tuple(x[idx] for x in problem), _State(*(x[idx] for x in state)), ridge[idx],
                               lipschitz[idx], True)
            state = _State(*(x.index_copy(0, idx, y) for x, y in zip(state, sub)))
        iterations = iterations + active.to(torch.int32)
    return NewtonResult(state.f, _residual_norm(state, w) <= tol, iterations)
