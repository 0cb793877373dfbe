"""``HostBody``: ``StructuredSchema.body_si`` at a few postures on the CPU, in numpy (``networks.host``).

It repeats ``StructuredSchema.body`` step by step, each cast included: the normalized posture in the schema's dtype,
the path in float64 then cast to it, the lengths and moment arms scaled in it, the gravity torque at that posture
decoded to radians in float64, then cast. Only for the body it covers (a per-muscle path without hidden layers, the
gravity torque) and a schema on the CPU; ``HostBody.of`` answers None otherwise. Plain numpy and torch, no
Lightning.
"""
from __future__ import annotations

from typing import Optional

import numpy as np
import torch

from ..networks.few_postures import few_for
from ..networks.host import HostGravity, HostPath, host_copy
from ..networks.per_muscle import PerMusclePath

# up to this many postures (and the few-postures path's own budget, ``few_postures.few_for``): on myoArm numpy takes
# 0.73 / 1.38 / 3.42 ms at 1 / 4 / 16 postures, torch 2.11 / 2.64 / 5.02 (myoLegs 1.07 / 3.09 / 11.3 against
# 2.36 / 4.58 / 13.9); level near 100 (BENCHMARKS.md "Per-muscle body evaluation, myoArm")
HOST_ROWS = 16


class HostBody:
    """``(l_geo [m], G [m/rad], tau [N m])`` float64 arrays at postures ``q_rad (B, N)`` [rad] (numpy)."""

    @classmethod
    def of(cls, schema) -> Optional["HostBody"]:
        """The snapshot of ``schema``'s fitted body, or None where it has no host evaluation."""
        path = schema.length_net
        if not (isinstance(path, PerMusclePath) and not path.n_hidden and schema.hparams.torque_model == "gravity"
                and schema.device.type == "cpu"):
            return None
        return cls(schema)

    def __init__(self, schema):
        norm = schema.normalizer
        self.dtype = host_copy(torch.empty(0, dtype=schema.dtype)).dtype
        self.q_lo, self.q_hi = host_copy(norm.q_lo.to(torch.float64)), host_copy(norm.q_hi.to(torch.float64))
        cache = schema.inference_cache  # the entries ``StructuredSchema.body`` and ``torque`` keep (not rebuilt)
        self.path = HostPath(schema.length_net, cache.get("path_coefficients", schema.length_net.dense_coefficients))
        self.gravity = HostGravity(schema.torque_net, cache.get("gravity_coef_terms", schema.torque_net.coef_terms))
        self.l_mean, self.l_std, self.arm = (host_copy(t) for t in schema._length_scales(schema.dtype))

    def __call__(self, q_rad: np.ndarray):
        lo, hi = self.q_lo, self.q_hi
        q_n = (2.0 * (q_rad - lo) / (hi - lo) - 1.0).astype(self.dtype)  # normalizer.encode_q, then the dtype
        y, dy = self.path(q_n.astype(np.float64))
        l_geo = self.l_mean + self.l_std * y.astype(self.dtype)
        q = lo + (q_n.astype(np.float64) + 1.0) * 0.5 * (hi - lo)  # normalizer.decode_q
        tau = self.gravity(q).astype(self.dtype)
        return l_geo.astype(np.float64), (dy.astype(self.dtype) * self.arm).astype(np.float64), \
            tau.astype(np.float64)


def host_body(schema, q_rad) -> Optional[HostBody]:
    """``schema``'s ``HostBody`` for postures ``q_rad``, kept in its inference cache; None while it trains or exports,
    above ``HOST_ROWS`` postures or the few-postures budget, or for a body without a host evaluation."""
    if schema.training or torch.compiler.is_exporting() or len(q_rad) > HOST_ROWS:
        return None
    if isinstance(schema.length_net, PerMusclePath) and not few_for(schema.length_net, q_rad):
        return None
    return schema.inference_cache.get("host_body", lambda: HostBody.of(schema))
