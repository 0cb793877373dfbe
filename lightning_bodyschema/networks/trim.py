"""Trimmed least squares: refits without the samples a fit misses by far (the per-muscle polynomial torque and the
gravity torque: where a learned moment arm swings, at a jump or a cell's edge, its torque is no smooth function and
would pull the whole least squares). Plain PyTorch, no Lightning."""
from __future__ import annotations

from typing import Callable

import torch


def trimmed_refits(model: Callable, x: torch.Tensor, y: torch.Tensor, refit: Callable, factor: float, rounds: int,
                   chunk: int) -> torch.Tensor:
    """After a first fit of ``model`` on every sample ``x (S, .)``, ``y (S, .)``: up to ``rounds`` times, keep the
    samples whose residual norm ``|model(x) - y|`` is at most ``factor`` times the kept ones' median (a dropped
    sample may come back) and call ``refit(keep, new)`` with the old and new masks; stop when the mask no longer
    changes. Returns the kept mask ``(S,)``."""
    keep = torch.ones(len(x), dtype=torch.bool, device=x.device)
    for _ in range(rounds):
        miss = torch.cat([(model(x[i:i + chunk]) - y[i:i + chunk]).norm(dim=1) for i in range(0, len(x), chunk)])
        new = miss <= factor * miss[keep].median()
        if torch.equal(new, keep):
            break
        refit(keep, new)
        keep = new
    return keep
