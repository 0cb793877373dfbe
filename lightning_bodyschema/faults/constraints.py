"""Fault constraints as intervals (paper eq:muscle-cut, eq:muscle-fix and the tension bounds of eq:latent-opt).

Each constraint states its bounds: which column group it constrains (motor length or tension), which muscles
of which cases (a (B, M) mask), the interval ``[lower, upper]`` in SI units, and the name of its weight in
``AdaptWeights``. The adaptation loss of eq:latent-opt is the weighted sum of squared distances of the command
to these intervals; ``faults.penalty`` builds it on normalized x, with its gradient.

Beyond the paper: a weakened muscle lowers ``MaxTension``'s upper bound, and a motor confined to a band is a
``LengthBand``. numpy only (the evaluation uses faults without torch).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

LENGTH, TENSION = "l_motor", "f"  # the two column groups of x = [l_motor, f]


@dataclass(frozen=True)
class AdaptWeights:
    """Loss weights C^adapt; defaults are the paper's (section IV-A). ``c_band`` (not in the paper) is c_fix's value."""

    c_cut: float = 0.01
    c_fix: float = 1.0
    c_fmin: float = 0.01
    c_fmax: float = 0.01
    c_band: float = 1.0


@dataclass
class Constraint:
    """``lower <= x <= upper`` on the masked muscles of one column group; ``mask (B, M)`` bool.

    Subclasses name their column, their weight and their bounds; ``violation`` follows from the bounds.
    """

    mask: np.ndarray
    column: ClassVar[str] = ""
    weight_name: ClassVar[str] = ""

    def bounds(self) -> tuple:
        """(lower, upper) in SI units: (B, M) arrays (ignored off the mask) or floats (+-inf: unbounded)."""
        raise NotImplementedError

    def violation(self, l_motor_m, f_n) -> np.ndarray:
        """Worst distance outside the interval per case (B,), in m or N; 0 where the case has no such constraint."""
        x = np.asarray(l_motor_m if self.column == LENGTH else f_n, float)
        lower, upper = self.bounds()
        with np.errstate(invalid="ignore"):  # NaN bounds off the mask
            outside = np.maximum(np.maximum(np.asarray(lower) - x, x - np.asarray(upper)), 0.0)
        return np.where(self.mask, outside, 0.0).max(-1)


@dataclass
class Rupture(Constraint):
    """Cut muscle: f_i = 0 (eq:muscle-cut)."""

    column: ClassVar[str] = TENSION
    weight_name: ClassVar[str] = "c_cut"

    def bounds(self):
        return 0.0, 0.0


@dataclass
class Jam(Constraint):
    """Jammed motor: l_motor_j <= l_fixed_j (eq:muscle-fix); ``l_fixed_m (B, M)`` [m], ignored off the mask."""

    l_fixed_m: np.ndarray = None
    column: ClassVar[str] = LENGTH
    weight_name: ClassVar[str] = "c_fix"

    def bounds(self):
        return -np.inf, self.l_fixed_m


@dataclass
class MinTension(Constraint):
    """A wire cannot push: f >= f_min (0); ``f_min_n (B, M)`` [N]."""

    f_min_n: np.ndarray = None
    column: ClassVar[str] = TENSION
    weight_name: ClassVar[str] = "c_fmin"

    def bounds(self):
        return self.f_min_n, np.inf


@dataclass
class MaxTension(Constraint):
    """Motor limit: f <= f_max (a weakened muscle lowers its f_max); ``f_max_n (B, M)`` [N]."""

    f_max_n: np.ndarray = None
    column: ClassVar[str] = TENSION
    weight_name: ClassVar[str] = "c_fmax"

    def bounds(self):
        return -np.inf, self.f_max_n


@dataclass
class LengthBand(Constraint):
    """Motor confined to a band: l_lo_j <= l_motor_j <= l_hi_j; ``l_lo_m``, ``l_hi_m (B, M)`` [m], ignored off the mask.

    A jam is the one-sided case (l_hi = l_fixed, l_lo = -inf); a band also stops the motor reeling in.
    """

    l_lo_m: np.ndarray = None
    l_hi_m: np.ndarray = None
    column: ClassVar[str] = LENGTH
    weight_name: ClassVar[str] = "c_band"

    def bounds(self):
        return self.l_lo_m, self.l_hi_m
