"""Stage 1: motors that did not follow their command, from the encoders.

A healthy or cut muscle's motor follows its command; a jammed winch reads ``min(l_cmd, l_fixed)``; a banded one
``clip(l_cmd, lo, hi)``; a weak motor slips at its limit and reads ``l_geo(q) - delta(f_w)`` (above the command)
while it slips. So a reading below its command is a winch stopped from paying out (a jam, or a band's upper edge:
the same constraint ``l_motor <= l_fixed`` on every command the log tried; reported as a jam, the explanation with
fewer parameters), a reading above it a motor held back from reeling in: a weak motor (its tension constant, its
length following the posture) or a band's lower edge (its length constant). Where the log cannot tell those two
apart (one slipping row, or rows at the same posture) both stay: the muscle is ``ambiguous``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .readings import Readings, masked_mean, masked_spread

NONE, JAM, BAND, WEAK, WEAK_OR_BAND, UNEXPLAINED = range(6)


@dataclass
class MotorFaults:
    """Per muscle (C, M): ``kind`` (one of the codes above), the estimates ``l_fixed_m``, ``f_weak_n``, ``lo_m``,
    ``hi_m`` (NaN where not estimated), ``flagged`` (C, R, M) rows where the motor left its command, and ``score``
    the encoders' evidence (sum of squared z of the flagged rows)."""

    kind: np.ndarray
    l_fixed_m: np.ndarray
    f_weak_n: np.ndarray
    lo_m: np.ndarray
    hi_m: np.ndarray
    flagged: np.ndarray
    score: np.ndarray


def motor_faults(ev: Readings, z_limit: float) -> MotorFaults:
    """Classify every muscle's motor from its encoder against its command (module docstring)."""
    log, tol = ev.log, z_limit * ev.noise.l_m
    z = np.where(ev.mask, (log.l_m - log.l_cmd_m) / ev.noise.l_m, 0.0)
    below, above = z < -z_limit, z > z_limit
    followed = ev.mask & ~(below | above)
    hi, lo = masked_mean(log.l_m, below), masked_mean(log.l_m, above)
    with np.errstate(invalid="ignore"):
        hi_ok = (masked_spread(log.l_m, below, hi, tol) <= 1.0) & ~(followed & (log.l_cmd_m > hi[:, None] + tol)).any(1)
        lo_ok = (masked_spread(log.l_m, above, lo, tol) <= 1.0) & ~(followed & (log.l_cmd_m < lo[:, None] - tol)).any(1)
    f_weak, weak_ok = _weak_limit(ev, above, followed, z_limit)
    any_below, any_above = below.any(1), above.any(1)
    kind = np.full(any_below.shape, NONE)
    kind[any_below & ~any_above] = np.where(hi_ok, JAM, UNEXPLAINED)[any_below & ~any_above]
    kind[any_below & any_above] = np.where(hi_ok & lo_ok, BAND, UNEXPLAINED)[any_below & any_above]
    only_above = any_above & ~any_below
    verdict = np.select([weak_ok & lo_ok, weak_ok, lo_ok], [WEAK_OR_BAND, WEAK, BAND], UNEXPLAINED)
    kind[only_above] = verdict[only_above]
    score = np.where(below | above, z ** 2, 0.0).sum(1)
    nan = np.full(kind.shape, np.nan)
    return MotorFaults(kind, np.where(kind == JAM, hi, nan), np.where(np.isin(kind, (WEAK, WEAK_OR_BAND)), f_weak, nan),
                       np.where(np.isin(kind, (BAND, WEAK_OR_BAND)), lo, nan), np.where(kind == BAND, hi, nan),
                       below | above, score)


def _weak_limit(ev: Readings, slipped: np.ndarray, followed: np.ndarray, z_limit: float):
    """(f_weak (C, M) [N], consistent (C, M) bool): the limit a slipping motor held, from the spring between the body's
    path length and the encoder, and from its load cell where it has one (the two weighed by their variances);
    consistent when every slipping row shows the same tension and no row that followed its command pulled harder."""
    log = ev.log
    from_spring = ev.tension(log.l_m)
    stiffness = ev.stiffness(from_spring)
    spring_var = stiffness ** 2 * (ev.noise.l_m ** 2 + ev.noise.q_rad ** 2 * ev.arm_norm2() + ev.error.length_m ** 2)
    cell_var = np.where(log.has_f, ev.sigma_f ** 2, np.inf)
    weight = 1.0 / cell_var + 1.0 / np.maximum(spring_var, 1e-30)
    f_seen = (np.nan_to_num(log.f_n) / cell_var + from_spring / np.maximum(spring_var, 1e-30)) / weight
    sigma = np.sqrt(1.0 / weight)
    f_weak = masked_mean(f_seen * weight, slipped) / masked_mean(weight, slipped)
    # a limit lies in [0, f_max): a noisy estimate outside it is kept at the nearest valid value
    f_max = np.broadcast_to(np.asarray(ev.spring.f_max_n, float), f_weak.shape[1:])
    f_weak = np.clip(f_weak, 0.0, np.nextafter(f_max, 0.0))
    held = np.where(log.has_f, np.nan_to_num(log.f_n), ev.tension(log.l_cmd_m))
    held_sigma = np.sqrt(np.where(log.has_f, ev.sigma_f ** 2, spring_var) + 1e-30)
    with np.errstate(invalid="ignore"):
        same = masked_spread(f_seen, slipped, f_weak, sigma) <= z_limit
        above_limit = (followed & (held > f_weak[:, None] + z_limit * held_sigma)).any(1)
    return f_weak, same & ~above_limit
