"""Trimmed least squares: refits without the samples a fit misses by far (the per-muscle polynomial torque and the
gravity torque: where a learned moment arm swings, at a jump or a cell's edge, its torque is no smooth function and
would pull the whole least squares; the path cells of ``PerMusclePath(cell_trim=...)``: a wrap's jump inside a cell).
Plain PyTorch, no Lightning."""
from __future__ import annotations

from typing import Callable

import torch


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
