"""The box least squares: the tensions closest to balancing a torque that no tension in the box may balance.

Per case ``min_f ||G^T f + tau||^2 + reg s ||f - f_ref||^2`` over ``lo <= f <= hi``, ``s`` the case's mean squared
moment arm (so ``reg`` is dimensionless): the box QP of ``solvers.problem`` with ``w = reg s``, solved by the dual
Newton (``solvers.newton``). torch only.
"""
from __future__ import annotations

import torch

from .newton import NEWTON_TOL_NM, NewtonResult, dual_newton

LS_REG = 1e-6  # the default reg: the torque balance first, f_ref only to pick among equal residuals


def least_squares_weight(G: torch.Tensor, reg: float) -> torch.Tensor:
    """(B,) ``reg s`` [m^2] with ``s`` each case's mean squared moment arm (so ``reg`` is dimensionless)."""
    return reg * torch.clamp((G * G).flatten(1).sum(1) / G.shape[1], min=1e-300)


def box_least_squares(G, tau, f_ref, lo, hi, reg: float = LS_REG) -> NewtonResult:
    """The module docstring's problem per case (tensors as ``dual_newton`` takes them, ``lo <= hi``)."""
    return dual_newton(G, tau, f_ref, lo, hi, least_squares_weight(G, reg), NEWTON_TOL_NM)
