"""The paper's four evaluation metrics (section IV-B), batched over cases.

    E_cut = mean_{i in I_cut} |f_i|                                   [N]
    E_fix = mean_{j in I_fix} max(0, l_motor_j - l_fixed_j)           [m]  (x 1000 for mm, as tables do)
    E_tau = || -G(q_hat)^T f_eff - tau_bias(q_hat) ||_2               [N m] f_eff: f on the taut set E(q_hat)
    E_q   = || q_ref - q_hat ||_2                                     [rad]

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


def evaluate_commands(model: MusculoskeletalModel, cases: FaultCases, l_motor, f,
                      spring: SpringParams = SpringParams(),
                      params: ForwardSolverParams = ForwardSolverParams()) -> dict:
    """Solve for q_hat and score the commands (l_motor [m], f [N]) (B, M) of ``cases``.

    Returns (B,) arrays E_cut, E_fix, E_tau, E_q, status (``SolverStatus`` ints), converged, n_iter,
    objective, and q_hat (B, N). Cases with a non-finite command have NaN E_tau, E_q and q_hat.
    """
    res = solve_posture(model, l_motor, f, cases.q_ref, cases.cut, cases.fix, cases.l_fixed, spring, params)
    return {
        "E_cut": cut_error(cases, f),
        "E_fix": fix_error(cases, l_motor),
        "E_tau": np.linalg.norm(res.tau_nm, axis=1),
        "E_q": np.linalg.norm(cases.q_ref - res.q_hat, axis=1),
        "q_hat": res.q_hat, "status": res.status, "converged": res.converged,
        "n_iter": res.n_iter, "objective": res.objective,
    }


def summarize_metrics(metrics: dict, cond, mask=None) -> dict:
    """{condition: {metric: {n, median, q1, q3, mean}}} over the cases in ``mask`` (default: all).

    NaN entries (empty index sets, failed commands) are left out and not counted in n.
    """
    cond = np.asarray(cond)
    mask = np.ones(len(cond), bool) if mask is None else np.asarray(mask, bool)
    out = {}
    for c in dict.fromkeys(cond.tolist()):
        rows = (cond == c) & mask
        out[c] = {m: _stats(np.asarray(metrics[m])[rows]) for m in METRICS}
    return out


def _stats(values):
    values = values[np.isfinite(values)]
    if values.size == 0:
        return {"n": 0, "median": np.nan, "q1": np.nan, "q3": np.nan, "mean": np.nan}
    q1, med, q3 = np.percentile(values, [25, 50, 75])
    return {"n": int(values.size), "median": float(med), "q1": float(q1), "q3": float(q3),
            "mean": float(values.mean())}
