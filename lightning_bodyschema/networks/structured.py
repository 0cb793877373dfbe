"""An MLP that returns its output and its input Jacobian in one pass (forward-mode tangents), for the structured
schema: a learned length map whose derivative is the moment-arm matrix, and a learned potential whose derivative is
a torque. Plain PyTorch, no Lightning.
"""
from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F

from ..errors import BodySchemaInputError
from .mlp import check_dims

BLOCKS = ("plain", "residual")
# postures per pass of ``with_jacobian``: their tangents stay in cache between a layer's elementwise product and its
# matmul (BENCHMARKS.md, "Figures behind code choices")
JACOBIAN_CHUNK = 256
NORMS = ("none", "layer")


def silu_slope(z: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
    """``silu'(z) = s (1 + z (1 - s)) = s + a (1 - s)`` with ``s = sigmoid(z)`` and ``a = silu(z)`` (already made for
    the value: three elementwise passes)."""
    s = torch.sigmoid(z)
    return torch.addcmul(s, a, 1.0 - s)


def check_architecture(block: str, norm: str) -> None:
    """One ``BodySchemaInputError`` naming a ``block`` or ``norm`` outside ``BLOCKS`` / ``NORMS``."""
    for name, value, allowed in (("block", block, BLOCKS), ("norm", norm, NORMS)):
        if value not in allowed:
            raise BodySchemaInputError(f"{name}={value!r}; allowed: {list(allowed)}")


class JacobianMLP(nn.Module):
    """``y = MLP(x)`` (SiLU hidden layers, linear output) with ``dy/dx`` carried alongside.

    Args:
        in_dim, out_dim: sizes of x (B, in_dim) and y (B, out_dim).
        hidden, n_hidden: width and number of hidden layers (each >= 1): an input layer ``h = W_0 x``, then
            ``n_hidden - 1`` hidden steps and the output layer, each applied to ``a = silu(N(h))``.
        block: ``"plain"``: each hidden step is ``h <- W a`` (the default network); ``"residual"``: ``h <- h + W a``
            (pre-norm residual blocks, same weights and cost; the identity path keeps deep stacks trainable).
        norm: ``"none"`` (``N`` the identity) or ``"layer"`` (``N`` a LayerNorm over the width, with its affine
            weight and bias, before every activation).
    ``forward(x)`` gives y; ``with_jacobian(x)`` gives ``(y, J)`` with ``J (B, out_dim, in_dim) = dy/dx``, exact and
    differentiable by autograd in the weights. State: ``layers`` (one ``nn.Linear`` each), with ``norm="layer"``
    ``norms`` (one per activation).
    """

    def __init__(self, in_dim: int, out_dim: int, hidden: int = 256, n_hidden: int = 3, block: str = "plain",
                 norm: str = "none"):
        super().__init__()
        check_dims(in_dim=in_dim, out_dim=out_dim, hidden=hidden, n_hidden=n_hidden)
        check_architecture(block, norm)
        self.residual = block == "residual"
        sizes = [in_dim] + [hidden] * n_hidden + [out_dim]
        self.layers = nn.ModuleList(nn.Linear(a, b) for a, b in zip(sizes[:-1], sizes[1:]))
        self.norms = nn.ModuleList(nn.LayerNorm(hidden) for _ in range(n_hidden)) if norm == "layer" else None

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self._through_layers(x, False)[0]

    def with_jacobian(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(y (B, out), dy/dx (B, out, in)): tangents (B, in, width) pushed through every layer with the values,
        ``JACOBIAN_CHUNK`` postures at a time (each row's numbers do not depend on the others)."""
        if torch.compiler.is_exporting() or len(x) <= JACOBIAN_CHUNK:  # exported: one pass (a symbolic batch)
            return self._through_layers(x, True)
        values, jacobians = zip(*(self._through_layers(part, True) for part in x.split(JACOBIAN_CHUNK)))
        return torch.cat(values), torch.cat(jacobians)

    def _through_layers(self, x: torch.Tensor, tangents: bool) -> tuple[torch.Tensor, torch.Tensor | None]:
        """``(y, dy/dx)``, the Jacobian None without ``tangents`` (``F.linear``, not the modules: no hook dispatch per
        layer)."""
        first, *rest = self.layers  # unpacked, not sliced: a slice of a ModuleList builds a new one
        h = F.linear(x, first.weight, first.bias)
        # d h / d x (1, in, width), rows = input directions, broadcast over B; contiguous (a matmul of the transposed
        # layout is many times slower)
        tangent = first.weight.T.contiguous().unsqueeze(0) if tangents else None
        for i, layer in enumerate(rest):
            norm = None if self.norms is None else self.norms[i]
            residual = self.residual and i < len(rest) - 1  # residual hidden steps add their input; the output never
            z = h if norm is None else norm(h)
            a = F.silu(z)
            if tangents:
                slope = silu_slope(z, a)
                scaled = tangent * slope.unsqueeze(1) if norm is None else _layer_norm_tangent(h, tangent, norm, slope)
                step = F.linear(scaled, layer.weight)
                tangent = tangent + step if residual else step
            out = F.linear(a, layer.weight, layer.bias)
            h = h + out if residual else out
        return h, None if tangent is None else tangent.transpose(1, 2)


def _layer_norm_tangent(h: torch.Tensor, tangent: torch.Tensor, norm: nn.LayerNorm, slope: torch.Tensor):
    """``slope * d LayerNorm(h)`` for tangents ``(B, in, width)`` of ``h (B, width)`` (``slope (B, width)``: the
    next activation's derivative): with ``c = h - mean(h)``, ``s = sqrt(var(h) + eps)`` and ``n = c / s``,
    ``dn = (dc - n mean(n dc)) / s`` times the affine weight, ``mean(n dc) = mean(n dh) - mean(n) mean(dh)``."""
    c = h - h.mean(-1, keepdim=True)
    s = (c.pow(2).mean(-1, keepdim=True) + norm.eps).sqrt()
    n = c / s
    scale = slope / s if norm.weight is None else slope * norm.weight / s
    dh_mean = tangent.mean(-1, keepdim=True)  # (B, in, 1)
    n_dc = (n.unsqueeze(1) * tangent).mean(-1, keepdim=True) - n.mean(-1, keepdim=True).unsqueeze(1) * dh_mean
    return torch.addcmul(tangent - dh_mean, n.unsqueeze(1), n_dc, value=-1.0) * scale.unsqueeze(1)
