"""The branched part of a per-muscle path (``PerMusclePath(branches=2)``): per branched muscle a second polynomial over
its own terms and a gate whose sign picks it (the length jumps where the gate changes sign): its state, its
coefficients and the choice. The fit: ``networks.branches``. Plain PyTorch, no Lightning.
"""
from __future__ import annotations

import torch


def add_branches(path) -> None:
    """``path``'s branch state, none branched: ``coef_alt``, ``gate`` like its ``coef`` and ``branched (M,)``, and
    ``branched_index`` (not in the state dict: a shape known before a call, for torch.export), kept in step with
    ``branched`` by the fit and every state-dict load (``refresh_branches``)."""
    path.register_buffer("coef_alt", torch.zeros_like(path.coef))
    path.register_buffer("gate", torch.zeros_like(path.coef))
    path.register_buffer("branched", torch.zeros(len(path.coef), dtype=torch.bool))
    path.register_buffer("branched_index", torch.zeros(0, dtype=torch.long), persistent=False)
    path.register_load_state_dict_post_hook(lambda module, _: refresh_branches(module))


def refresh_branches(path) -> None:
    """``branched_index`` from ``branched`` (not on the meta device, where a skeleton holds no values)."""
    if not path.branched.is_meta:
        path.branched_index = torch.nonzero(path.branched).flatten()
