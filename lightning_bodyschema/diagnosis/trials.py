"""Trials of the diagnosis: random faults, the logs a robot holding healthy commands under them would record
(simulated in MuJoCo, ``sensors``), and how the diagnosis scores against the truth.

A log holds 1 to ``max_rows`` postures, each a reachable q_ref with the healthy command for it, the same faults
throughout. Faults are drawn so that each binds on the log's first row: a cut muscle; a jam ``0.5-8 mm`` below the
command; a weak limit ``30-80 %`` of the commanded tension; a band whose lower edge lies ``0.5-5 mm`` above the
command or whose upper edge lies as far below it, ``2-20 mm`` wide.

A fault is **identifiable** in a log when the diagnosis run on the true body (MuJoCo's lengths, moment arms and
gravity) with the same noise settings, on the noise-free readings, names exactly the true faults with status
``identified``: the limit any body model can reach. Scores are given over identifiable logs, and the counts of
the others beside them.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..faults import Faults
from ..sim.settle import SettleParams
from ..status import Status
from .explain import diagnose
from .log import SensorLog
from .noise import BodyError, SensorNoise, Thresholds
from .result import BAND, CUT, HEALTHY, JAM, KINDS, WEAK
from .sensors import noisy, true_readings

FAULT_KINDS = ("cut", "jam", "weak", "band")
HOLD_S = 10.0  # a held posture's simulated time: a learned command drifts slowly along an arm's soft directions


@dataclass
class Trial:
    """Logs with their truth: ``truth`` (C, M) kind indices, ``faults`` (per log), the flat rows' ``log_rows``
    (S,) log index, the noise-free ``readings`` and which logs came to rest in every row (``at_rest`` (C,))."""

    truth: np.ndarray
    faults: Faults
    q_ref: np.ndarray
    l_cmd: np.ndarray
    f_cmd: np.ndarray
    log_rows: np.ndarray
    readings: object
    at_rest: np.ndarray


def draw_trial(model, spring, pool, n_logs: int, n_faults: int, rng: np.random.Generator, max_rows: int = 5,
               kinds=FAULT_KINDS, params: SettleParams = SettleParams(max_time_s=HOLD_S)) -> Trial:
    """``n_logs`` logs of 1..max_rows postures drawn from ``pool = (q (P, N), l_cmd (P, M), f_cmd (P, M))`` (reachable
    postures with the healthy command for each), ``n_faults`` (0, 1, 2) faults per log of ``kinds``."""
    q_pool, l_pool, f_pool = pool
    n_rows = rng.integers(1, max_rows + 1, n_logs)
    log_rows = np.repeat(np.arange(n_logs), n_rows)
    pick = rng.integers(0, len(q_pool), len(log_rows))
    q_ref, l_cmd, f_cmd = q_pool[pick], l_pool[pick], f_pool[pick]
    first = np.r_[0, np.cumsum(n_rows)[:-1]]
    truth, faults = _draw_faults(l_cmd[first], f_cmd[first], n_faults, kinds, rng)
    readings = true_readings(model, spring, q_ref, l_cmd, f_cmd, faults.take(log_rows), params)
    at_rest = np.bincount(log_rows, readings.at_rest, n_logs) == n_rows
    return Trial(truth, faults, q_ref, l_cmd, f_cmd, log_rows, readings, at_rest)


def _draw_faults(l_cmd, f_cmd, n_faults, kinds, rng):
    """(truth (C, M), Faults) with ``n_faults`` distinct faulty muscles per log, binding on the given command."""
    C, M = l_cmd.shape
    truth = np.full((C, M), HEALTHY)
    muscles = np.argsort(rng.random((C, M)), 1)[:, :n_faults]
    kind_of = {name: KINDS.index(name) for name in FAULT_KINDS}
    picks = rng.choice([kind_of[k] for k in kinds], (C, n_faults))
    truth[np.arange(C)[:, None], muscles] = picks
    mm = 1e-3
    l_fixed = np.where(truth == JAM, l_cmd - rng.uniform(0.5, 8.0, (C, M)) * mm, np.nan)
    f_weak = np.where(truth == WEAK, np.maximum(f_cmd, 0.0) * rng.uniform(0.3, 0.8, (C, M)), np.nan)
    gap, width = rng.uniform(0.5, 5.0, (C, M)) * mm, rng.uniform(2.0, 20.0, (C, M)) * mm
    lower = rng.random((C, M)) < 0.5  # the command lies below the band (its lower edge binds), else above it
    lo = np.where(lower, l_cmd + gap, l_cmd - gap - width)
    band = np.where((truth == BAND)[..., None], np.stack([lo, lo + width], -1), np.nan)
    faults = Faults(truth == CUT, truth == JAM, l_fixed, f_weak if (truth == WEAK).any() else None,
                    band if (truth == BAND).any() else None)
    return truth, faults


def trial_log(trial: Trial, model, spring, noise: SensorNoise, rng, has_f=None, noise_free: bool = False) -> SensorLog:
    """The trial's ``SensorLog`` (noisy readings, or the noise-free ones)."""
    r = trial.readings
    q, l_m, f = (r.q_rad, r.l_m, np.where(has_f, r.f_n, np.nan) if has_f is not None else r.f_n) if noise_free \
        else noisy(r, spring, noise, rng, has_f)
    return SensorLog.from_rows(model.joint_names, model.muscle_names, q, l_m, trial.l_cmd, trial.f_cmd, f,
                               trial.log_rows)


def oracle_diagnosis(trial: Trial, model, spring, noise: SensorNoise, thresholds: Thresholds, has_f=None):
    """The true body's diagnosis of the noise-free logs: what the logs themselves show (module docstring)."""
    return diagnose(trial_log(trial, model, spring, noise, None, has_f, noise_free=True), model.kinematics, spring,
                    noise, BodyError.exact(model.n_muscles, model.n_joints), thresholds)


def identifiable(trial: Trial, model, spring, noise: SensorNoise, thresholds: Thresholds, has_f=None) -> np.ndarray:
    """(C,) bool: the true body's diagnosis of the noise-free log names exactly the true faults (module docstring)."""
    return right(oracle_diagnosis(trial, model, spring, noise, thresholds, has_f), trial.truth)


def right(diagnosis, truth: np.ndarray) -> np.ndarray:
    """(C,) bool: status ``identified`` (or ``no_fault`` for a healthy truth) with every muscle's kind right."""
    healthy = (truth == HEALTHY).all(1)
    status_ok = np.where(healthy, diagnosis.status == Status.NO_FAULT, diagnosis.status == Status.IDENTIFIED)
    return status_ok & (diagnosis.kind == truth).all(1)
