"""Batched dual semismooth Newton for the command QPs: every case at once in numpy, proxsuite only where it stalls.

Per case (``G (M, N)`` [m/rad], ``tau (N,)`` [N m], tensions ``f (M,)`` [N] in the box ``lo <= f <= hi``)::

    min_f  1/2 ||f - f_ref||^2 + 1/(2 w) ||G^T f + tau||^2        w > 0: the least-squares answer (faults.qp)
    min_f  1/2 ||f - f_ref||^2   s.t.  G^T f + tau = 0             w = 0: the equilibrium QP (-G^T f = tau)

The Hessian in f is the identity, so for a multiplier ``lam (N,)`` [N rad/m] the box minimiser is a clip:

    (1) f(lam) = clip(f_ref - G lam, lo, hi)
    (2) F(lam) = G^T f(lam) + tau - w lam = 0        (the gradient of the concave dual; its root is the optimum)
    (3) F'(lam) = -(G^T D G + w I),  D = diag(lo < f_ref - G lam < hi)   (the free tensions)

Newton steps on (2) with (3) and a backtracking line search on the dual value: a strictly concave piecewise-quadratic
function, so the iteration settles the active set in a few steps. A case whose residual is not below ``tol`` after
``max_iter`` steps (an equilibrium that the box cannot hold has no root) is reported as not converged. numpy only.
"""
from __future__ import annotations

import numpy as np

NEWTON_MAX_ITER = 30
# the stop [N m] of the equilibrium solves: far below EQUILIBRIUM_TOL_NM, a converged row is an equilibrium
NEWTON_TOL_NM = 1e-9
_ARMIJO = 1e-4


def _tensions(G, lam, f_ref, lo, hi):
    free_f = f_ref - np.einsum("bmn,bn->bm", G, lam)  # (1) before the clip
    return np.clip(free_f, lo, hi), (free_f > lo) & (free_f < hi)


def _dual_value(G, tau, f_ref, f, lam, w):
    """The dual function at lam (to be maximised): the Lagrangian at its box minimiser f(lam)."""
    balance = np.einsum("bmn,bm->bn", G, f) + tau
    return (0.5 * np.sum((f - f_ref) ** 2, 1) + np.sum(lam * balance, 1) - 0.5 * w * np.sum(lam ** 2, 1)), balance


def dual_newton(G, tau, f_ref, lo, hi, w, tol, max_iter: int = NEWTON_MAX_ITER):
    """``(f (B, M) [N], converged (B,))`` for the problem of the module docstring, ``w (B,)`` (0 for equilibrium);
    converged where ``max |F(lam)| <= tol`` (N m): then f balances ``tau`` to ``tol`` plus ``w |lam|``."""
    batch, m, n = G.shape
    w = np.broadcast_to(np.asarray(w, float), (batch,))
    gram = np.swapaxes(G, 1, 2) @ G
    ridge = 1e-12 * np.maximum(np.trace(gram, axis1=1, axis2=2) / n, 1e-30)[:, None, None] * np.eye(n)  # G may be 0
    lipschitz = np.linalg.eigvalsh(gram)[:, -1] + w  # of the dual's gradient
    lam = np.linalg.solve(gram + ridge, (np.einsum("bmn,bm->bn", G, f_ref) + tau)[..., None])[..., 0]
    f, free = _tensions(G, lam, f_ref, lo, hi)
    value, balance = _dual_value(G, tau, f_ref, f, lam, w)
    for _ in range(max_iter):
        residual = balance - w[:, None] * lam  # (2)
        active = np.abs(residual).max(1) > tol
        if not active.any():
            break
        idx = np.flatnonzero(active)
        hessian = np.einsum("bmn,bm,bmk->bnk", G[idx], free[idx].astype(float), G[idx])  # (3)
        hessian += w[idx, None, None] * np.eye(n) + ridge[idx]
        step = np.linalg.solve(hessian, residual[idx][..., None])[..., 0]
        lam[idx], f[idx], free[idx], value[idx], balance[idx] = _line_search(
            G[idx], tau[idx], f_ref[idx], lo[idx], hi[idx], w[idx], lam[idx], value[idx], residual[idx], step,
            lipschitz[idx])
    residual = balance - w[:, None] * lam
    return f, np.abs(residual).max(1) <= tol


def least_squares_weight(G, reg: float) -> np.ndarray:
    """(B,) ``reg s`` with ``s`` each case's mean squared moment arm (so ``reg`` is dimensionless)."""
    return reg * np.maximum(np.einsum("bmn,bmn->b", G, G) / G.shape[1], 1e-300)


def box_least_squares(G, tau, f_ref, lo, hi, reg: float):
    """``(f, converged)`` of ``min ||G^T f + tau||^2 + reg s ||f - f_ref||^2`` over the box per case
    (``least_squares_weight``): ``dual_newton`` with ``w = reg s``."""
    return dual_newton(G, tau, f_ref, lo, hi, least_squares_weight(G, reg), NEWTON_TOL_NM)


def _line_search(G, tau, f_ref, lo, hi, w, lam, value, residual, step, lipschitz, halvings: int = 12):
    """Backtracking on the dual value (Armijo) along the Newton ``step``, every case at once. Where no trial is
    accepted (a nearly singular Newton system), a gradient step ``residual / lipschitz``, which always ascends
    (the dual is concave with a ``lipschitz``-continuous gradient)."""
    t = np.ones(len(lam))
    slope = np.sum(residual * step, 1)  # the dual's directional derivative: ascent for a Newton step
    best = [lam.copy(), None, None, value.copy(), None]
    todo = np.ones(len(lam), bool)
    for _ in range(halvings):
        trial = lam + t[:, None] * step
        f, free = _tensions(G, trial, f_ref, lo, hi)
        new_value, balance = _dual_value(G, tau, f_ref, f, trial, w)
        if best[1] is None:
            best[1], best[2], best[4] = f.copy(), free.copy(), balance.copy()
        take = todo & (new_value >= value + _ARMIJO * t * slope)
        for k, v in enumerate((trial, f, free, new_value, balance)):
            best[k][take] = v[take]
        todo &= ~take
        if not todo.any():
            return tuple(best)
        t = np.where(todo, 0.5 * t, t)
    trial = lam + residual / lipschitz[:, None]
    f, free = _tensions(G, trial, f_ref, lo, hi)
    new_value, balance = _dual_value(G, tau, f_ref, f, trial, w)
    for k, v in enumerate((trial, f, free, new_value, balance)):
        best[k][todo] = v[todo]
    return tuple(best)
