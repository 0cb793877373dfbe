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
from ..samplers.guided import INPAINT as MODES  # the sampler's inpainting modes: one tuple (samplers import no faults)


class FaultProjection:
    """P(x_n) for one batch of fault cases. ``lo``, ``hi`` (B, D): the feasible box in SI units (+-inf where free);
    ``x_mean``, ``x_std`` (D,): the normalizer (x = x_n x_std + x_mean); ``k_n``, ``alpha_per_m``: the spring
    (scalars or (M,)); ``mode``: ``"box"`` or ``"spring"`` (see the module doc)."""

    def __init__(self, lo: torch.Tensor, hi: torch.Tensor, x_mean: torch.Tensor, x_std: torch.Tensor, k_n,
                 alpha_per_m, mode: str = "spring"):
        if mode not in MODES[1:]:
            raise BodySchemaInputError(f"unknown projection mode {mode!r}; allowed: {list(MODES[1:])}")
        self.mode, m = mode, lo.shape[-1] // 2
        self.m = m
        self.lo_n, self.hi_n = (lo - x_mean) / x_std, (hi - x_mean) / x_std  # the box in normalized units
        as_t = lambda v: torch.as_tensor(np.broadcast_to(np.asarray(v, np.float64), (m,)).copy(),  # noqa: E731
                                         dtype=lo.dtype, device=lo.device)
        k, alpha, s_l = as_t(k_n), as_t(alpha_per_m), x_std[:m]
        # the spring in normalized length units: e_n = log1p(f / k) / (alpha s_l), f = k expm1(alpha s_l e_n)
        self.f_mean, self.f_std, self.inv_f_std = x_mean[m:], x_std[m:], 1.0 / x_std[m:]
        self.inv_k, self.k, self.inv_alpha_sl, self.alpha_sl = 1.0 / k, k, 1.0 / (alpha * s_l), alpha * s_l
        # the tension box as an elongation box, e_n in [delta(lo_f), delta(hi_f)] (eq:muscle-elongation-inv)
        e_box = [torch.log1p(b[:, m:].clamp_min(0.0) * self.inv_k) * self.inv_alpha_sl for b in (lo, hi)]
        self.e_lo_n, self.e_hi_n = e_box
        self.l_lo_n, self.l_hi_n = self.lo_n[:, :m], self.hi_n[:, :m]

    @classmethod
    def from_penalty(cls, penalty, x_mean, x_std, k_n, alpha_per_m, mode: str = "spring") -> "FaultProjection":
        """The box of ``penalty`` (the intersection of its slots' intervals where a weight applies), in SI units."""
        inf = torch.full_like(penalty.lo[0], float("inf"))
        lo_n, hi_n = -inf, inf
        for w2, lo, hi in penalty.slots:
            active = w2 != 0
            lo_n = torch.where(active, torch.maximum(lo_n, lo), lo_n)
            hi_n = torch.where(active, torch.minimum(hi_n, hi), hi_n)
        return cls.from_normalized_box(lo_n, hi_n, x_mean, x_std, k_n, alpha_per_m, mode)

    @classmethod
    def from_normalized_box(cls, lo_n, hi_n, x_mean, x_std, k_n, alpha_per_m, mode: str = "spring"):
        """From the feasible box ``lo_n``, ``hi_n`` (B, D) in normalized units (a ``BoundsPenalty``'s ``both``)."""
        mean, std = (torch.as_tensor(np.asarray(v, np.float64), dtype=lo_n.dtype, device=lo_n.device)
                     for v in (x_mean, x_std))
        return cls(lo_n * std + mean, hi_n * std + mean, mean, std, k_n, alpha_per_m, mode)

    def offset(self, x_n: torch.Tensor, out: Optional[torch.Tensor] = None) -> torch.Tensor:
        """d = x_n - P(x_n) (B, D), normalized units (``out``: a (B, D) buffer to write into).

        Spring mode, per muscle: the geometric length g = l + e the prediction implies is kept (e its elongation,
        eq:muscle-elongation-inv), so one number moves: the motor goes into its length box, the elongation that
        leaves into the tension box (as an elongation box), and the motor follows (l = g - e, still in its box).
        Where nothing is violated, P(x) = x up to rounding (~1e-16)."""
        if self.mode == "box":
            return torch.sub(x_n, torch.clamp(x_n, self.lo_n, self.hi_n), out=out)
        m = self.m
        l_n, f_n = x_n[:, :m], x_n[:, m:]
        f = torch.addcmul(self.f_mean, f_n, self.f_std)
        e = torch.log1p(f.clamp_min(0.0).mul_(self.inv_k)).mul_(self.inv_alpha_sl)  # eq:muscle-elongation-inv
        g = e.add_(l_n)  # the geometric length, kept
        e = torch.clamp(g - torch.clamp(l_n, self.l_lo_n, self.l_hi_n), self.e_lo_n, self.e_hi_n)
        d_l = torch.sub(l_n, torch.clamp(g.sub_(e), self.l_lo_n, self.l_hi_n))
        f_new = torch.expm1(e.mul_(self.alpha_sl)).mul_(self.k)  # eq:nonlinear-spring
        return torch.cat([d_l, f.sub_(f_new).mul_(self.inv_f_std)], 1, out=out)  # (out=: torch.compile wants it whole)

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
