"""What a faulted robot's sensors read, simulated: each command dropped into MuJoCo (``sim.settle``, every fault
kind), then the readings of the sensor model at the rest posture, with Gaussian noise.

The sensor model (the one ``diagnose`` assumes): length-controlled motors hold their command; a cut muscle's load
cell reads 0 and its encoder the command; a jammed winch's encoder reads ``min(l_cmd, l_fixed)``; a banded winch
``clip(l_cmd, lo, hi)``; a weak motor slips at its limit (tension ``f_w``, encoder ``l_geo(q) - delta(f_w)``); the
joints read where the body rests. numpy and MuJoCo only.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from ..evaluation.cases import FaultCases, condition_of
from ..faults import Faults
from ..sim.settle import SettleParams, SettleResult, settle
from ..sim.spring import SpringParams, elongation_from_tension, tension_from_elongation
from .noise import SensorNoise


@dataclass
class TrueReadings:
    """Per row (S, ...): the rest posture ``q_rad``, motor positions ``l_m`` and tensions ``f_n`` before noise, and
    the simulation's ``settle`` result (rows that did not come to rest are no held posture)."""

    q_rad: np.ndarray
    l_m: np.ndarray
    f_n: np.ndarray
    settle: SettleResult

    @property
    def at_rest(self) -> np.ndarray:
        return self.settle.settled


def true_readings(model, spring: SpringParams, q_ref, l_cmd_m, f_cmd_n, faults: Faults,
                  params: SettleParams = SettleParams()) -> TrueReadings:
    """Simulate each row's command (S, M) under its row of ``faults`` from ``q_ref`` (S, N); noise-free readings."""
    cases = FaultCases(q_ref, faults.cut, faults.fix, faults.l_fixed_m,
                       condition_of(faults.cut, faults.fix, faults.weak, faults.band), faults.f_max_n, faults.l_band_m)
    result = settle(model, l_cmd_m, f_cmd_n, cases, spring=spring, params=params)
    q = np.where(np.isfinite(result.q_settle), result.q_settle, q_ref)
    l_geo, _, _ = model.kinematics(q)
    motor, f = sensor_model(l_geo, l_cmd_m, faults, spring)
    return TrueReadings(q, motor, f, result)


def sensor_model(l_geo_m, l_cmd_m, faults: Faults, spring: SpringParams):
    """(motor [m], tension [N]) (S, M) at rest with path lengths ``l_geo_m``: the module docstring's model."""
    motor = np.where(faults.fix, np.minimum(l_cmd_m, np.nan_to_num(faults.l_fixed_m, nan=np.inf)), l_cmd_m)
    if faults.l_band_m is not None:
        band = faults.band
        motor = np.where(band, np.clip(motor, np.nan_to_num(faults.l_band_m[..., 0], nan=-np.inf),
                                       np.nan_to_num(faults.l_band_m[..., 1], nan=np.inf)), motor)
    f = tension_from_elongation(l_geo_m - motor, spring)
    if faults.f_max_n is not None:
        limit = np.where(faults.weak, faults.f_max_n, np.inf)
        slipping = f > limit
        motor = np.where(slipping, l_geo_m - elongation_from_tension(np.where(slipping, limit, 0.0), spring), motor)
        f = np.minimum(f, limit)
    return motor, np.where(faults.cut, 0.0, f)


def noisy(readings: TrueReadings, spring: SpringParams, noise: SensorNoise, rng: np.random.Generator,
          has_f: Optional[np.ndarray] = None):
    """(q, l, f) readings with noise; ``has_f`` (M,) False: that muscle has no load cell (NaN column)."""
    q, l_m, f = readings.q_rad, readings.l_m, readings.f_n
    sigma_f = noise.f_frac * np.broadcast_to(np.asarray(spring.f_max_n, float), (f.shape[1],))
    q = q + noise.q_rad * rng.standard_normal(q.shape)
    l_m = l_m + noise.l_m * rng.standard_normal(l_m.shape)
    f = f + sigma_f * rng.standard_normal(f.shape)
    if has_f is not None:
        f = np.where(has_f, f, np.nan)
    return q, l_m, f
