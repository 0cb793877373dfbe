"""``diagnose``: which muscles failed, and how, from a sensor log and a body (learned or true).

Stage 1 (``motors``) reads the encoders against the commands: jams, bands and slipping weak motors. Stage 2
(``cuts``) finds cut muscles: from each muscle's load cell where it has one, else from the torque balance at the
measured posture. The whole log is then ``no_fault``, ``identified`` (one explanation), ``ambiguous`` (two or more
fit within the noise: it does not guess) or ``not_identifiable`` (the log is no healthy body's and nothing the
diagnosis knows explains it). A fault that leaves no trace in the log (a cut muscle slack in every row, a jam never
asked to pay out) cannot be seen: such a log reads ``no_fault``, and ``Diagnosis.observed`` says which muscles'
cuts the log could have shown.
"""
from __future__ import annotations

from itertools import product
from typing import Optional

import numpy as np

from ..faults import Faults
from ..sim.spring import SpringParams
from ..status import Status, status_array
from .cuts import balance_cuts, load_cell_cuts
from .log import SensorLog
from .motors import BAND as M_BAND, JAM as M_JAM, UNEXPLAINED, WEAK as M_WEAK, WEAK_OR_BAND, motor_faults
from .noise import BodyError, SensorNoise, Thresholds
from .readings import readings
from .result import BAND, CUT, HEALTHY, JAM, WEAK, Diagnosis, fault_request, merge_requests

OPEN_EDGE_M = 1.0  # a band edge the log never reached is put this far beyond the reached one: it binds nothing
MAX_CANDIDATES = 16


def diagnose(log: SensorLog, body, spring: SpringParams, noise: Optional[SensorNoise] = None,
             error: Optional[BodyError] = None, thresholds: Optional[Thresholds] = None) -> Diagnosis:
    """Diagnose every log of ``log`` on ``body`` (``body(q_rad (B, N)) -> (l_geo [m], G [m/rad], tau [N m])``, float64
    arrays, ``-G^T f = tau`` at rest) with the robot's ``spring``; ``error``: the body's own (None: exact)."""
    noise, thr = noise or SensorNoise(), thresholds or Thresholds()
    error = error or BodyError.exact(len(log.muscles), len(log.joints))
    ev = readings(log, body, spring, noise, error)
    motors = motor_faults(ev, thr.z_encoder)
    cells = load_cell_cuts(ev, motors, thr)
    balance = balance_cuts(ev, motors, cells, thr)
    kind = np.full(motors.kind.shape, HEALTHY)
    for code, value in ((M_JAM, JAM), (M_WEAK, WEAK), (M_BAND, BAND)):
        kind[motors.kind == code] = value
    in_set = _cut_sets(balance.sets, kind.shape[1])
    agreed = balance.tested[:, None] & balance.fits.any(1)[:, None] & np.all(in_set | ~balance.close[..., None], 1)
    kind[cells.cut | agreed] = CUT
    status = _status(kind, motors, cells, balance)
    score = np.where(motors.flagged.any(1), motors.score, np.where(ev.log.has_f, cells.score, balance.evidence))
    observed = motors.flagged.any(1) | cells.observed | balance.observed
    band = np.stack([motors.lo_m, motors.hi_m], -1)
    faults = _certain_faults(kind, motors, status, spring)
    out = Diagnosis(status, kind, score, observed, motors.l_fixed_m, motors.f_weak_n, band, faults, list(log.muscles),
                    [[] for _ in range(len(kind))], log.cases)
    for c in np.flatnonzero(status == Status.AMBIGUOUS):
        out.candidates[c] = _candidates(c, faults, motors, cells, balance, in_set, log.muscles)
    return out


def _status(kind, motors, cells, balance) -> np.ndarray:
    unexplained = (motors.kind == UNEXPLAINED).any(1) | (balance.tested & ~balance.fits.any(1))
    ambiguous = (motors.kind == WEAK_OR_BAND).any(1) | cells.ambiguous.any(1) | (balance.close.sum(1) > 1)
    faulted = (kind != HEALTHY).any(1)
    codes = np.select([unexplained, ambiguous, faulted], [Status.NOT_IDENTIFIABLE.code, Status.AMBIGUOUS.code,
                                                          Status.IDENTIFIED.code], Status.NO_FAULT.code)
    return status_array(codes.astype(np.int64))


def _cut_sets(sets: np.ndarray, n_muscles: int) -> np.ndarray:
    """(C, H, M) bool: the muscles each explanation cuts."""
    C, H, _ = sets.shape
    out = np.zeros((C, H, n_muscles + 1), bool)  # the last column takes the -1 padding
    c, h = np.meshgrid(np.arange(C), np.arange(H), indexing="ij")
    for slot in range(sets.shape[-1]):
        out[c, h, sets[..., slot]] = True
    return out[..., :n_muscles]


def _certain_faults(kind, motors, status, spring) -> Faults:
    """The faults every explanation agrees on, as ``Faults`` (none for ``no_fault``/``not_identifiable``), valid for
    ``adapt`` (a band whose noisy edges crossed is closed at their mean)."""
    keep = np.isin(status, [Status.IDENTIFIED, Status.AMBIGUOUS])[:, None]
    faults = Faults.none(*kind.shape)
    faults.cut = keep & (kind == CUT)
    faults.fix = keep & (kind == JAM)
    faults.l_fixed_m = np.where(faults.fix, motors.l_fixed_m, np.nan)
    weak = keep & (kind == WEAK)
    if weak.any():
        faults.f_max_n = np.where(weak, motors.f_weak_n, np.nan)  # within [0, f_max) (motors)
    band = keep & (kind == BAND)
    if band.any():
        edges = _closed_band(motors.lo_m, motors.hi_m)
        mean = edges.mean(-1, keepdims=True)
        edges = np.where(edges[..., :1] > edges[..., 1:], mean, edges)
        faults.l_band_m = np.where(band[..., None], edges, np.nan)
    return faults.validate(kind.shape[1], spring.f_max_n)


def _closed_band(lo, hi) -> np.ndarray:
    """(C, M, 2) a band with an edge the log never reached put ``OPEN_EDGE_M`` beyond the other one."""
    return np.stack([np.where(np.isnan(lo), hi - OPEN_EDGE_M, lo), np.where(np.isnan(hi), lo + OPEN_EDGE_M, hi)], -1)


def _candidates(c, faults, motors, cells, balance, in_set, muscles) -> list:
    """The alternative explanations of ambiguous log ``c``: every combination of each ambiguity's options (at most
    ``MAX_CANDIDATES``), each as a request dict on top of the faults they all share."""
    base = fault_request(faults, c, muscles)
    groups = []
    for m in np.flatnonzero(motors.kind[c] == WEAK_OR_BAND):
        band = _closed_band(motors.lo_m[c, m:m + 1], motors.hi_m[c, m:m + 1])[0]
        groups.append([{"weak": {muscles[m]: float(motors.f_weak_n[c, m])}},
                       {"band": {muscles[m]: [float(v) for v in band]}}])
    for m in np.flatnonzero(cells.ambiguous[c]):
        groups.append([{"cut": [muscles[m]]}, {}])
    if balance.close[c].sum() > 1:
        sets = [in_set[c, h] & ~faults.cut[c] for h in np.flatnonzero(balance.close[c])]
        groups.append([{"cut": [muscles[m] for m in np.flatnonzero(s)]} if s.any() else {} for s in sets])
    out = []
    for combo in product(*groups):
        out.append(merge_requests(base, combo))
        if len(out) == MAX_CANDIDATES:
            break
    return out
