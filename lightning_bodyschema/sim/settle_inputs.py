"""Inputs of the settle check: a case batch or q_ref with masks, as validated (B, M) arrays (one clear error each),
and the force law they give each muscle (``sim/settle.py`` describes the laws)."""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ..errors import BodySchemaInputError


def _unpack_faults(cases_or_q_ref, cut, fix, l_fixed):
    """q_ref and fault masks from a ``FaultCases`` or from a q_ref array plus optional masks."""
    if _is_cases(cases_or_q_ref):
        if cut is not None or fix is not None or l_fixed is not None:
            raise BodySchemaInputError("give cut/fix/l_fixed either in the FaultCases or as arguments, not both")
        c = cases_or_q_ref
        return c.q_ref, c.cut, c.fix, c.l_fixed
    return cases_or_q_ref, cut, fix, l_fixed


def _is_cases(obj) -> bool:
    """A case batch (``evaluation.FaultCases`` or alike: q_ref, cut, fix, l_fixed, f_max, l_band), not an array."""
    return all(hasattr(obj, name) for name in ("q_ref", "cut", "fix", "l_fixed"))


def _as_batch(name, value, shape, default, dtype):
    """``value`` as a (B, M) array of ``dtype`` (``default`` when None), refusing a wrong shape."""
    if value is None and default is None:
        raise BodySchemaInputError(f"{name} is required: a (B, M) = {shape} array")
    a = np.full(shape, default, dtype) if value is None else np.asarray(value)
    if a.shape != shape:
        raise BodySchemaInputError(f"{name} has shape {a.shape}; expected {shape}")
    if dtype is bool and a.dtype != bool:
        raise BodySchemaInputError(f"{name} must be a bool array; got dtype {a.dtype}")
    if dtype is float and not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)):
        raise BodySchemaInputError(f"{name} must be a numeric array; got dtype {a.dtype}")
    return a.astype(dtype)


def _check_inputs(model, l_motor, f, cases_or_q_ref, cut, fix, l_fixed):
    """Validated (q_ref, l_motor, f, cut, fix, l_fixed) and the (B,) finite-command mask."""
    q_ref, cut, fix, l_fixed = _unpack_faults(cases_or_q_ref, cut, fix, l_fixed)
    q_ref = model.check_q(q_ref)
    shape = (q_ref.shape[0], model.n_muscles)
    l_motor, f = _as_batch("l_motor", l_motor, shape, None, float), _as_batch("f", f, shape, None, float)
    cut, fix = _as_batch("cut", cut, shape, False, bool), _as_batch("fix", fix, shape, False, bool)
    l_fixed = _as_batch("l_fixed", l_fixed, shape, np.nan, float)
    if np.any(cut & fix):
        raise BodySchemaInputError(f"cases {np.flatnonzero(np.any(cut & fix, axis=1)).tolist()} have a muscle "
                                   "both cut and jammed; cut and fix must not overlap")
    if not np.all(np.isfinite(l_fixed[fix])):
        raise BodySchemaInputError(f"l_fixed is NaN/inf for a jammed muscle in cases "
                                   f"{np.flatnonzero(np.any(fix & ~np.isfinite(l_fixed), axis=1)).tolist()}")
    finite = np.all(np.isfinite(l_motor) & np.isfinite(f), axis=1)
    return q_ref, l_motor, f, cut, fix, l_fixed, finite


class _Laws(NamedTuple):
    """Per-muscle force laws (B, M): a spring with rest length ``rest_m`` where ``spring``, else ``f_const_n``."""

    rest_m: np.ndarray  # spring rest length [m]
    spring: np.ndarray  # bool: exponential spring (else a constant force)
    f_const_n: np.ndarray  # constant tension where not a spring [N] (0 for cut muscles)
    f_cap_n: np.ndarray  # tension ceiling [N]: a weakened muscle's f_max', inf elsewhere

    def take(self, idx):
        return _Laws(*(a[idx] for a in self))


def _force_laws(l_motor, f, cut, fix, l_fixed, params, f_max=None, l_band=None) -> _Laws:
    """The force law of every muscle of every case (``sim/settle.py`` describes each).

    ``f_max`` (B, M) weakened muscles' limits (NaN: not weakened), ``l_band`` (B, M, 2) motor bands (NaN: free).
    """
    with np.errstate(invalid="ignore"):  # NaN commands are never simulated
        jam_rest = l_fixed if params.jam == "immobile" else np.minimum(l_motor, l_fixed)
        healthy = ~(cut | fix)
        spring = fix | (healthy & (params.mode == "length"))
        f_const = np.where(healthy & ~spring, np.maximum(f, 0.0), 0.0)
        rest = np.where(fix, jam_rest, l_motor)
        if l_band is not None and params.mode == "length":
            banded = ~np.isnan(l_band).all(-1)
            rest = np.where(banded, np.clip(rest, l_band[..., 0], l_band[..., 1]), rest)
    f_cap = np.full(rest.shape, np.inf) if f_max is None else np.where(np.isnan(f_max), np.inf, f_max)
    return _Laws(rest, spring, f_const, f_cap)
