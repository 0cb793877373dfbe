"""The muscle's nonlinear spring (paper eq:nonlinear-spring, eq:muscle-elongation-inv).

``f = k (exp(alpha * delta) - 1)`` with ``delta = max(0, l_geo - l_motor)``. Works on numpy arrays
and torch tensors alike; k, alpha and f_max may be scalars or per-muscle arrays that broadcast.
"""
from __future__ import annotations

from dataclasses import dataclass

import sys

import numpy as np


@dataclass(frozen=True)
class SpringParams:
    """Spring constants; defaults are the paper's (section IV)."""

    k_n: float = 1000.0  # elastic coefficient k [N]
    alpha_per_m: float = 20.0  # nonlinearity alpha [1/m]
    f_max_n: float = 150.0  # maximum muscle tension [N]

    def __post_init__(self):
        from ..errors import BodySchemaInputError

        for name in ("k_n", "alpha_per_m", "f_max_n"):
            value = np.asarray(getattr(self, name), dtype=float)
            if not np.all(np.isfinite(value)) or np.any(value <= 0):
                raise BodySchemaInputError(f"spring parameter {name}={getattr(self, name)!r} must be finite and > 0")

    @property
    def delta_max_m(self):
        """Spring elongation at f_max: the most a taut muscle can stretch [m] (~7 mm for the paper)."""
        return elongation_from_tension(np.asarray(self.f_max_n, float), self)

    def as_dict(self) -> dict:
        return {k: np.asarray(v, float).tolist() for k, v in self.__dict__.items()}


def _xp(x):
    """numpy for arrays, torch for tensors, without importing torch here (evaluation stays light)."""
    return sys.modules["torch"] if type(x).__module__.startswith("torch") else np


def tension_from_elongation(delta_m, spring: SpringParams):
    """f = k (exp(alpha delta) - 1) for delta >= 0 (eq:nonlinear-spring); slack (delta < 0) gives 0."""
    xp = _xp(delta_m)
    delta_m = xp.clip(delta_m, 0.0, None) if xp is np else delta_m.clamp_min(0.0)
    return spring.k_n * (xp.exp(spring.alpha_per_m * delta_m) - 1.0)


def elongation_from_tension(f_n, spring: SpringParams):
    """delta = log(f/k + 1) / alpha for f >= 0 (eq:muscle-elongation-inv); negative f counts as 0."""
    xp = _xp(f_n)
    f_n = xp.clip(f_n, 0.0, None) if xp is np else f_n.clamp_min(0.0)
    return xp.log1p(f_n / spring.k_n) / spring.alpha_per_m
