"""A log's readings beside the body's predictions: the learned (or true) body evaluated at every measured posture,
and the spring constants per muscle, as the two stages of the diagnosis use them."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..sim.spring import SpringParams, elongation_from_tension, tension_from_elongation
from .log import SensorLog
from .noise import BodyError, SensorNoise


@dataclass
class Readings:
    """A ``SensorLog`` (C logs, R rows) with the body at its measured postures, padding rows zeroed.

    l_geo (C, R, M) [m], G (C, R, M, N) [m/rad], tau (C, R, N) [N m] of the body at each row's measured q;
    k, alpha, f_max (M,) the springs; sigma_f (M,) load-cell noise [N]; mask (C, R, 1) the real rows.
    """

    log: SensorLog
    l_geo: np.ndarray
    G: np.ndarray
    tau: np.ndarray
    spring: SpringParams
    noise: SensorNoise
    error: BodyError
    sigma_f: np.ndarray
    mask: np.ndarray

    def tension(self, motor_m: np.ndarray) -> np.ndarray:
        """(C, R, M) spring tension [N] of motors at ``motor_m`` at the measured postures (0 where slack)."""
        return tension_from_elongation(self.l_geo - motor_m, self.spring)

    def stiffness(self, f_n: np.ndarray) -> np.ndarray:
        """(C, R, M) d f / d l_geo [N/m] of a spring pulling ``f_n`` (0 where it is slack: f = 0)."""
        alpha, k = np.asarray(self.spring.alpha_per_m, float), np.asarray(self.spring.k_n, float)
        return alpha * (f_n + k) * (f_n > 0.0)

    def motor_from_tension(self, f_n: np.ndarray) -> np.ndarray:
        """(C, R, M) the motor length [m] at which the spring pulls ``f_n`` at the measured postures."""
        return self.l_geo - elongation_from_tension(f_n, self.spring)

    def arm_norm2(self) -> np.ndarray:
        """(C, R, M) squared moment-arm norm [m^2/rad^2]: a joint reading's noise moves a length by G dq."""
        return np.einsum("crmn,crmn->crm", self.G, self.G)

    def prediction_var(self, stiffness: np.ndarray) -> np.ndarray:
        """(C, R, M) variance [N^2] of a predicted tension: the joint reading's noise and the body's length error,
        both through the spring's stiffness."""
        return stiffness ** 2 * (self.noise.q_rad ** 2 * self.arm_norm2() + self.error.length_m ** 2)


def readings(log: SensorLog, body, spring: SpringParams, noise: SensorNoise, error: BodyError) -> Readings:
    """The body (``body(q (B, N)) -> (l_geo, G, tau)``, float64 arrays) at every real row's measured posture."""
    c, r = np.nonzero(log.rows)
    l_geo_rows, G_rows, tau_rows = body(log.q_rad[c, r])
    C, R = log.rows.shape
    l_geo, G, tau = np.zeros((C, R) + l_geo_rows.shape[1:]), np.zeros((C, R) + G_rows.shape[1:]), np.zeros(
        (C, R) + tau_rows.shape[1:])
    l_geo[c, r], G[c, r], tau[c, r] = l_geo_rows, G_rows, tau_rows
    sigma_f = noise.f_frac * np.broadcast_to(np.asarray(spring.f_max_n, float), (len(log.muscles),))
    return Readings(log, l_geo, G, tau, spring, noise, error, sigma_f, log.rows[..., None])


def masked_mean(values: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(C, M) mean over the rows where ``mask`` (C, R, M); NaN where no row is."""
    count = mask.sum(1)
    total = np.where(mask, values, 0.0).sum(1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(count > 0, total / np.maximum(count, 1), np.nan)


def masked_spread(values: np.ndarray, mask: np.ndarray, centre: np.ndarray, scale) -> np.ndarray:
    """(C, M) the largest ``|values - centre| / scale`` over the rows where ``mask`` (0 where no row is)."""
    with np.errstate(invalid="ignore"):
        return np.where(mask, np.abs(values - centre[:, None]) / scale, 0.0).max(1)
