"""Inputs of the settle check: a case batch or q_ref with masks, as validated (B, M) arrays (one clear error each)."""
from __future__ import annotations

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
