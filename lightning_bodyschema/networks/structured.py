"""An MLP that returns its output and its input Jacobian in one pass (forward-mode tangents), for the structured
schema: a learned length map whose derivative is the moment-arm matrix, and a learned potential whose derivative is
a torque. Plain PyTorch, no Lightning.
"""
from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F

from ..errors import BodySchemaInputError


def _silu_derivative(h: torch.Tensor) -> torch.Tensor:
    s = torch.sigmoid(h)
    return s * (1.0 + h * (1.0 - s))


class JacobianMLP(nn.Module):
    """``y = MLP(x)`` (SiLU hidden layers, linear output) with ``dy/dx`` carried alongside.

    Args:
        in_dim, out_dim: sizes of x (B, in_dim) and y (B, out_dim).
        hidden, n_hidden: width and number of hidden layers (each >= 1).
    ``forward(x)`` gives y; ``with_jacobian(x)`` gives ``(y, J)`` with ``J (B, out_dim, in_dim) = dy/dx``, exact (the
    chain rule through each layer, differentiable by autograd in the weights), at ``in_dim + 1`` times the cost.
    """

    def __init__(self, in_dim: int, out_dim: int, hidden: int = 256, n_hidden: int = 3):
        super().__init__()
        for name, value in (("in_dim", in_dim), ("out_dim", out_dim), ("hidden", hidden), ("n_hidden", n_hidden)):
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise BodySchemaInputError(f"{name}={value!r} must be an integer >= 1")
        sizes = [in_dim] + [hidden] * n_hidden + [out_dim]
        self.layers = nn.ModuleList(nn.Linear(a, b) for a, b in zip(sizes[:-1], sizes[1:]))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        for layer in self.layers[:-1]:
            x = F.silu(layer(x))
        return self.layers[-1](x)

    def with_jacobian(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(y (B, out), dy/dx (B, out, in)): tangents (B, in, width) pushed through every layer with the values."""
        first = self.layers[0]
        h = first(x)
        tangent = first.weight.T.unsqueeze(0).expand(len(x), -1, -1)  # d h / d x, rows = input directions
        for layer in self.layers[1:]:
            slope = _silu_derivative(h)
            a = F.silu(h)
            tangent = tangent * slope.unsqueeze(1)
            h = layer(a)
            tangent = tangent @ layer.weight.T
        return h, tangent.transpose(1, 2)
