"""MuJoCo's muscle activation dynamics, batched, and its inverse: the excitations (controls) that take activations
``a0`` to ``a1`` over one frame step.

MuJoCo's ``mju_muscleDynamics`` (Millard et al. 2013): with ``c = clip(ctrl, 0, 1)`` and ``a~ = clip(act, 0, 1)``,

    act_dot = (c - act) / tau,   tau_act = t_a (0.5 + 1.5 a~),   tau_deact = t_d / (0.5 + 1.5 a~),

``tau = tau_act`` where ``c > act`` else ``tau_deact`` (``tausmooth = 0``), or with ``tausmooth = w > 0`` the smooth
switch ``tau = tau_deact + (tau_act - tau_deact) S((c - act) / w + 0.5)``, ``S`` MuJoCo's quintic ``mju_sigmoid``.
Every MuJoCo integrator advances ``act`` by Euler: ``act += h act_dot`` at the model's timestep ``h`` (no clamp
without ``actlimited``). A frame step ``dt`` is ``n = round(dt / h)`` such steps of ``dt / n`` with the control held
(MuJoCo's own when ``dt`` is a multiple of ``h``). numpy only.
"""
from __future__ import annotations

import numpy as np

from .muscles import MJMINVAL

# an excitation outside [0, 1] by less than this is the rounding of one that lies at the end (a1 - a0 ~1e-16 times
# tau / h <= ~100), not a clipped one
CLIP_TOL = 1e-12
BISECTIONS = 60  # halvings of [0, 1] for the excitation where no closed form exists: below 1e-17, float64's floor


def _sigmoid(x):
    """MuJoCo's ``mju_sigmoid``: 0 below 0, 1 above 1, the quintic smoothstep between."""
    x = np.clip(x, 0.0, 1.0)
    return x ** 3 * (x * (6.0 * x - 15.0) + 10.0)


def _time_constants(act, dynprm):
    """``(tau_act, tau_deact)`` (B, M) [s] at activations ``act`` (B, M)."""
    a = np.clip(act, 0.0, 1.0)
    return dynprm[:, 0] * (0.5 + 1.5 * a), dynprm[:, 1] / (0.5 + 1.5 * a)


def activation_rate(ctrl, act, dynprm) -> np.ndarray:
    """(B, M) ``act_dot`` [1/s] of MuJoCo's ``mju_muscleDynamics`` at controls ``ctrl`` and activations ``act``
    (B, M); ``dynprm`` (M, 3): ``tau_act``, ``tau_deact`` [s], ``tausmooth``."""
    excess = np.clip(ctrl, 0.0, 1.0) - act
    tau_act, tau_deact = _time_constants(act, dynprm)
    width = dynprm[:, 2]
    hard = np.where(excess > 0, tau_act, tau_deact)
    smooth = tau_deact + (tau_act - tau_deact) * _sigmoid(excess / np.maximum(width, MJMINVAL) + 0.5)
    return excess / np.maximum(MJMINVAL, np.where(width < MJMINVAL, hard, smooth))


def advance(ctrl, act, dynprm, dt_s, steps) -> np.ndarray:
    """(B, M) activations after ``steps`` (B,) Euler steps of ``dt_s / steps`` (B,) [s] with ``ctrl`` held."""
    h, steps = np.asarray(dt_s, float) / steps, np.asarray(steps)
    act = np.array(act, float)
    for k in range(int(steps.max(initial=0))):
        moving = (k < steps)[:, None]
        act = np.where(moving, act + h[:, None] * activation_rate(ctrl, act, dynprm), act)
    return act


def excitation(a0, a1, dynprm, dt_s, timestep_s: float) -> tuple[np.ndarray, np.ndarray]:
    """``(control (B, M), clipped (B, M))``: the excitation in [0, 1] that MuJoCo's activation dynamics turn from
    ``a0`` into ``a1`` (B, M) over frame steps ``dt_s`` (B,) [s] at the model's ``timestep_s``; ``clipped`` where none
    in [0, 1] reaches ``a1`` (the nearest end is returned). NaN where ``a0`` or ``a1`` is NaN."""
    dt_s = np.broadcast_to(np.asarray(dt_s, float), (len(a0),))
    steps = np.maximum(1, np.round(dt_s / timestep_s)).astype(int)
    if (steps == 1).all() and (dynprm[:, 2] < MJMINVAL).all():
        control = _one_hard_step(a0, a1, dynprm, dt_s)
    else:
        control = _bisection(a0, a1, dynprm, dt_s, steps)
    clipped = (control < -CLIP_TOL) | (control > 1.0 + CLIP_TOL)
    return np.clip(control, 0.0, 1.0), clipped


def _one_hard_step(a0, a1, dynprm, dt_s):
    """The closed form for one Euler step with the hard switch: ``c = a0 + (a1 - a0) tau / h`` with the branch the
    sign of ``a1 - a0`` picks (may lie outside [0, 1]: ``excitation`` clips and flags it)."""
    rate = (a1 - a0) / dt_s[:, None]
    tau_act, tau_deact = _time_constants(a0, dynprm)
    return a0 + rate * np.where(rate > 0, tau_act, tau_deact)


def _bisection(a0, a1, dynprm, dt_s, steps):
    """The excitation by bisection on [0, 1] (``advance`` rises with it); -1 or 2 where ``a1`` lies below what 0
    reaches or above what 1 does, so that ``excitation`` flags it."""
    lo, hi = np.zeros_like(a0), np.ones_like(a0)
    below = a1 < advance(lo, a0, dynprm, dt_s, steps)
    above = a1 > advance(hi, a0, dynprm, dt_s, steps)
    for _ in range(BISECTIONS):
        mid = 0.5 * (lo + hi)
        short = advance(mid, a0, dynprm, dt_s, steps) < a1
        lo, hi = np.where(short, mid, lo), np.where(short, hi, mid)
    control = 0.5 * (lo + hi)
    return np.where(below, -1.0, np.where(above, 2.0, np.where(np.isnan(a0 + a1), np.nan, control)))
