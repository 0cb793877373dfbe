"""The nearest command that respects the faults: the projection used to inpaint the predicted x0 while denoising.

The adaptation loss (``faults.penalty.BoxPenalty``) is a sum of squared distances to a box per element of
x = [l_motor, f]; its zero set is the box itself. Guidance only pulls toward it, so a jam that binds is still
broken by ~1 mm after 200 steps. Inpainting (as RePaint and diffusion policies do) replaces the constrained
coordinates of the predicted x0 at every step by feasible values and lets the network fill in the rest:

* ``"box"``:    clamp every element into its box (a cut muscle's f = 0, a jammed motor's l = min(l, l_fixed), ...).
* ``"spring"``: the same, but keep each muscle on its own spring (eq:nonlinear-spring): the geometric length the
  prediction implies, g = l_motor + delta(f) (eq:muscle-elongation-inv), is kept, so a jammed motor held at l_fixed
  pulls with f = k (exp(alpha (g - l_fixed)) - 1), and a tension clipped to its limit moves the motor to
  g - delta(f). A box-clamped jam leaves the tension of a muscle that is no longer where it was, and the next
  denoising steps must repair that inconsistency; the spring-consistent value is what the muscle would do.

``offset(x_n)`` returns d = x_n - P(x_n) in normalized units (0 exactly where nothing is violated); samplers take
the projection as a value, like the penalty. torch only; no Lightning.
"""
from __future__ import annotations

from typing import Optional

import numpy as np
import torch

from ..errors import BodySchemaInputError

MODES = ("none", "box", "spring")


class FaultProjection:
    """P(x_n) for one batch of fault cases. ``lo``, ``hi`` (B, D): the feasible box in SI units (+-inf where free);
    ``x_mean``, ``x_std`` (D,): the normalizer (x = x_n x_std + x_mean); ``k_n``, ``alpha_per_m``: the spring
    (scalars or (M,)); ``mode``: ``"box"`` or ``"spring"`` (see the module doc)."""

    def __init__(self, lo: torch.Tensor, hi: torch.Tensor, x_mean: torch.Tensor, x_std: torch.Tensor, k_n,
                 alpha_per_m, mode: str = "spring"):
        if mode not in MODES[1:]:
            raise BodySchemaInputError(f"unknown projection mode {mode!r}; allowed: {list(MODES[1:])}")
        self.mode, self.m = mode, lo.shape[-1] // 2
        self.lo, self.hi, self.mean, self.std = lo, hi, x_mean, x_std
        self.lo_n, self.hi_n = (lo - x_mean) / x_std, (hi - x_mean) / x_std  # the box in normalized units
        as_t = lambda v: torch.as_tensor(np.asarray(v, np.float64), dtype=lo.dtype, device=lo.device)  # noqa: E731
        self.k, self.alpha = as_t(k_n), as_t(alpha_per_m)

    @classmethod
    def from_penalty(cls, penalty, x_mean, x_std, k_n, alpha_per_m, mode: str = "spring") -> "FaultProjection":
        """The box of ``penalty`` (the intersection of its slots' intervals where a weight applies), in SI units."""
        inf = torch.full_like(penalty.lo[0], float("inf"))
        lo_n, hi_n = -inf, inf
        for w2, lo, hi in penalty.slots:
            active = w2 != 0
            lo_n = torch.where(active, torch.maximum(lo_n, lo), lo_n)
            hi_n = torch.where(active, torch.minimum(hi_n, hi), hi_n)
        mean, std = (torch.as_tensor(np.asarray(v, np.float64), dtype=lo_n.dtype, device=lo_n.device)
                     for v in (x_mean, x_std))
        return cls(lo_n * std + mean, hi_n * std + mean, mean, std, k_n, alpha_per_m, mode)

    def offset(self, x_n: torch.Tensor) -> torch.Tensor:
        """d = x_n - P(x_n) (B, D), normalized units."""
        if self.mode == "box":
            return x_n - torch.clamp(x_n, self.lo_n, self.hi_n)
        m, k, alpha = self.m, self.k, self.alpha
        x = torch.addcmul(self.mean, x_n, self.std)
        l, f = x[:, :m], x[:, m:]
        lo_l, hi_l, lo_f, hi_f = self.lo[:, :m], self.hi[:, :m], self.lo[:, m:], self.hi[:, m:]
        g = l + torch.log1p(f.clamp_min(0.0) / k) / alpha  # eq:muscle-elongation-inv: the implied geometric length
        l_box = torch.clamp(l, lo_l, hi_l)
        # a motor held back by its jam/band: the tension its spring gives there (eq:nonlinear-spring)
        f_src = torch.where(l_box != l, k * torch.expm1(alpha * (g - l_box).clamp_min(0.0)), f)
        f_new = torch.clamp(f_src, lo_f, hi_f)
        # a tension moved (spring or limits): the motor length that keeps the muscle on its spring, inside its box
        l_new = torch.where(f_new != f, torch.clamp(g - torch.log1p(f_new.clamp_min(0.0) / k) / alpha, lo_l, hi_l),
                            l_box)
        return (x - torch.cat([l_new, f_new], 1)) / self.std

    def __call__(self, x_n: torch.Tensor) -> torch.Tensor:
        """P(x_n)."""
        return x_n - self.offset(x_n)


def projection_for(penalty, mode: Optional[str], x_mean, x_std, spring) -> Optional[FaultProjection]:
    """The projection of ``mode`` ("none"/None: no projection) for ``penalty``'s box and ``spring``."""
    if mode in (None, "none"):
        return None
    if mode not in MODES:
        raise BodySchemaInputError(f"unknown inpaint mode {mode!r}; allowed: {list(MODES)}")
    return FaultProjection.from_penalty(penalty, x_mean, x_std, spring.k_n, spring.alpha_per_m, mode)
