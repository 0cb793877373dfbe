"""Z-scoring of x = [l_motor, f] (statistics of the train split) and scaling of q into [-1, 1].

Buffers only, so it travels in a checkpoint's ``state_dict`` (no pickle).
"""
from __future__ import annotations

import torch
from torch import nn

from ..networks.arrays import decode_q, encode_q


class Normalizer(nn.Module):
    """x_n = (x - mean) / std per channel; q_n = 2 (q - lo) / (hi - lo) - 1 with the model's joint range."""

    def __init__(self, x_dim: int, q_dim: int):
        super().__init__()
        self.register_buffer("x_mean", torch.zeros(x_dim, dtype=torch.float64))
        self.register_buffer("x_std", torch.ones(x_dim, dtype=torch.float64))
        self.register_buffer("q_lo", -torch.ones(q_dim, dtype=torch.float64))
        self.register_buffer("q_hi", torch.ones(q_dim, dtype=torch.float64))

    def fit(self, x: torch.Tensor, q_range: torch.Tensor) -> "Normalizer":
        """Fit x statistics on the train split; q uses the model's limits, not the data's."""
        x = torch.as_tensor(x, dtype=torch.float64)
        self.x_mean.copy_(x.mean(0))
        self.x_std.copy_(x.std(0).clamp_min(1e-9))  # a constant channel must not divide by zero
        q_range = torch.as_tensor(q_range, dtype=torch.float64)
        self.q_lo.copy_(q_range[:, 0])
        self.q_hi.copy_(q_range[:, 1])
        return self

    def affine(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """``(q_scale, q_shift, x_scale, x_shift)``, float64: ``q_n = q q_scale + q_shift`` and
        ``x_n = x x_scale + x_shift``, the maps of ``encode_q`` / ``encode_x`` as one multiply-add each."""
        q_scale = 2.0 / (self.q_hi - self.q_lo)
        x_scale = 1.0 / self.x_std
        return q_scale, -self.q_lo * q_scale - 1.0, x_scale, -self.x_mean * x_scale

    def encode_x(self, x):
        return (x - self.x_mean.to(x.dtype)) / self.x_std.to(x.dtype)

    def decode_x(self, x_n):
        return x_n * self.x_std.to(x_n.dtype) + self.x_mean.to(x_n.dtype)

    def encode_q(self, q):
        return encode_q(q, self.q_lo.to(q.dtype), self.q_hi.to(q.dtype))

    def decode_q(self, q_n):
        return decode_q(q_n, self.q_lo.to(q_n.dtype), self.q_hi.to(q_n.dtype))
