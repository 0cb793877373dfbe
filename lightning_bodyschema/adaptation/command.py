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


def command_status(x_si: torch.Tensor, bounds: FaultBounds, l_lo_m, l_hi_m, bad=None):
    """The safe command as tensor ops (the one the exported package traces): ``(l_motor_m, f_n, status, worst)``.

    ``x_si (B, 2M)`` float64 [m, N]: a schema's output ``[l_motor, f]``; ``bounds`` its faults (tensors on x_si's
    device); ``l_lo_m``, ``l_hi_m`` (M,) [m]: the plausible motor lengths; ``bad (B,)`` bool or None: rows whose
    input was refused. Tensions are clipped into ``[0, f_limit]``. status (B,) int32 ``Status`` codes, the first
    that applies of bad_input, non_finite, out_of_range (outside the plausible lengths or <= 0), fault_not_met (a
    jam or band broken by more than ``FAULT_TOL_M``, a cut muscle pulling more than ``FAULT_TOL_N``), ok; rows not
    ok are NaN. worst: per-case (B,) diagnostics (how far the raw output broke each bound; NaN where not finite).
    """
    m = x_si.shape[1] // 2
    l_motor, f = x_si[:, :m], x_si[:, m:]
    finite = torch.isfinite(x_si).all(1)
    f_safe = torch.minimum(f.clamp_min(0.0), bounds.f_limit_n)
    zero = torch.zeros_like(l_motor)
    outside = torch.maximum(torch.maximum(l_lo_m - l_motor, l_motor - l_hi_m), zero)
    out_of_range = (outside > 0).any(1) | (l_motor <= 0).any(1)
    length_m, cut_n = bounds.broken(l_motor, f_safe)
    not_met = (length_m > FAULT_TOL_M).any(1) | (cut_n > FAULT_TOL_N).any(1)
    status = torch.where(not_met, Status.FAULT_NOT_MET.code, Status.OK.code)
    status = torch.where(out_of_range, Status.OUT_OF_RANGE.code, status)
    status = torch.where(finite, status, Status.NON_FINITE.code)
    if bad is not None:
        status = torch.where(bad, Status.BAD_INPUT.code, status)
    status = status.to(torch.int32)
    ok = (status == Status.OK.code)[:, None]
    nan = torch.full_like(l_motor, float("nan"))
    worst = {"f_clipped_n": (f_safe - f).abs(), "cut_violation_n": cut_n,
             "jam_violation_m": torch.where(bounds.jam, torch.maximum(l_motor - bounds.l_fixed_m, zero), zero),
             "weak_violation_n": torch.where(bounds.weak, torch.maximum(f - bounds.f_limit_n, zero), zero),
             "band_violation_m": torch.where(bounds.band, torch.maximum(torch.maximum(
                 bounds.band_lo_m - l_motor, l_motor - bounds.band_hi_m), zero), zero),
             "l_motor_out_of_range_m": outside}
    worst = {name: torch.where(finite, value.max(1).values, float("nan")) for name, value in worst.items()}
    return torch.where(ok, l_motor, nan), torch.where(ok, f_safe, nan), status, worst


def plausible_lengths(l_range_m, like: torch.Tensor):
    """(lo, hi) (M,) float64 tensors like ``like`` from ``motor_length_range``'s (2, M) [m] (lo at least 0: a motor
    length is positive); None: (0, inf)."""
    if l_range_m is None:
        return like.new_zeros(()), like.new_full((), float("inf"))
    lo, hi = (torch.as_tensor(np.asarray(v, float), dtype=torch.float64, device=like.device) for v in l_range_m)
    return lo.clamp_min(0.0), hi


def safe_command(x_si: torch.Tensor, faults, f_limit_n=None, l_range_m=None) -> AdaptationResult:
    """The command a controller may send, from a schema's decoded output ``x_si = [l_motor, f] (B, 2M)`` [m, N]:
    ``command_status`` (the exported package's own) with numpy results.

    ``faults``: a ``FaultBounds`` on x_si's device, or a ``Faults`` with ``f_limit_n`` (B, M) [N]
    (``faults.f_limit(spring.f_max_n)``, a weakened muscle's own limit). ``l_range_m`` (2, M) [m]: the plausible
    motor lengths (``motor_length_range``; None: any positive length). ``diagnostics``: how far the raw output
    broke each fault before clipping, and ``clipped_l_motor_m``, ``clipped_f_n``: every finite row's clipped
    command, whatever its status (what a fault_not_met row would have sent; scorers of the raw adaptation use it).
    """
    if isinstance(faults, FaultBounds):
        bounds, x = faults, x_si.detach().to(faults.f_limit_n.device, torch.float64)
    else:
        x = x_si.detach().to(torch.float64)
        bounds = FaultBounds.from_faults(faults, f_limit_n, like=x)
    lo, hi = plausible_lengths(l_range_m, x)
    l_motor, f, status, worst = command_status(x, bounds, lo, hi)
    m = x.shape[1] // 2
    finite = torch.isfinite(x).all(1, keepdim=True)
    clipped = torch.where(finite, torch.cat([x[:, :m], torch.minimum(x[:, m:].clamp_min(0.0), bounds.f_limit_n)], 1),
                          float("nan"))
    as_np = lambda t: t.detach().cpu().numpy()  # noqa: E731  (the numpy boundary)
    diagnostics = {name: as_np(value) for name, value in worst.items()}
    diagnostics.update(clipped_l_motor_m=as_np(clipped[:, :m]), clipped_f_n=as_np(clipped[:, m:]))
    return AdaptationResult(as_np(l_motor), as_np(f), status_array(as_np(status).tolist()), diagnostics)


def motor_length_range(x_mean, x_std, n_muscles: int) -> np.ndarray:
    """(2, M) [m]: the healthy data's mean motor length -+ ``LENGTH_SPREADS`` of its spreads."""
    mean, std = (np.asarray(v.cpu() if torch.is_tensor(v) else v, float)[:n_muscles] for v in (x_mean, x_std))
    return np.stack([mean - LENGTH_SPREADS * std, mean + LENGTH_SPREADS * std])
