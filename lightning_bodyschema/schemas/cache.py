"""``InferenceCache``: what a schema derives from its weights for fast inference, with one owner and one lifetime.

Fast adaptation needs objects derived from the weights: frozen snapshots of the networks (``FrozenMLP``), the
per-step matrices of a sampling plan, the penalty builder of the normalizer, the shared initial noise. Building
them is a sizeable share of a prepared adaptation (BENCHMARKS.md "Figures behind code choices"), so they are kept
between calls. They are never keyed on tensor addresses or version counters (fused optimizers update weights in place
without bumping ``_version``, so such a key can serve stale weights). Instead the owning ``BodySchema`` clears its cache

* on every ``train()`` / ``eval()`` call (Lightning switches modes around every validation, test and fault
  benchmark, so each sees the weights of that moment),
* on ``load_state_dict`` and on every dtype or device move (``_apply``: ``.to()``, ``.double()``, ``.cuda()``),
* on ``schema.clear_caches()`` (after editing weights by hand in eval mode),

and keeps nothing while it is in training mode: there the weights change with every optimizer step, so each call
builds afresh.
"""
from __future__ import annotations

import copy
from typing import Callable, Hashable

import torch


class InferenceCache:
    """Entries built by ``get(key, build)`` on first use; see the module docstring for when they are dropped."""

    def __init__(self, owner: torch.nn.Module):
        self._owner = owner
        self._entries: dict = {}

    def __deepcopy__(self, memo) -> "InferenceCache":
        """An empty cache for the copied owner: the copy builds its own entries (a numpy snapshot holds the numpy
        module, which does not copy)."""
        return InferenceCache(copy.deepcopy(self._owner, memo))

    def get(self, key: Hashable, build: Callable):
        """The entry for ``key``, built by ``build()`` (outside inference mode, so the tensors are ordinary ones
        even when built during Lightning's validation) if missing or while the owner is training."""
        if not self._owner.training and key in self._entries:
            return self._entries[key]
        with torch.inference_mode(False), torch.no_grad():
            value = build()
        if not self._owner.training:
            self._entries[key] = value
        return value

    def put(self, key: Hashable, value) -> None:
        """Replace the entry for ``key`` with ``value`` (a measurement of the current weights, e.g. the body's error);
        dropped with the others when the weights change."""
        self._entries[key] = value

    def clear(self) -> None:
        self._entries.clear()

    def __len__(self) -> int:
        return len(self._entries)
