"""The adaptation loss L_adapt (eq:latent-opt) as a value: a box penalty on normalized x with its analytic gradient.

Every term of L_adapt is a weighted squared distance of one element of x = [l_motor, f] to an interval: a
rupture is [0, 0] on f_i, a jam (-inf, l_fixed] on l_j, the tension bounds [0, f_max], a band [lo, hi]. On the
normalized data (x = x_n std + mean) an interval stays an interval and the weight absorbs the unit scales, so

    L(x_n) = sum_k sum_j 0.5 w2_kj dist(x_n_j, [lo_kj, hi_kj])^2,   dL/dx_n = sum_k w2_k (x_n - clamp(x_n, lo_k, hi_k)),

one *slot* k per set of terms that never overlap on an element. Terms bounding the same element from opposite
sides with the same weight share a slot (their squared hinges add up to one box distance), so the usual loss is
ONE slot. Samplers receive the penalty as an argument (they import nothing from here): call it for the loss
(autograd works through it), ``grad`` for dL/dx_n, ``residual`` for dL/dx_n / c where every weight equals c.
"""
from __future__ import annotations

from typing import Optional

import numpy as np
import torch

from .constraints import LENGTH, AdaptWeights


class BoxPenalty:
    """L_adapt of a batch on normalized x (B, D). ``w2``, ``lo``, ``hi``: (K, B, D) tensors, K slots; bounds may be
    +-inf and w2 is 0 where nothing applies. ``uniform_weight``: c when there is one slot and every constrained
    element has w2 = c (then dL/dx = c * residual and a sampler folds c into its matrices), else None."""

    def __init__(self, w2: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor, uniform_weight: Optional[float]):
        self.w2, self.lo, self.hi, self.uniform_weight = w2, lo, hi, uniform_weight
        self.slots = list(zip(w2.unbind(0), lo.unbind(0), hi.unbind(0)))

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        """Loss per case (B,); differentiable (the autograd reference samplers use it)."""
        total = 0.0
        for w2, lo, hi in self.slots:
            r = x - torch.clamp(x, lo, hi)
            total = total + (0.5 * w2 * r * r).sum(-1)
        return total

    def residual(self, x: torch.Tensor, out: Optional[tuple] = None) -> torch.Tensor:
        """dL/dx / c (c = ``uniform_weight``, else 1), (B, D); ``out``: two (B, D) buffers to write into."""
        clamped, r = out if out is not None else (torch.empty_like(x), torch.empty_like(x))
        w2, lo, hi = self.slots[0]
        torch.sub(x, torch.clamp(x, lo, hi, out=clamped), out=r)
        if self.uniform_weight is not None:
            return r
        r.mul_(w2)
        for w2, lo, hi in self.slots[1:]:
            r.add_(torch.sub(x, torch.clamp(x, lo, hi)).mul_(w2))
        return r

    def grad(self, x: torch.Tensor) -> torch.Tensor:
        """dL/dx (B, D)."""
        r = self.residual(x)
        return r if self.uniform_weight is None else r.mul_(self.uniform_weight)


class BoundsPenalty:
    """L_adapt with ONE weight c for every term, from a batch's ``FaultBounds`` as tensor ops (traceable by
    ``torch.export``): two boxes per element of normalized x (B, D), A (a jam's l_fixed on l; the tension box on f)
    and B (a band on l); where only one applies the other adds an exact 0, and a jam and a band on one motor add up
    as ``PenaltyBuilder``'s two slots do. ``box_a``, ``box_b``: (lo, hi) pairs, ``both`` their intersection (the
    projection's box), normalized as ``PenaltyBuilder`` does (SI bounds in float64, then cast to ``dtype``)."""

    def __init__(self, bounds, x_mean: torch.Tensor, x_std: torch.Tensor, weight: float, dtype=torch.float32):
        m, inf = bounds.cut.shape[1], float("inf")
        lcols, fcols = slice(0, m), slice(m, 2 * m)

        def normalized(bound_si, cols):
            return ((bound_si - x_mean[cols]) / x_std[cols]).to(dtype)
        jam_hi = torch.where(bounds.jam, normalized(torch.where(bounds.jam, bounds.l_fixed_m, 0.0), lcols), inf)
        band_lo = torch.where(bounds.band, normalized(torch.where(bounds.band, bounds.band_lo_m, 0.0), lcols), -inf)
        band_hi = torch.where(bounds.band, normalized(torch.where(bounds.band, bounds.band_hi_m, 0.0), lcols), inf)
        f_lo, f_hi = normalized(bounds.f_lo_n, fcols), normalized(bounds.f_hi_n, fcols)
        free = torch.full_like(jam_hi, inf)
        self.box_a = (torch.cat([-free, f_lo], 1), torch.cat([jam_hi, f_hi], 1))
        self.box_b = (torch.cat([band_lo, -free], 1), torch.cat([band_hi, free], 1))
        self.both = (torch.maximum(self.box_a[0], self.box_b[0]), torch.minimum(self.box_a[1], self.box_b[1]))
        self.uniform_weight = float(weight)

    def residual(self, x: torch.Tensor, out=None) -> torch.Tensor:
        """dL/dx / c (B, D) (``out``: accepted for ``BoxPenalty``'s signature, not needed in a graph)."""
        (lo_a, hi_a), (lo_b, hi_b) = self.box_a, self.box_b
        return (x - torch.clamp(x, lo_a, hi_a)) + (x - torch.clamp(x, lo_b, hi_b))

    def grad(self, x: torch.Tensor) -> torch.Tensor:
        return self.uniform_weight * self.residual(x)

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        r_a = x - torch.clamp(x, *self.box_a)
        r_b = x - torch.clamp(x, *self.box_b)
        return 0.5 * self.uniform_weight * (r_a * r_a + r_b * r_b).sum(-1)


class PenaltyBuilder:
    """Turns a batch's constraints (``Faults.constraints``) into its ``BoxPenalty`` on normalized x.

    Built once per (weights, unit scales, normalizer): ``weights`` an ``AdaptWeights``; ``l_scale``, ``f_scale``
    scalars or (M,) [m], [N] (residuals are divided by them before squaring: 1 gives the paper's SI loss, the
    data's spreads give every term the same unit); ``x_mean``, ``x_std`` (2M,) with x = x_n x_std + x_mean.
    Each call places every constraint's interval, in normalized units, into the first slot where it meets nothing
    or a compatible box on every element, else into a new slot (vectorized over cases).
    """

    def __init__(self, weights: AdaptWeights, l_scale, f_scale, x_mean, x_std, dtype=torch.float32, device=None):
        self.mean, self.std = _np(x_mean), _np(x_std)
        self.m = m = self.mean.shape[-1] // 2
        scale = np.concatenate([np.broadcast_to(_np(l_scale), (m,)), np.broadcast_to(_np(f_scale), (m,))])
        self.ratio2 = (self.std / scale) ** 2
        self.weights, self.dtype, self.device = weights, dtype, device

    def __call__(self, constraints) -> BoxPenalty:
        b, m = np.asarray(constraints[0].mask).shape
        slots: list = []
        for c in constraints:
            cols = slice(0, m) if c.column == LENGTH else slice(m, 2 * m)
            w2 = 2.0 * float(getattr(self.weights, c.weight_name)) * self.ratio2[cols]
            mask = np.asarray(c.mask, bool)
            if not w2.any() or not mask.any():
                continue
            lo, hi = (self._normalized(bound, cols) for bound in c.bounds())  # NaN off the mask is never copied
            _place(slots, b, 2 * m, cols, mask, w2, lo, hi)
        packed = np.stack([slot for slot, _ in slots] or [_empty_slot(b, 2 * m)], axis=1)  # (3, K, B, D)
        tensors = torch.from_numpy(packed).to(dtype=self.dtype, device=self.device)
        return BoxPenalty(tensors[0], tensors[1], tensors[2], _uniform(packed[0]))

    def _normalized(self, bound, cols: slice):
        """A bound in SI units -> normalized units (infinite scalars stay as they are)."""
        if np.isscalar(bound) and np.isinf(bound):
            return float(bound)
        with np.errstate(invalid="ignore"):
            return (np.asarray(bound, float) - self.mean[cols]) / self.std[cols]


def _uniform(w2: np.ndarray) -> Optional[float]:
    """The one nonzero value of a single-slot weight array (1, B, D), else None (1.0 if all zero)."""
    if len(w2) != 1:
        return None
    nz = w2[w2 != 0]
    if not nz.size:
        return 1.0
    return float(nz[0]) if (nz == nz[0]).all() else None


def _np(a) -> np.ndarray:
    return a.detach().cpu().numpy().astype(np.float64) if torch.is_tensor(a) else np.asarray(a, np.float64)


def _empty_slot(b: int, d: int) -> np.ndarray:
    slot = np.empty((3, b, d))
    slot[0], slot[1], slot[2] = 0.0, -np.inf, np.inf
    return slot


def _place(slots: list, b: int, d: int, cols: slice, mask, w2, lo, hi) -> None:
    """Put one term in the first slot where, on every element it covers, it meets nothing or a compatible box
    (same weight, one side bounded by each, bounds not crossing: the two squared hinges are one box distance);
    otherwise open a new slot."""
    lo_b, hi_b = np.broadcast_to(lo, mask.shape), np.broadcast_to(hi, mask.shape)
    for slot, occupied in slots:
        overlap = occupied[:, cols] & mask
        if overlap.any():
            s_w2, s_lo, s_hi = slot[0][:, cols][overlap], slot[1][:, cols][overlap], slot[2][:, cols][overlap]
            n_lo, n_hi = lo_b[overlap], hi_b[overlap]
            ok = ((s_w2 == np.broadcast_to(w2, mask.shape)[overlap]).all()
                  and ((n_lo == -np.inf) | (s_lo == -np.inf)).all() and ((n_hi == np.inf) | (s_hi == np.inf)).all()
                  and (np.maximum(n_lo, s_lo) <= np.minimum(n_hi, s_hi)).all())
            if not ok:
                continue
        break
    else:
        slot, occupied = _empty_slot(b, d), np.zeros((b, d), bool)
        slots.append((slot, occupied))
    np.copyto(slot[0][:, cols], w2, where=mask)
    np.copyto(slot[1][:, cols], np.maximum(slot[1][:, cols], lo), where=mask)
    np.copyto(slot[2][:, cols], np.minimum(slot[2][:, cols], hi), where=mask)
    occupied[:, cols] |= mask
