"""``FaultBounds``: one batch of faults as SI bounds on the tensions f and the motor lengths l_motor, and the tension
box those bounds give through the spring at given muscle lengths.

Per muscle (``Faults``: cut, jammed, weakened, length-banded; the robot's f_max and spring):

* tensions ``f_lo_n <= f <= f_hi_n``: ``[0, 0]`` cut, ``[0, f_max']`` weakened, ``[0, f_max]`` otherwise;
* motor lengths ``l_lo_m <= l_motor <= l_hi_m``: a jam's ``l_fixed`` and a band's hi above, a band's lo below;
* through the spring ``l_motor = l_geo - delta(f)`` (``sim.spring``: the law written once) at lengths ``l_geo``,
  ``tension_box``:
  ``l_motor <= l_hi`` is ``f >= k (exp(alpha (l_geo - l_hi)) - 1)`` (the tension the spring gives with the motor at
  ``l_hi``; reeling in, a higher tension, is allowed) and ``l_motor >= l_lo`` is
  ``f <= k (exp(alpha (l_geo - l_lo)) - 1)`` (below ``l_geo`` the wire is slack: f = 0, the motor anywhere above).
  Where the two cross (lo > hi) no tension meets them; ``motor_length_m`` turns a tension in the box back into the
  motor length of the command.

Every method works on numpy arrays and torch tensors alike (the backend of the fields; torch: any device, float64,
traceable by ``torch.export``), so the feasibility check (numpy), the adapters and the exported graph (torch) share
it. Built from ``Faults`` (``from_faults``) or from the exported package's tensor inputs (``from_tensors``); the
rules a fault set must obey are ``faults.fault_rules`` (``Faults.validate`` and the package both ask them).
"""
from __future__ import annotations

import sys
from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np

from .._arrays import fill, isfinite, isnan, maximum, minimum, namespace, where
from ..sim.spring import spring_elongation_m, spring_tension_n
from .faults import fault_rules


@dataclass(frozen=True)
class FaultBounds:
    """SI bounds of one batch of faults (module docstring). Masks ``cut``, ``jam``, ``weak``, ``band`` (B, M) bool;
    ``l_fixed_m``, ``band_lo_m``, ``band_hi_m`` (B, M) [m], NaN where off; ``f_limit_n`` (B, M) [N]: a weakened
    muscle's limit, else the robot's f_max; ``k_n``, ``alpha_per_m``: the spring (scalars or (M,); None: no spring,
    ``tension_box`` unavailable). numpy arrays or torch tensors, all of one backend."""

    cut: Any
    jam: Any
    weak: Any
    band: Any
    l_fixed_m: Any
    band_lo_m: Any
    band_hi_m: Any
    f_limit_n: Any
    k_n: Any = None
    alpha_per_m: Any = None

    @classmethod
    def from_tensors(cls, cut, jam, l_fixed_m, f_weak_n, band_lo_m, band_hi_m, f_max_n, k_n=None,
                     alpha_per_m=None) -> "FaultBounds":
        """From the exported package's inputs: ``cut``, ``jam`` (B, M) masks (bool, or 1.0 where on), ``l_fixed_m``,
        ``f_weak_n`` (NaN: not weakened), ``band_lo_m``, ``band_hi_m`` (NaN: free) (B, M); ``f_max_n`` the robot's
        limit (scalar or (M,)). Not validated (``fault_rules`` says what is broken)."""
        cut, jam = (m if m.dtype == bool or str(m.dtype) == "torch.bool" else m == 1.0 for m in (cut, jam))
        weak, band = ~isnan(f_weak_n), ~(isnan(band_lo_m) & isnan(band_hi_m))
        f_limit = where(weak, f_weak_n, fill(f_weak_n, 0.0) + f_max_n)  # the robot's limit broadcast to (B, M)
        return cls(cut, jam, weak, band, l_fixed_m, band_lo_m, band_hi_m, f_limit, k_n, alpha_per_m)

    @classmethod
    def from_faults(cls, faults, f_max_n, spring=None, like=None) -> "FaultBounds":
        """From ``faults`` (a ``Faults``), the robot's ``f_max_n`` (scalar or (M,)) [N] and ``spring`` (a
        ``SpringParams``; None: no tension box); numpy arrays, or float64 tensors on ``like``'s device."""
        nan = np.full(np.shape(faults.cut), np.nan)
        band = np.stack([nan, nan], -1) if faults.l_band_m is None else np.asarray(faults.l_band_m, float)
        arrays = [np.asarray(faults.cut, bool), np.asarray(faults.fix, bool), np.asarray(faults.l_fixed_m, float),
                  nan if faults.f_max_n is None else np.asarray(faults.f_max_n, float), band[..., 0], band[..., 1],
                  np.asarray(f_max_n, float)]
        springs = [None, None] if spring is None else [np.broadcast_to(np.asarray(v, float), nan.shape[-1:])
                                                       for v in (spring.k_n, spring.alpha_per_m)]
        if like is not None:
            torch = sys.modules["torch"]
            as_t = lambda a: None if a is None else torch.as_tensor(  # noqa: E731
                np.array(a), dtype=torch.bool if a.dtype == bool else torch.float64, device=like.device)
            arrays, springs = [as_t(a) for a in arrays], [as_t(a) for a in springs]
        return cls.from_tensors(*arrays, *springs)

    def on_host(self) -> "FaultBounds":
        """The same bounds as numpy arrays (host copies of tensors; itself when already numpy)."""
        if namespace(self.f_limit_n) is np:
            return self
        as_np = lambda a: a.detach().cpu().numpy() if namespace(a) is not np and a is not None else a  # noqa: E731
        return FaultBounds(*(as_np(getattr(self, name)) for name in self.__dataclass_fields__))

    def take(self, rows) -> "FaultBounds":
        """The cases ``rows`` (indices or a (B,) bool mask; the spring is shared)."""
        return FaultBounds(*(getattr(self, name)[rows] for name in list(self.__dataclass_fields__)[:8]),
                           self.k_n, self.alpha_per_m)

    # ------------------------------------------------------------------ the bounds
    @cached_property
    def f_lo_n(self):
        """(B, M) [N]: 0 (a muscle only pulls)."""
        return fill(self.f_limit_n, 0.0)

    @cached_property
    def f_hi_n(self):
        """(B, M) [N]: 0 where cut, else the muscle's limit."""
        return where(self.cut, 0.0, self.f_limit_n)

    @cached_property
    def l_lo_m(self):
        """(B, M) [m]: a band's lo, -inf where free."""
        return where(self.band, self.band_lo_m, -np.inf)

    @cached_property
    def l_hi_m(self):
        """(B, M) [m]: the lower of a jam's l_fixed and a band's hi, +inf where free."""
        return minimum(where(self.jam, self.l_fixed_m, np.inf), where(self.band, self.band_hi_m, np.inf))

    @cached_property
    def length_bounds_set(self):
        """``(has_lo, lo, has_hi, hi, any_lo, any_hi)``: where a motor-length bound is set (B, M) and its value [m]
        (0 where free), and whether any is set at all (numpy; torch: True, no data-dependent branch in a traced
        graph), once per bounds: every ``tension_box`` and ``motor_length_m`` call (a controller's every tick) reads
        them, and skips the arithmetic of a kind of bound no muscle has (its answer there is the other operand)."""
        has_lo, has_hi = isfinite(self.l_lo_m), isfinite(self.l_hi_m)
        traced = namespace(has_lo) is not np
        return (has_lo, where(has_lo, self.l_lo_m, 0.0), has_hi, where(has_hi, self.l_hi_m, 0.0),
                traced or bool(has_lo.any()), traced or bool(has_hi.any()))

    def tension_box(self, l_geo_m):
        """``(lo, hi)`` (B, M) [N]: the tensions that meet every bound at muscle lengths ``l_geo_m`` (module
        docstring); lo > hi where they cross (then no tension meets them). New arrays (tensors) either way."""
        if self.k_n is None:
            raise ValueError("FaultBounds without a spring has no tension box")
        has_lo, l_lo, has_hi, l_hi, any_lo, any_hi = self.length_bounds_set
        whole = np.shape(l_geo_m) != self.f_lo_n.shape  # lengths that broadcast the bounds: no skip
        with np.errstate(over="ignore", invalid="ignore"):  # an absurd stretch overflows to inf: crossed, as it should
            lo = maximum(self.f_lo_n, where(has_hi, spring_tension_n(l_geo_m - l_hi, self.k_n, self.alpha_per_m),
                                            0.0)) if any_hi or whole else self.f_lo_n.copy()  # max(0, 0)
            hi = minimum(self.f_hi_n, where(has_lo, spring_tension_n(l_geo_m - l_lo, self.k_n, self.alpha_per_m),
                                            np.inf)) if any_lo or whole else self.f_hi_n.copy()  # min(f_hi, inf)
            return lo, hi

    def motor_length_m(self, l_geo_m, f_n):
        """``l_motor = l_geo - delta(f)`` (B, M) [m]: the motor lengths that give tensions ``f_n`` at muscle lengths
        ``l_geo_m`` through the spring, within the length bounds: a slack wire's (f <= 0) motor may stand anywhere
        above l_geo, so at least at its band's lower end; never above ``l_hi_m`` (a tension in the box keeps it
        there, but for exp/log1p's rounding). NaN tensions give NaN. The one rule of the commands (numpy, torch,
        the exported graph)."""
        if self.k_n is None:
            raise ValueError("FaultBounds without a spring has no motor lengths")
        has_lo, _, _, _, any_lo, any_hi = self.length_bounds_set
        l_motor = l_geo_m - spring_elongation_m(f_n, self.k_n, self.alpha_per_m)
        if any_lo:
            l_motor = where((f_n <= 0.0) & has_lo, maximum(l_motor, self.l_lo_m), l_motor)
        return minimum(l_motor, self.l_hi_m) if any_hi or l_motor.shape != self.l_hi_m.shape else l_motor  # min(l, inf)

    def broken(self, l_motor_m, f_n):
        """``(length_m, cut_n)`` (B, M): how far ``l_motor_m`` lies outside its length bounds (a jam, a band) [m] and
        how hard a cut muscle pulls [N] (``f_n`` as sent: clipped to 0 <= f <= f_limit); 0 where nothing is broken."""
        with np.errstate(invalid="ignore"):  # NaN commands give NaN; +-inf where free gives 0
            length = maximum(l_motor_m - self.l_hi_m, self.l_lo_m - l_motor_m)
            length = np.maximum(length, 0.0) if namespace(length) is np else length.clamp_min(0.0)
        return length, where(self.cut, f_n, 0.0)

    def invalid(self, f_max_n=None):
        """(B,) bool: the cases that break a rule of ``fault_rules`` (``Faults.validate`` refuses them)."""
        bad = None
        for _, mask in fault_rules(self.cut, self.jam, self.l_fixed_m, where(self.weak, self.f_limit_n, np.nan),
                                   self.band_lo_m, self.band_hi_m, f_max_n):
            bad = mask if bad is None else bad | mask
        return bad.any(1)


__all__ = ["FaultBounds"]
