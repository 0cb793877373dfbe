"""The paper's four evaluation metrics (section IV-B), batched over cases.

    E_cut = mean_{i in I_cut} |f_i|                                   [N]
    E_fix = mean_{j in I_fix} max(0, l_motor_j - l_fixed_j)           [m]  (x 1000 for mm, as tables do)
    E_tau = || -G(q_hat)^T f_eff - tau_bias(q_hat) ||_2               [N m] f_eff: f on the taut set E(q_hat),
                                                                      min(f, f_max') on a weakened muscle
    E_q   = || q_ref - q_hat ||_2                                     [rad]

Beyond the paper (``EXTRA_METRICS``, NaN for cases without such a fault):

    E_weak = mean_{i weakened} max(0, f_i - f_max'_i)                 [N]
    E_band = mean_{j banded} max(0, lo_j - l_motor_j, l_motor_j - hi_j) [m]

The posture solver models every fault kind as ``sim.settle`` does: a weakened muscle commanded above
its limit pulls f_max' and slips, a banded motor stops at its band (``forward_solver``). So E_tau and
E_q score what the command does to the faulty body; E_weak and E_band say how far it breaks the new faults.

q_hat comes from ``solve_posture``. A metric whose index set is empty for a case (E_fix under CUT,
E_cut under FIX) is NaN there, so means over a condition never mix in meaningless zeros.
E_q alone reacts weakly to torque imbalance (the length residuals dominate the solver's objective),
so report it beside E_tau.
"""
from __future__ import annotations

import numpy as np

from ..sim.model import MusculoskeletalModel
from ..sim.spring import SpringParams
from .cases import FaultCases
from .forward_solver import ForwardSolverParams, solve_posture

METRICS = ("E_cut", "E_fix", "E_tau", "E_q")
EXTRA_METRICS = ("E_weak", "E_band")  # weakened muscles, length-banded motors (not in the paper)


def _masked_mean(values, mask):
    """Row-wise mean of ``values`` over ``mask`` (B, M); NaN for rows with an empty mask."""
    count = mask.sum(axis=1)
    total = np.where(mask, values, 0.0).sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(count > 0, total / np.maximum(count, 1), np.nan)


def cut_error(cases: FaultCases, f) -> np.ndarray:
    """E_cut (B,) [N]: mean |f_i| over the ruptured muscles."""
    return _masked_mean(np.abs(np.asarray(f, float)), cases.cut)


def fix_error(cases: FaultCases, l_motor) -> np.ndarray:
    """E_fix (B,) [m]: mean max(0, l_motor_j - l_fixed_j) over the jammed muscles."""
    over = np.maximum(0.0, np.asarray(l_motor, float) - np.where(cases.fix, cases.l_fixed, 0.0))
    return _masked_mean(over, cases.fix)


def weak_error(cases: FaultCases, f) -> np.ndarray:
    """E_weak (B,) [N]: mean max(0, f_i - f_max'_i) over the weakened muscles (NaN without any)."""
    limit = np.zeros(cases.cut.shape) if cases.f_max is None else np.nan_to_num(cases.f_max)
    return _masked_mean(np.maximum(0.0, np.asarray(f, float) - limit), cases.weak)


def band_error(cases: FaultCases, l_motor) -> np.ndarray:
    """E_band (B,) [m]: mean distance of l_motor_j outside [lo_j, hi_j] over the banded motors (NaN without any)."""
    band, l_motor = cases.band, np.asarray(l_motor, float)
    if cases.l_band is None:
        return _masked_mean(np.zeros_like(l_motor), band)
    lo, hi = np.nan_to_num(cases.l_band[..., 0]), np.nan_to_num(cases.l_band[..., 1])
    return _masked_mean(np.maximum(0.0, np.maximum(lo - l_motor, l_motor - hi)), band)


def evaluate_commands(model: MusculoskeletalModel, cases: FaultCases, l_motor, f,
                      spring: SpringParams = SpringParams(),
                      params: ForwardSolverParams = ForwardSolverParams()) -> dict:
    """Solve for q_hat and score the commands (l_motor [m], f [N]) (B, M) of ``cases``.

    Returns (B,) arrays E_cut, E_fix, E_tau, E_q, E_weak, E_band, status (``SolverStatus`` ints), converged, n_iter,
    objective, and q_hat (B, N). Cases with a non-finite command have NaN E_tau, E_q and q_hat.
    """
    res = solve_posture(model, l_motor, f, cases.q_ref, cases.cut, cases.fix, cases.l_fixed, spring, params,
                        f_max_n=cases.f_max, l_band_m=cases.l_band)
    return {
        "E_cut": cut_error(cases, f),
        "E_fix": fix_error(cases, l_motor),
        "E_tau": np.linalg.norm(res.tau_nm, axis=1),
        "E_q": np.linalg.norm(cases.q_ref - res.q_hat, axis=1),
        "E_weak": weak_error(cases, f), "E_band": band_error(cases, l_motor),
        "q_hat": res.q_hat, "status": res.status, "converged": res.converged,
        "n_iter": res.n_iter, "objective": res.objective,
    }


def summarize_metrics(metrics: dict, cond, mask=None, names=METRICS) -> dict:
    """{condition: {metric: {n, median, q1, q3, mean}}} over the cases in ``mask`` (default: all).

    ``names``: which metrics (default the paper's four; ``METRICS + EXTRA_METRICS`` for all).

    NaN entries (empty index sets, failed commands) are left out and not counted in n.
    """
    cond = np.asarray(cond)
    mask = np.ones(len(cond), bool) if mask is None else np.asarray(mask, bool)
    out = {}
    for c in dict.fromkeys(cond.tolist()):
        rows = (cond == c) & mask
        out[c] = {m: _stats(np.asarray(metrics[m])[rows]) for m in names}
    return out


def _stats(values):
    values = values[np.isfinite(values)]
    if values.size == 0:
        return {"n": 0, "median": np.nan, "q1": np.nan, "q3": np.nan, "mean": np.nan}
    q1, med, q3 = np.percentile(values, [25, 50, 75])
    return {"n": int(values.size), "median": float(med), "q1": float(q1), "q3": float(q3),
            "mean": float(values.mean())}
