"""The QPs of a motion's frames, warm-started: a frame's optimum mostly has the same muscles at their bounds as the
optimum of a frame shortly before it, and on a known active set the QP is one linear solve.

Per chunk of frames (``statics.qp_blocks``): every ``SEED_EVERY``-th frame is solved by the solver (a seed); every
other frame takes its seed's active set (the muscles at their lower or upper bound) as a guess and makes the exact
step on it: with the bound muscles held at their bounds, the free ones ``x = x_ref - G lam`` and the balance
``G^T x + tau = 0`` give ``(G_F^T G_F) lam = G_F^T x_ref_F + G_B^T x_B + tau`` (N x N). The answer is the QP's
optimum exactly when it keeps that active set (the free ones within their bounds, each bound one pushed against its
bound: the KKT conditions; the optimum is unique, the Hessian being the identity) and balances the torque to the
solver's own tolerance. A frame where it does not is given the active set the step found and tries again
(``WARM_ROUNDS`` such steps: the dual Newton's, from a warm start), then goes to the solver. Only frames proven this
way are taken, so the statuses are the solver's; the answers are the optimum to rounding (the solver's stop, 1e-12
N m of residual, leaves up to ~1e-12 of activation). torch on the CPU; never imports Lightning.
"""
from __future__ import annotations

import numpy as np
import torch

from .._numpy import to_numpy
from ..status import Status

SEED_EVERY = 32  # frames between two seeds (64 ms at 2 ms frames): on the benchmark's reach and squat every other
# frame was taken within WARM_ROUNDS steps, so the solver ran on 1 frame in 32
WARM_ROUNDS = 3  # exact steps from the seed's active set before a frame goes to the solver


def solve_warm(solve, G, tau_nm, x_ref, lo, hi, tol_nm: float):
    """``solve``'s ``(x (B, M), codes (B,))`` for consecutive frames of one QP block (``G`` (B, M, N) scaled,
    ``tau_nm`` (B, N), ``x_ref, lo, hi`` (B, M)), the non-seed frames warm-started (module docstring); ``tol_nm``:
    the largest torque residual [N m] of a taken frame (the solver's own stop)."""
    rows = len(G)
    seeds = np.arange(0, rows, SEED_EVERY)
    x, code = np.empty_like(lo), np.full(rows, Status.OK.code)
    x[seeds], code[seeds] = solve(*(a[seeds] for a in (G, tau_nm, x_ref, lo, hi)))
    todo = np.ones(rows, dtype=bool)
    todo[seeds] = False
    guess = x[seeds][np.arange(rows) // SEED_EVERY]
    for _ in range(WARM_ROUNDS):
        idx = np.flatnonzero(todo)
        if not len(idx):
            break
        step, held = exact_step(*(a[idx] for a in (G, tau_nm, x_ref, lo, hi)), guess[idx], tol_nm)
        x[idx], guess[idx], todo[idx[held]] = step, step, False
    if todo.any():
        x[todo], code[todo] = solve(*(a[todo] for a in (G, tau_nm, x_ref, lo, hi)))
    return x, code


@torch.inference_mode()
def exact_step(G, tau_nm, x_ref, lo, hi, guess, tol_nm: float):
    """``(x (b, M), held (b,))``: the exact step on the active set of ``guess`` (b, M) (at or beyond a bound: held
    there), and where it is the QP's optimum (it keeps that active set, balances to ``tol_nm``)."""
    G, tau, x_ref, lo, hi, guess = (torch.from_numpy(np.ascontiguousarray(a)) for a in (G, tau_nm, x_ref, lo, hi,
                                                                                        guess))
    at_lo, at_hi = guess <= lo, guess >= hi
    free = ~(at_lo | at_hi)
    Gt = G.transpose(1, 2)
    gram = torch.bmm(Gt, G * free.unsqueeze(-1))
    held_x = torch.where(free, x_ref, torch.where(at_lo, lo, hi))
    lam, info = torch.linalg.solve_ex(gram, (torch.bmm(Gt, held_x.unsqueeze(-1)).squeeze(-1) + tau).unsqueeze(-1))
    unclipped = x_ref - torch.bmm(G, lam).squeeze(-1)
    x = torch.clamp(unclipped, lo, hi)
    kept = torch.where(free, (lo <= unclipped) & (unclipped <= hi),
                       (at_lo & at_hi) | (at_lo & (unclipped <= lo)) | (at_hi & (unclipped >= hi)))
    residual = (torch.bmm(Gt, x.unsqueeze(-1)).squeeze(-1) + tau).abs().amax(1)
    held = kept.all(1) & (residual <= tol_nm) & (info == 0)  # NaN residuals compare False
    return to_numpy(x), to_numpy(held)
