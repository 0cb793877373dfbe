"""What adaptation returns, and the step that makes a schema's raw output safe to send to motors."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

# ok: a command to send. non_finite: adaptation diverged (NaN/inf). infeasible: the true physics admits no command
# at q_ref under these faults (check_physics). unreachable: a task-space target out of reach (adapt_to_target).
# out_of_range: adaptation diverged to finite but absurd motor lengths (beyond ``LENGTH_SPREADS`` spreads of the
# healthy data): no motor may be sent there.
# unchecked: a finite command, but the physics check was asked for and could not run (a schema trained on recorded
# data has no model); a controller decides whether to send it. Never ``ok``: ok means checked or check turned off.
STATUSES = ("ok", "non_finite", "infeasible", "unreachable", "out_of_range", "unchecked")
# healthy motor lengths span a few spreads around their mean; a diverged guidance reaches metres (1e2-1e118 spreads)
LENGTH_SPREADS = 20.0


@dataclass
class AdaptationResult:
    """What ``adapt`` returns. Only cases whose ``status`` is ``"ok"`` carry a command to send.

    l_motor_m, f_n: (B, M) commands in SI units; a case that is not ``ok`` has NaN there, never numbers that look
    like a command. status: (B,) strings (``STATUSES``). diagnostics: per-case arrays (clipped tension, the
    constraint violations before clipping, the physics check's verdict, ...).
    """

    l_motor_m: np.ndarray
    f_n: np.ndarray
    status: np.ndarray
    diagnostics: dict[str, Any] = field(default_factory=dict)

    @property
    def ok(self) -> np.ndarray:
        return self.status == "ok"


def safe_command(x_si: torch.Tensor, faults, f_limit_n: np.ndarray, l_range_m=None) -> AdaptationResult:
    """The command a controller may send, from a schema's decoded output ``x_si = [l_motor, f] (B, 2M)`` [m, N].

    Non-finite rows become NaN with status ``non_finite``; tensions are clipped into [0, f_limit_n] (``f_limit_n``
    (B, M): ``faults.f_limit(spring.f_max_n)``, a weakened muscle's own limit), and how far the raw output broke each
    fault before clipping goes to ``diagnostics``. ``l_range_m`` (2, M) [m]: the plausible motor lengths
    (``motor_length_range``); a row outside is ``out_of_range`` (NaN), its distance outside in ``diagnostics``.
    """
    x = x_si.detach().cpu().numpy()
    m = x.shape[1] // 2
    l_motor, f = x[:, :m], x[:, m:]
    finite = np.isfinite(x).all(1)
    f_safe = np.clip(f, 0.0, f_limit_n)  # non-finite rows are replaced by NaN below
    # a motor length is positive whatever the plausible range says (mean - 20 spreads can lie below 0)
    lo_m, hi_m = (0.0, np.inf) if l_range_m is None else (np.maximum(l_range_m[0], 0.0), l_range_m[1])
    with np.errstate(invalid="ignore"):  # NaN rows are non_finite
        outside = np.maximum(np.maximum(lo_m - l_motor, l_motor - hi_m), 0.0).max(1)
        bad = (outside > 0) | (l_motor <= 0).any(1)
    status = np.where(finite, np.where(bad, "out_of_range", "ok"), "non_finite").astype("<U16")
    lo, hi = (np.zeros((2,) + f.shape) if faults.l_band_m is None else np.moveaxis(faults.l_band_m, -1, 0))
    with np.errstate(invalid="ignore"):  # NaN off the faults is masked
        worst = {"f_clipped_n": np.abs(f_safe - f).max(1),
                 "cut_violation_n": np.where(faults.cut, np.abs(f_safe), 0.0).max(1),
                 "jam_violation_m": np.where(faults.fix, np.maximum(0.0, l_motor - faults.l_fixed_m), 0.0).max(1),
                 # before clipping: how far the adapted tension overshot a weakened muscle's limit
                 "weak_violation_n": np.where(faults.weak, np.maximum(0.0, f - f_limit_n), 0.0).max(1),
                 "band_violation_m": np.where(faults.band, np.maximum(np.maximum(lo - l_motor, l_motor - hi), 0.0),
                                              0.0).max(1)}
    diagnostics = {name: np.where(finite, value, np.nan) for name, value in worst.items()}
    diagnostics["l_motor_out_of_range_m"] = np.where(finite, outside, np.nan)
    sendable = (status == "ok")[:, None]
    return AdaptationResult(np.where(sendable, l_motor, np.nan), np.where(sendable, f_safe, np.nan), status, diagnostics)


def motor_length_range(x_mean, x_std, n_muscles: int) -> np.ndarray:
    """(2, M) [m]: the healthy data's mean motor length -+ ``LENGTH_SPREADS`` of its spreads."""
    mean, std = (np.asarray(v.cpu() if torch.is_tensor(v) else v, float)[:n_muscles] for v in (x_mean, x_std))
    return np.stack([mean - LENGTH_SPREADS * std, mean + LENGTH_SPREADS * std])
