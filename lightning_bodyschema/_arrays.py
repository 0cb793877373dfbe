"""The one backend switch of the array-API code: numpy arrays and torch tensors through the same few calls.

``faults.bounds``, ``sim.spring`` and the crossed-box rule of ``solvers.problem`` run on numpy (the feasibility check,
the numpy adapters) and on torch (the adapters' tensors, the exported graph, traceable by ``torch.export``) alike.
torch is never imported here: a tensor's own module is looked up, so numpy-only callers stay light.
"""
from __future__ import annotations

import sys

import numpy as np


def namespace(a):
    """torch for tensors, numpy for anything else."""
    return sys.modules["torch"] if type(a).__module__.startswith("torch") else np


def fill(like, value):
    """An array or tensor like ``like`` (float64 in numpy) holding ``value`` everywhere."""
    if namespace(like) is np:
        return np.full_like(like, value, dtype=float)
    return sys.modules["torch"].full_like(like, value)


def where(cond, a, b):
    """``where`` of the condition's backend; a number beside a tensor becomes a float64 tensor on its device."""
    xp = namespace(cond)
    if xp is np:
        return np.where(cond, a, b)
    torch = xp
    return torch.where(cond, a if torch.is_tensor(a) else torch.as_tensor(a, dtype=torch.float64, device=cond.device),
                       b if torch.is_tensor(b) else torch.as_tensor(b, dtype=torch.float64, device=cond.device))


def minimum(a, b):
    return namespace(a).minimum(a, b)


def maximum(a, b):
    return namespace(a).maximum(a, b)


def isnan(a):
    return namespace(a).isnan(a)


def isfinite(a):
    return namespace(a).isfinite(a)


def clamp_min(a, low: float):
    """``max(a, low)`` elementwise (NaN stays NaN)."""
    return np.clip(a, low, None) if namespace(a) is np else a.clamp_min(low)
