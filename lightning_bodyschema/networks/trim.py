"""Trimmed least squares: refits without the samples a fit misses by far (the polynomial and gravity torques, where a
learned moment arm swings; the path cells of ``PerMusclePath(cell_trim=...)``, a wrap's jump inside a cell), and
``solve_triangular``: the gravity torque's minimum-norm least squares from a QR. Plain PyTorch, no Lightning."""
from __future__ import annotations

from typing import Callable

import torch

ZERO_COLUMN = 1e-10  # a column norm below this times the largest is rounding (gravity's features are O(g x 1 m))
RCOND = 1e-10  # singular values of the column-scaled features below this times the largest are dropped (as lstsq's
# rcond: myoArm's weakest determined direction is at 3e-10, its undetermined ones at 1e-16)


def trimmed_refits(model: Callable, x: torch.Tensor, y: torch.Tensor, refit: Callable, factor: float, rounds: int,
                   chunk: int, per_column: bool = False, least: int = 0) -> torch.Tensor:
    """After a first fit of ``model`` on every sample ``x (S, .)``, ``y (S, .)``: up to ``rounds`` times, keep the
    samples whose residual norm ``|model(x) - y|`` is at most ``factor`` times the kept ones' median (a dropped
    sample may come back) and call ``refit(keep, new)`` with the old and new masks; stop when the mask no longer
    changes. Returns the kept mask ``(S,)``. With ``per_column`` each column of ``y`` is trimmed on its own (masks
    ``(S, M)``: one model per column, as the muscles of a cell), and a column that would keep fewer than ``least``
    samples keeps them all."""
    keep = torch.ones(y.shape if per_column else y.shape[:1], dtype=torch.bool, device=x.device)
    for _ in range(rounds):
        miss = torch.cat([model(x[i:i + chunk]) - y[i:i + chunk] for i in range(0, len(x), chunk)])
        miss = miss.abs() if per_column else miss.norm(dim=1)
        new = miss <= factor * torch.where(keep, miss, torch.nan).nanmedian(0).values
        new |= new.sum(0) < least
        if torch.equal(new, keep):
            break
        refit(keep, new)
        keep = new
    return keep


def solve_triangular(R: torch.Tensor) -> torch.Tensor:
    """The minimum-norm least-squares ``coef`` from ``R`` of ``[Y | tau]``, columns scaled to unit norm first (masses
    [kg] and moments [kg m] differ in size). Columns at rounding level (``ZERO_COLUMN`` of the largest: a frame whose
    origin sits on the axis of every joint moving it) get 0, and directions the data does not determine (a moment
    along a joint axis) are dropped below ``RCOND``: scaled up, either would fit rounding with huge coefficients."""
    A, b = R[:, :-1], R[:, -1]
    norm = A.norm(dim=0)  # the features' column norms (Q is orthonormal)
    used = torch.nonzero(norm > ZERO_COLUMN * norm.max()).flatten()
    U, S, Vh = torch.linalg.svd(A[:, used] / norm[used], full_matrices=False)
    kept = S > RCOND * S[0]
    inverse = torch.where(kept, 1.0 / torch.where(kept, S, torch.ones_like(S)), torch.zeros_like(S))
    coef = torch.zeros(A.shape[1], dtype=torch.float64, device=R.device)
    coef[used] = (Vh.T @ (inverse * (U.T @ b))) / norm[used]
    return coef
