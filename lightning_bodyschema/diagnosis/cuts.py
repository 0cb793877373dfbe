"""Stage 2: cut muscles, from the load cells where a muscle has one, else from the torque balance.

A cut muscle pulls nothing; its motor still follows its command, so its encoder cannot see it. With a load cell,
the muscle's own reading decides: near 0 where the body says its spring should pull (a cut), or near the body's
prediction (healthy). Without one, only the arm's sag shows it: at the measured posture the tensions the body
predicts must balance its torques (``-G^T f = tau``); a cut muscle's predicted pull is the imbalance. Each cut set
(none, one muscle, two) is an explanation scored by the chi-square of that imbalance, whitened by everything that
blurs it (joint-reading noise through the springs' stiffness, load-cell noise, the body's own length and torque
errors).
"""
from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations

import numpy as np

from .motors import NONE, MotorFaults
from .noise import Thresholds
from .readings import Readings

TOP_SINGLES = 6  # pairs are formed among each log's best few single cuts


@dataclass
class LoadCellCuts:
    """Per muscle (C, M): ``cut`` and ``ambiguous`` decisions, ``observed`` (a cut would have shown), ``score``
    (chi-square evidence for a cut over healthy; negative favours healthy)."""

    cut: np.ndarray
    ambiguous: np.ndarray
    observed: np.ndarray
    score: np.ndarray


def predicted_tensions(ev: Readings, motors: MotorFaults):
    """(f (C, R, M) [N], its variance [N^2]): each muscle's healthy pull at the measured posture, its motor where the
    encoder saw it leave its command (jam, band, slip), else at its command."""
    motor = np.where(motors.flagged, ev.log.l_m, ev.log.l_cmd_m)
    f = ev.tension(motor)
    return f, ev.prediction_var(ev.stiffness(f))


def load_cell_cuts(ev: Readings, motors: MotorFaults, thr: Thresholds) -> LoadCellCuts:
    """Cut or healthy, muscle by muscle, for the muscles with a load cell whose motor followed its command."""
    f_pred, var_pred = predicted_tensions(ev, motors)
    var_h = ev.sigma_f ** 2 + var_pred
    f_read = np.nan_to_num(ev.log.f_n)
    chi_healthy = np.where(ev.mask, (f_read - f_pred) ** 2 / var_h, 0.0).sum(1)
    chi_cut = np.where(ev.mask, f_read ** 2 / ev.sigma_f ** 2, 0.0).sum(1)
    signal = np.where(ev.mask, f_pred ** 2 / var_h, 0.0).sum(1)
    candidate = ev.log.has_f & (motors.kind == NONE)
    observed = candidate & (signal > thr.decisive)
    score = np.where(candidate, chi_healthy - chi_cut, 0.0)
    # a cut reads 0 within the load cell's noise: a reading that is not 0 is no cut, however far the body's
    # prediction is (its own error at that posture), so both verdicts need the cut's explanation to fit
    fits = chi_cut <= thr.fit_limit(ev.log.rows.sum(1))[:, None]
    cut = observed & (score > thr.margin) & fits
    ambiguous = observed & (np.abs(score) <= thr.margin) & fits
    return LoadCellCuts(cut, ambiguous, observed, score)


@dataclass
class BalanceCuts:
    """The torque-balance explanations of each log: ``sets`` (C, H, 2) muscle indices (-1 unused) of each
    explanation's cut muscles, ``chi2`` (C, H) and ``score`` (C, H) (chi-square plus the price of its faults),
    ``fits`` (C, H); ``best`` (C,), ``close`` (C, H) the fitting explanations within the margin of the best;
    ``observed`` (C, M) muscles whose cut would have shown; ``evidence`` (C, M) chi2(no cut) - chi2(that cut)."""

    sets: np.ndarray
    chi2: np.ndarray
    score: np.ndarray
    fits: np.ndarray
    best: np.ndarray
    close: np.ndarray
    observed: np.ndarray
    evidence: np.ndarray
    tested: np.ndarray


def balance_cuts(ev: Readings, motors: MotorFaults, cells: LoadCellCuts, thr: Thresholds) -> BalanceCuts:
    """Score no cut, every single cut and pairs of the best single cuts among the muscles with no load cell."""
    has_f = ev.log.has_f
    if has_f.all():  # every muscle has its load cell: nothing is left for the balance to decide
        return _nothing_to_test(motors.kind.shape)
    f_pred, _ = predicted_tensions(ev, motors)
    f_used = np.where(has_f, np.nan_to_num(ev.log.f_n), f_pred)
    imbalance = -np.einsum("crmn,crm->crn", ev.G, f_used) - ev.tau
    whiten = _whitener(ev, f_pred)
    w0 = np.einsum("crij,crj->cri", whiten, imbalance) * ev.mask
    u = np.einsum("crij,crmj->crmi", whiten, ev.G * f_pred[..., None]) * ev.mask[..., None]
    candidate = ~has_f & (motors.kind == NONE)
    signal = (u ** 2).sum((1, 3))
    observed = candidate & (signal > thr.decisive)
    chi0 = (w0 ** 2).sum((1, 2))
    chi1 = ((w0[:, :, None, :] + u) ** 2).sum((1, 3))
    tested = observed.any(1)
    sets, chi2 = _explanations(w0, u, chi0, np.where(observed, chi1, np.inf), thr.max_faults)
    n_faults = (sets >= 0).sum(-1)
    score = chi2 + thr.per_fault * n_faults
    fits = chi2 <= thr.fit_limit(ev.log.rows.sum(1) * ev.G.shape[-1])[:, None]
    ranked = np.where(fits, score, np.inf)
    best = ranked.argmin(1)
    close = fits & (ranked <= ranked[np.arange(len(best)), best][:, None] + thr.margin)
    return BalanceCuts(sets, chi2, score, fits, best, close, observed, np.where(observed, chi0[:, None] - chi1, 0.0),
                       tested)


def _nothing_to_test(shape) -> BalanceCuts:
    C, M = shape
    zeros = np.zeros(shape)
    return BalanceCuts(np.full((C, 1, 2), -1), np.zeros((C, 1)), np.zeros((C, 1)), np.ones((C, 1), bool),
                       np.zeros(C, int), np.ones((C, 1), bool), zeros.astype(bool), zeros, np.zeros(C, bool))


def _whitener(ev: Readings, f_pred) -> np.ndarray:
    """(C, R, N, N) W with W^T W the inverse covariance of a row's imbalance: each pull's own error (its load cell,
    or the body's length error through the spring), the joint reading's noise moving every predicted pull together
    (through the springs' stiffness), and the body's torque error."""
    has_f, stiffness = ev.log.has_f, ev.stiffness(f_pred)
    own_var = np.where(has_f, ev.sigma_f ** 2, (stiffness * ev.error.length_m) ** 2)
    cov = np.einsum("crmi,crm,crmj->crij", ev.G, own_var, ev.G)
    spring_k = np.einsum("crmi,crm,crmj->crij", ev.G, np.where(has_f, 0.0, stiffness), ev.G)
    cov += ev.noise.q_rad ** 2 * spring_k @ spring_k.transpose(0, 1, 3, 2)
    torque_var = ev.error.torque_nm ** 2 + 1e-12 * (1.0 + np.trace(cov, axis1=-2, axis2=-1))[..., None]
    cov += torque_var[..., None] * np.eye(cov.shape[-1])
    return np.linalg.inv(np.linalg.cholesky(cov))


def _explanations(w0, u, chi0, chi1, max_faults: int):
    """(sets (C, H, 2), chi2 (C, H)): no cut, each single cut, and (max_faults >= 2) each pair of the best
    ``TOP_SINGLES`` single cuts; unobserved singles carry chi2 = inf."""
    C, M = chi1.shape
    singles = np.stack([np.arange(M), np.full(M, -1)], -1)
    sets = [np.full((C, 1, 2), -1), np.broadcast_to(singles, (C, M, 2))]
    chis = [chi0[:, None], chi1]
    if max_faults >= 2 and M >= 2:
        top = np.argsort(chi1, 1, kind="stable")[:, :min(TOP_SINGLES, M)]
        pairs = np.array(list(combinations(range(top.shape[1]), 2)))
        i, j = top[:, pairs[:, 0]], top[:, pairs[:, 1]]
        c = np.arange(C)[:, None]
        w = w0[:, :, None, :] + u[c, :, i].transpose(0, 2, 1, 3) + u[c, :, j].transpose(0, 2, 1, 3)
        chi2 = (w ** 2).sum((1, 3))
        chi2 = np.where(np.isfinite(chi1[c, i]) & np.isfinite(chi1[c, j]), chi2, np.inf)
        sets.append(np.stack([i, j], -1))
        chis.append(chi2)
    return np.concatenate(sets, 1), np.concatenate(chis, 1)
