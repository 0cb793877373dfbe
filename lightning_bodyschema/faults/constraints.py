"""Fault constraints and the adaptation loss (paper eq:muscle-cut, eq:muscle-fix, eq:latent-opt).

Beyond the paper: a weakened muscle is ``MaxTension`` with a lowered per-case limit, and a motor
confined to a length band is ``LengthBand``.

Each constraint is one small class over a batch of cases, each case with its own muscles (masks):
``loss`` gives the penalty per case (torch, differentiable), ``violation`` the worst breach in SI units.
The adaptation loss is the weighted sum over the constraints plus the tension bounds 0 <= f <= f_max.

Residuals are divided by per-muscle scales before squaring: ``l_scale`` [m] and ``f_scale`` [N].
With scales of 1 this is the paper's loss in SI units; with the data's standard deviations every term
is measured in the same unit (one spread of the healthy data), which the default adaptation uses.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch


def _relu_sq(x):
    return torch.relu(x).square()


@dataclass
class Constraint:
    """Base: a per-case, per-muscle mask ``mask (B, M)`` and the loss weight's name in ``AdaptWeights``."""

    mask: torch.Tensor
    weight_name = ""

    def loss(self, l_motor_m, f_n, l_scale, f_scale) -> torch.Tensor:
        raise NotImplementedError

    def violation(self, l_motor_m, f_n) -> torch.Tensor:
        """Worst breach per case (B,), in N or m; 0 where the case has no such constraint."""
        raise NotImplementedError


@dataclass
class Rupture(Constraint):
    """Cut muscle: f_i = 0 (eq:muscle-cut)."""

    weight_name = "c_cut"

    def loss(self, l_motor_m, f_n, l_scale, f_scale):
        return (self.mask * (f_n / f_scale).square()).sum(-1)

    def violation(self, l_motor_m, f_n):
        return (self.mask * f_n.abs()).amax(-1)


@dataclass
class Jam(Constraint):
    """Jammed motor: l_motor_j <= l_fixed_j (eq:muscle-fix); ``l_fixed_m (B, M)``, ignored off the mask."""

    l_fixed_m: torch.Tensor = None
    weight_name = "c_fix"

    def _excess(self, l_motor_m):
        return torch.where(self.mask, l_motor_m - torch.nan_to_num(self.l_fixed_m), torch.zeros_like(l_motor_m))

    def loss(self, l_motor_m, f_n, l_scale, f_scale):
        return _relu_sq(self._excess(l_motor_m) / l_scale).sum(-1)

    def violation(self, l_motor_m, f_n):
        return torch.relu(self._excess(l_motor_m)).amax(-1)


@dataclass
class MinTension(Constraint):
    """A wire cannot push: f >= f_min (0 by default)."""

    f_min_n: torch.Tensor = None
    weight_name = "c_fmin"

    def loss(self, l_motor_m, f_n, l_scale, f_scale):
        return (self.mask * _relu_sq((self.f_min_n - f_n) / f_scale)).sum(-1)

    def violation(self, l_motor_m, f_n):
        return (self.mask * torch.relu(self.f_min_n - f_n)).amax(-1)


@dataclass
class MaxTension(Constraint):
    """Motor limit: f <= f_max (a weakened muscle lowers its f_max)."""

    f_max_n: torch.Tensor = None
    weight_name = "c_fmax"

    def loss(self, l_motor_m, f_n, l_scale, f_scale):
        return (self.mask * _relu_sq((f_n - self.f_max_n) / f_scale)).sum(-1)

    def violation(self, l_motor_m, f_n):
        return (self.mask * torch.relu(f_n - self.f_max_n)).amax(-1)


@dataclass
class LengthBand(Constraint):
    """Motor confined to a band: l_lo_j <= l_motor_j <= l_hi_j; ``l_lo_m``, ``l_hi_m (B, M)``, ignored off the mask.

    A jam is the one-sided case (l_hi = l_fixed, l_lo = -inf); a band also stops the motor reeling in.
    """

    l_lo_m: torch.Tensor = None
    l_hi_m: torch.Tensor = None
    weight_name = "c_band"

    def _excess(self, l_motor_m):
        """Distance outside the band per muscle [m] (0 inside it and off the mask)."""
        below = torch.nan_to_num(self.l_lo_m) - l_motor_m
        above = l_motor_m - torch.nan_to_num(self.l_hi_m)
        return torch.where(self.mask, torch.relu(torch.maximum(below, above)), torch.zeros_like(l_motor_m))

    def loss(self, l_motor_m, f_n, l_scale, f_scale):
        return (self._excess(l_motor_m) / l_scale).square().sum(-1)

    def violation(self, l_motor_m, f_n):
        return self._excess(l_motor_m).amax(-1)


@dataclass(frozen=True)
class AdaptWeights:
    """Loss weights C^adapt; defaults are the paper's (section IV-A). ``c_band`` (not in the paper) is c_fix's value."""

    c_cut: float = 0.01
    c_fix: float = 1.0
    c_fmin: float = 0.01
    c_fmax: float = 0.01
    c_band: float = 1.0


def adaptation_loss(constraints, weights: AdaptWeights, l_motor_m, f_n, l_scale=1.0, f_scale=1.0) -> torch.Tensor:
    """L_adapt per case (B,) (eq:latent-opt): the weighted sum of every constraint's penalty."""
    total = torch.zeros(f_n.shape[:-1], dtype=f_n.dtype, device=f_n.device)
    for constraint in constraints:
        total = total + getattr(weights, constraint.weight_name) * constraint.loss(l_motor_m, f_n, l_scale, f_scale)
    return total
