"""``all_finite(tensors)``: is every element of every tensor finite? One foreach kernel per training step.

The fast path is the check ``torch.amp.GradScaler`` runs before every step it takes,
``torch._amp_foreach_non_finite_check_and_unscale_`` with a scale of 1 (which leaves finite values bit-identical).
It is a private torch op: where it is missing or refuses the tensors, ``torch.nn.utils.get_total_norm`` (public, slower:
BENCHMARKS.md) gives the same answer.
``tests/training/test_finite.py`` fails loudly on a torch version where the op changed.
"""
from __future__ import annotations

from typing import Optional, Sequence

import torch

_AMP_CHECK = getattr(torch, "_amp_foreach_non_finite_check_and_unscale_", None)
_UNIT_SCALE: dict = {}  # device -> the scale 1 the check multiplies by (made once per device, read-only)


def non_finite_flag(tensors: Sequence[torch.Tensor]) -> Optional[torch.Tensor]:
    """A float32 0-dim tensor on the tensors' device, 1 where any element is inf or NaN and 0 otherwise, computed
    without a read on the host (a fused optimizer takes it as ``found_inf``). None where the fast op is missing or
    refuses the tensors (the caller then uses ``all_finite``)."""
    if not tensors or _AMP_CHECK is None:
        return None
    device = tensors[0].device
    found_inf = torch.zeros((), dtype=torch.float32, device=device)
    unit = _UNIT_SCALE.get(device)
    if unit is None:
        unit = _UNIT_SCALE[device] = torch.ones((), dtype=torch.float32, device=device)
    try:
        _AMP_CHECK(list(tensors), found_inf, unit)
    except (RuntimeError, TypeError):  # e.g. tensors on several devices
        return None
    return found_inf


def all_finite(tensors: Sequence[torch.Tensor], fast: bool = True) -> bool:
    """True when no tensor holds an inf or a NaN (one device; any floating dtypes). ``fast=False``: the public path."""
    if not tensors:
        return True
    found_inf = non_finite_flag(tensors) if fast else None
    if found_inf is not None:
        return not bool(found_inf)
    return bool(torch.isfinite(torch.nn.utils.get_total_norm(list(tensors), foreach=True)))
