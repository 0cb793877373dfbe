"""What the diagnosis assumes about its readings: the sensors' noise, the learned body's own error, and its
decision thresholds. Every default is a documented choice (README "When you don't know what broke")."""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Optional

import numpy as np

from ..errors import BodySchemaInputError


@dataclass(frozen=True)
class SensorNoise:
    """One standard deviation of each sensor's noise, SI units.

    q_rad: joint angle readings (default 1 mrad); l_m: motor encoders (default 0.05 mm); f_frac: load cells, as a
    fraction of each muscle's f_max (default 0.5 %).
    """

    q_rad: float = 1e-3
    l_m: float = 5e-5
    f_frac: float = 0.005

    def __post_init__(self):
        for name in ("q_rad", "l_m", "f_frac"):
            value = getattr(self, name)
            if isinstance(value, bool) or not 0.0 < float(value) < math.inf:
                raise BodySchemaInputError(f"SensorNoise.{name}={value!r} must be a finite number > 0")


@dataclass(frozen=True)
class BodyError:
    """The learned body's own error, one standard deviation: ``length_m`` (M,) of each muscle's path length and
    ``torque_nm`` (N,) of the torque balance at each joint (moment arms and gravity), measured on held-out healthy
    samples (``calibrate_body_error``). The true body (a MuJoCo model) has none: ``BodyError.exact(M, N)``."""

    length_m: np.ndarray
    torque_nm: np.ndarray

    @classmethod
    def exact(cls, n_muscles: int, n_joints: int) -> "BodyError":
        return cls(np.zeros(n_muscles), np.zeros(n_joints))


@dataclass(frozen=True)
class Thresholds:
    """The diagnosis's decisions, in standard deviations (z) or chi-square units.

    z_encoder: an encoder reading this many sigma from its command is a motor that did not follow it (default 6:
        one false flag in ~5e8 readings).
    z_observed: a fault is observable in a log when its effect on the readings reaches this many sigma (default 5);
        a cut, which the log must tell from a healthy pull, when it reaches ``z_observed + sqrt(margin)`` sigma (9):
        its evidence then falls on the right side of the margin but for a three-sigma draw of the noise.
    margin: an explanation is preferred over another when its chi-square is lower by this much; within it, both fit
        (``ambiguous``) (default 16, four sigma).
    per_fault: the chi-square price of each fault an explanation adds (default 9): a simpler explanation wins ties.
    fit_p: an explanation fits the log when its chi-square lies below this quantile of the chi-square law of the
        log's degrees of freedom (default 1 - 1e-6).
    max_faults: the most faults one explanation holds beyond the encoders' (default 2).
    """

    z_encoder: float = 6.0
    z_observed: float = 5.0
    margin: float = 16.0
    per_fault: float = 9.0
    fit_p: float = 1.0 - 1e-6
    max_faults: int = 2

    @property
    def decisive(self) -> float:
        """The chi-square a cut's expected evidence must reach for the log to decide it (``z_observed``)."""
        return (self.z_observed + math.sqrt(self.margin)) ** 2

    def fit_limit(self, dof: np.ndarray) -> np.ndarray:
        """The chi-square a fitting explanation stays below, per log (``dof`` (C,) degrees of freedom)."""
        return chi2_quantile(self.fit_p, dof)


def chi2_quantile(p: float, dof) -> np.ndarray:
    """The ``p`` quantile of the chi-square law with ``dof`` degrees of freedom (Wilson-Hilferty's cube of a normal:
    within 1 % of the exact value for dof >= 2 at the tails used here)."""
    k = np.maximum(np.asarray(dof, float), 1.0)
    z = _normal_quantile(p)
    return k * (1.0 - 2.0 / (9.0 * k) + z * np.sqrt(2.0 / (9.0 * k))) ** 3


@functools.lru_cache(maxsize=64)
def _normal_quantile(p: float) -> float:
    """The standard normal quantile (bisection on erf: exact to 1e-12; a few settings, cached)."""
    lo, hi = -40.0, 40.0
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if 0.5 * (1.0 + math.erf(mid / math.sqrt(2.0))) < p else (lo, mid)
    return 0.5 * (lo + hi)


def check_noise(noise: Optional[SensorNoise]) -> SensorNoise:
    if noise is None:
        return SensorNoise()
    if not isinstance(noise, SensorNoise):
        raise BodySchemaInputError(f"noise={noise!r} must be a SensorNoise")
    return noise
