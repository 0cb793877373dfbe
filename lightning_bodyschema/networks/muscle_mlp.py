"""The optional per-muscle MLP of a per-muscle path: a small network per muscle (weights ``(M, ...)``) on the joint
angles times the muscle's crossing mask; its moment arms by forward tangents, exactly zero on every joint the muscle
does not cross. Plain PyTorch, no Lightning."""
from __future__ import annotations

import math

import torch
from torch import nn
from torch.nn import functional as F

from .structured import silu_slope


def muscle_mlp_parameters(n_muscles: int, n_joints: int, hidden: int, n_hidden: int):
    """``weights``, ``biases``: ``nn.ParameterList`` of every layer, each ``(M, in, out)`` / ``(M, 1, out)``
    (``nn.Linear``'s initialization, the last layer zero: the polynomial alone until it learns); empty lists
    without hidden layers."""
    if not n_hidden:
        return nn.ParameterList(), nn.ParameterList()
    sizes = [n_joints] + [hidden] * n_hidden + [1]
    weights = nn.ParameterList(nn.Parameter(_uniform((n_muscles, a, b), a)) for a, b in zip(sizes[:-1], sizes[1:]))
    biases = nn.ParameterList(nn.Parameter(_uniform((n_muscles, 1, b), a)) for a, b in zip(sizes[:-1], sizes[1:]))
    with torch.no_grad():
        weights[-1].zero_()
        biases[-1].zero_()
    return weights, biases


def muscle_mlp(path, x: torch.Tensor, slopes: bool):
    """The MLPs of ``path`` (its ``weights``, ``biases``, ``crossing``) on masked inputs ``x (B, N)``: ``(B, M)``
    and, with ``slopes``, ``(B, M, N)`` (else None)."""
    first = path.weights[0] * path.crossing.to(x.dtype)[:, :, None]  # (M, N, K): nothing from an uncrossed joint
    h = torch.einsum("bn,mnk->bmk", x, first) + path.biases[0].transpose(0, 1)
    tangent = first.unsqueeze(0) if slopes else None  # (1, M, N, K)
    for w, b in zip(path.weights[1:], path.biases[1:]):
        a = F.silu(h)
        if slopes:
            tangent = torch.einsum("bmnk,mkj->bmnj", tangent * silu_slope(h, a).unsqueeze(2), w)
        h = torch.einsum("bmk,mkj->bmj", a, w) + b.transpose(0, 1)
    return h[..., 0], None if tangent is None else tangent[..., 0].expand(x.shape[0], -1, -1)


def _uniform(shape, fan_in: int) -> torch.Tensor:
    """``nn.Linear``'s default initialization, for batched per-muscle weights."""
    bound = 1.0 / math.sqrt(fan_in)
    return torch.empty(shape).uniform_(-bound, bound)
