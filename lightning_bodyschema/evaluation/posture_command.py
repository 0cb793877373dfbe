"""The command a posture solve takes (``forward_solver.solve_posture``): checked, and rewritten as the faulty body
can realize it.

The two faults beyond the paper enter as ``sim.settle`` models them (``sim/settle_inputs.py``), by
rewriting the command before the solve:

* a banded motor (``l_band_m`` [lo, hi]) stops at its band: ``l_motor`` becomes ``clip(l_motor, lo, hi)``
  and a jammed one's ``l_fixed`` becomes ``clip(l_fixed, lo, hi)`` (clip is monotone, so this is
  settle's ``clip(min(l_motor, l_fixed), lo, hi)``);
* a weakened muscle (``f_max_n`` = f_max') never pulls more than f_max' (tension ``min(spring, f_max')``):
  its motor slips once the wire is stretched past phi^-1(f_max'). So ``f`` becomes ``min(f, f_max')`` in
  every term, and each of its overstretch residuals (``-r_eq``, ``r_slack``, ``r_fix``) is capped at the
  slip margin ``phi^-1(f_max') - phi^-1(f)``: beyond it the wire pulls a constant f_max', so the
  residual stays constant and d r/dq is 0 (no length stiffness). A command above its limit (*saturated*)
  has margin 0: it pulls f_max' and only its under-stretched side ``max(0, r_eq)`` counts. The cap is
  continuous in f (a command at its limit up to rounding scores as one just below it), and a muscle
  whose stretch stays inside its margin scores as a healthy one.

Without weakened or banded muscles every array is the paper's, bit for bit.

numpy only; never imports Lightning.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ..errors import BodySchemaInputError
from ..sim.spring import SpringParams, elongation_from_tension


class PostureCommand(NamedTuple):
    """One batch of commands and faults, pre-processed (NaN l_fixed replaced, bands and limits applied, phi^-1
    taken): the command as the faulty body can realize it (module docstring)."""

    l_motor: np.ndarray  # (B, M) [m], clipped to a banded motor's band
    f: np.ndarray  # (B, M) [N], min(f, f_max') on a weakened muscle
    delta: np.ndarray  # (B, M) phi^-1(f) [m]
    q_ref: np.ndarray  # (B, N) [rad]
    cut: np.ndarray  # (B, M) bool
    fix: np.ndarray  # (B, M) bool
    l_fixed: np.ndarray  # (B, M) [m], 0 where not jammed (clipped to a motor's band)
    slip_m: np.ndarray  # (B, M) [m] phi^-1(f_max') - phi^-1(f): overstretch at which a weakened motor slips; inf

    def take(self, idx):
        return PostureCommand(*(a[idx] for a in self))


def _check_inputs(model, l_motor, f, q_ref, cut, fix, l_fixed) -> tuple[PostureCommand, np.ndarray]:
    """Validate shapes and faults; returns the command and (B,) finite-command mask."""
    q_ref = model.check_q(q_ref)
    batch, n_m = q_ref.shape[0], model.n_muscles
    arrays = {"l_motor": l_motor, "f": f, "cut": cut, "fix": fix, "l_fixed": l_fixed}
    arrays = {k: np.asarray(v) for k, v in arrays.items()}
    for name, a in arrays.items():
        if a.shape != (batch, n_m):
            raise BodySchemaInputError(f"{name} has shape {a.shape}; expected ({batch}, {n_m})")
    cut, fix = arrays["cut"].astype(bool), arrays["fix"].astype(bool)
    if np.any(cut & fix):
        raise BodySchemaInputError("a muscle is both cut and jammed; cut and fix must not overlap")
    l_fixed = arrays["l_fixed"].astype(float)
    if not np.all(np.isfinite(l_fixed[fix])):
        raise BodySchemaInputError("l_fixed is NaN/inf for a jammed muscle")
    l_motor, f = arrays["l_motor"].astype(float), arrays["f"].astype(float)
    finite = np.all(np.isfinite(l_motor) & np.isfinite(f), axis=1)
    l_motor, f = np.where(finite[:, None], l_motor, 0.0), np.where(finite[:, None], f, 0.0)
    lo, hi = model.q_range.T
    cmd = PostureCommand(l_motor, f, None, np.clip(q_ref, lo, hi), cut, fix, np.where(fix, l_fixed, 0.0),
                   np.full((batch, n_m), np.inf))
    return cmd, finite


def _check_new_faults(shape, f_max_n, l_band_m):
    """f_max' (B, M) [N] and the band (B, M, 2) [m] as float arrays (NaN: no such fault), or None; one clear
    error for a wrong shape or value."""
    if f_max_n is not None:
        f_max_n = np.asarray(f_max_n, float)
        if f_max_n.shape != shape:
            raise BodySchemaInputError(f"f_max_n has shape {f_max_n.shape}; expected {shape}")
        bad = np.isinf(f_max_n) | (f_max_n < 0)
        if bad.any():
            raise BodySchemaInputError(f"f_max_n has the limit {float(f_max_n[bad][0])!r} N; a weakened muscle's "
                                       "limit is finite and >= 0 N, NaN where not weakened")
    if l_band_m is not None:
        l_band_m = np.asarray(l_band_m, float)
        if l_band_m.shape != shape + (2,):
            raise BodySchemaInputError(f"l_band_m has shape {l_band_m.shape}; expected {shape + (2,)}")
        banded = ~np.isnan(l_band_m).all(-1)
        lo, hi = l_band_m[..., 0][banded], l_band_m[..., 1][banded]
        if not (np.all(np.isfinite(lo) & np.isfinite(hi)) and np.all(lo <= hi)):
            raise BodySchemaInputError("l_band_m has a band with a NaN/inf bound or lo > hi; a banded motor needs "
                                       "finite lo <= hi [m], NaN for both where the motor is free")
    return f_max_n, l_band_m


def _apply_new_faults(cmd: PostureCommand, f_max_n, l_band_m, spring: SpringParams) -> PostureCommand:
    """The command as weakened muscles and banded motors realize it (module docstring): l_motor / l_fixed clipped
    to a band, f capped at f_max' and its slip margin set. Untouched entries keep their exact values."""
    if l_band_m is not None:
        banded = ~np.isnan(l_band_m).all(-1)
        lo, hi = l_band_m[..., 0], l_band_m[..., 1]
        cmd = cmd._replace(l_motor=np.where(banded, np.clip(cmd.l_motor, lo, hi), cmd.l_motor),
                           l_fixed=np.where(banded & cmd.fix, np.clip(cmd.l_fixed, lo, hi), cmd.l_fixed))
    if f_max_n is not None:
        weak = ~np.isnan(f_max_n)
        f = np.where(weak & (cmd.f > f_max_n), f_max_n, cmd.f)
        margin = elongation_from_tension(np.where(weak, f_max_n, 0.0), spring) - elongation_from_tension(f, spring)
        cmd = cmd._replace(f=f, slip_m=np.where(weak, margin, np.inf))
    return cmd


def prepare_command(model, l_motor, f, q_ref, cut, fix, l_fixed, spring: SpringParams = SpringParams(),
                    f_max_n=None, l_band_m=None) -> tuple[PostureCommand, np.ndarray]:
    """The validated command as the faulty body realizes it, phi^-1 taken, and the (B,) finite-command mask
    (``solve_posture``'s arguments)."""
    cmd, finite = _check_inputs(model, l_motor, f, q_ref, cut, fix, l_fixed)
    cmd = _apply_new_faults(cmd, *_check_new_faults(cmd.f.shape, f_max_n, l_band_m), spring)
    return cmd._replace(delta=elongation_from_tension(cmd.f, spring)), finite
