"""What adaptation returns, and the step that makes a schema's raw output safe to send to motors."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from ..faults.bounds import FaultBounds
from ..status import Status, status_array


# healthy motor lengths span a few spreads around their mean; a diverged guidance reaches metres (1e2-1e118 spreads)
LENGTH_SPREADS = 20.0
# a command that breaks a jam or band by more than FAULT_TOL_M [m], or a cut muscle pulling more than FAULT_TOL_N [N],
# is fault_not_met (never ok), in Python and in the exported package alike
FAULT_TOL_M, FAULT_TOL_N = 1e-5, 1e-2


@dataclass
class AdaptationResult:
    """What ``adapt`` returns. Only cases whose ``status`` is ``"ok"`` carry a command to send.

    l_motor_m, f_n: (B, M) commands in SI units; a case that is not ``ok`` has NaN there, never numbers that look
    like a command. status: (B,) object array of ``status.Status`` members (each equals its name: ``== "ok"``).
    diagnostics: per-case arrays (clipped tension, the constraint violations before clipping, the physics check's
    verdict, ...).
    """

    l_motor_m: np.ndarray
    f_n: np.ndarray
    status: np.ndarray
    diagnostics: dict[str, Any] = field(default_factory=dict)

    @property
    def ok(self) -> np.ndarray:
        return self.status == Status.OK


def command_status(x_si, bounds: FaultBounds, l_lo_m, l_hi_m, bad=None, diagnostics: bool = False):
    """The safe command, the one every Python adapter runs and the exported packages trace:
    ``(l_motor_m, f_n, status, worst)``, for numpy arrays or torch tensors alike (all of one backend and device).

    ``x_si (B, 2M)`` float64 [m, N]: a schema's output ``[l_motor, f]``; ``bounds`` its faults; ``l_lo_m``,
    ``l_hi_m`` (M,) [m]: the plausible motor lengths; ``bad (B,)`` bool or None: rows whose input was refused.
    Tensions are clipped into ``[0, f_limit]``. status (B,) int32 ``Status`` codes, the first that applies of
    bad_input, non_finite, out_of_range (outside the plausible lengths or <= 0), fault_not_met (a jam or band broken
    by more than ``FAULT_TOL_M``, a cut muscle pulling more than ``FAULT_TOL_N``), ok; rows not ok are NaN.
    worst (``diagnostics``, else None): per-case (B,) arrays of how far the raw output broke each bound (NaN where
    not finite), and every finite row's clipped command whatever its status (``clipped_l_motor_m``, ``clipped_f_n``
    (B, M); NaN rows elsewhere).
    """
    xp = torch if torch.is_tensor(x_si) else np
    pos = (lambda a: a.clamp_min(0.0)) if xp is torch else (lambda a: np.maximum(a, 0.0))  # noqa: E731
    m = x_si.shape[1] // 2
    l_motor, f = x_si[:, :m], x_si[:, m:]
    finite = xp.isfinite(x_si).all(1)
    f_safe = xp.minimum(pos(f), bounds.f_limit_n)
    outside = pos(xp.maximum(l_lo_m - l_motor, l_motor - l_hi_m))
    length_m, cut_n = bounds.broken(l_motor, f_safe)
    status = xp.where((length_m > FAULT_TOL_M).any(1) | (cut_n > FAULT_TOL_N).any(1), Status.FAULT_NOT_MET.code,
                      Status.OK.code)
    status = xp.where((outside > 0).any(1) | (l_motor <= 0).any(1), Status.OUT_OF_RANGE.code, status)
    status = xp.where(finite, status, Status.NON_FINITE.code)
    if bad is not None:
        status = xp.where(bad, Status.BAD_INPUT.code, status)
    status = status.to(torch.int32) if xp is torch else status.astype(np.int32)
    ok = (status == Status.OK.code)[:, None]
    out = (xp.where(ok, l_motor, float("nan")), xp.where(ok, f_safe, float("nan")), status)
    if not diagnostics:
        return out + (None,)
    worst = (xp.abs(f_safe - f), cut_n, xp.where(bounds.jam, pos(l_motor - bounds.l_fixed_m), 0.0),
             xp.where(bounds.weak, pos(f - bounds.f_limit_n), 0.0),
             xp.where(bounds.band, pos(xp.maximum(bounds.band_lo_m - l_motor, l_motor - bounds.band_hi_m)), 0.0),
             outside)
    worst = xp.where(finite[:, None], xp.amax(xp.stack(worst, 1), 2), float("nan"))  # (B, 6): one pass, not six
    diagnostics = {name: worst[:, i] for i, name in enumerate(DIAGNOSTICS)}
    diagnostics.update(clipped_l_motor_m=xp.where(finite[:, None], l_motor, float("nan")),
                       clipped_f_n=xp.where(finite[:, None], f_safe, float("nan")))
    return out + (diagnostics,)


# what ``command_status`` reports per case with ``diagnostics``
DIAGNOSTICS = ("f_clipped_n", "cut_violation_n", "jam_violation_m", "weak_violation_n", "band_violation_m",
               "l_motor_out_of_range_m")


def safe_command(x_si, faults, f_limit_n=None, l_range_m=None) -> AdaptationResult:
    """The command a controller may send, from a schema's decoded output ``x_si = [l_motor, f] (B, 2M)`` [m, N]
    (a tensor, copied to numpy here: the numpy boundary): ``command_status`` (the exported package's own).

    ``faults``: a ``FaultBounds``, or a ``Faults`` with ``f_limit_n`` (B, M) [N] (``faults.f_limit(spring.f_max_n)``,
    a weakened muscle's own limit). ``l_range_m`` (2, M) [m]: the plausible motor lengths (``motor_length_range``;
    None: any positive length). ``diagnostics``: how far the raw output broke each fault before clipping, and
    ``clipped_l_motor_m``, ``clipped_f_n``: every finite row's clipped command, whatever its status (what a
    fault_not_met row would have sent; scorers of the raw adaptation use it).
    """
    x = x_si.detach().to(torch.float64).cpu().numpy() if torch.is_tensor(x_si) else np.asarray(x_si, np.float64)
    bounds = faults.on_host() if isinstance(faults, FaultBounds) else FaultBounds.from_faults(faults, f_limit_n)
    lo, hi = (0.0, np.inf) if l_range_m is None else (np.maximum(l_range_m[0], 0.0), l_range_m[1])
    with np.errstate(invalid="ignore", over="ignore"):  # NaN rows are non_finite
        l_motor, f, status, diagnostics = command_status(x, bounds, lo, hi, diagnostics=True)
    return AdaptationResult(l_motor, f, statuses(status), diagnostics)


def statuses(codes: np.ndarray) -> np.ndarray:
    """(B,) object array of ``Status`` members from int codes (``status.status_array``'s one-op lookup)."""
    return status_array(np.asarray(codes, np.int64))


def motor_length_range(x_mean, x_std, n_muscles: int) -> np.ndarray:
    """(2, M) [m]: the healthy data's mean motor length -+ ``LENGTH_SPREADS`` of its spreads."""
    mean, std = (np.asarray(v.cpu() if torch.is_tensor(v) else v, float)[:n_muscles] for v in (x_mean, x_std))
    return np.stack([mean - LENGTH_SPREADS * std, mean + LENGTH_SPREADS * std])
