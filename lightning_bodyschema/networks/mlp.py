"""Plain ``nn.Module`` networks for the body schemas (paper section IV-A); no Lightning here.

Sizes, with x = [l_motor, f] (2M), q (N) and z_latent (L):

- AE / VAE encoder and decoder: "three-layer MLP, 64 hidden, Tanh" read as three ``Linear`` layers (two hidden
  layers of 64), which reproduces the paper's totals for M = 6, N = 2: AE latent 3/10/30 -> 10,383 / 11,286 / 13,866
  parameters (paper ~10k/11k/14k), VAE -> 10,448 / 11,806 / 15,686 (paper ~11k/12k/15k).
- Diffusion eps-predictor: two hidden layers of 91 SiLU units on (x_t, t/T, q): 10,932 (paper ~11k).

All tensors are batched ``(B, D)``; x is z-scored (dimensionless), q in rad.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Callable, Optional, Sequence

import torch
from torch import nn

from ..errors import BodySchemaInputError

ActivationSpec = str | type[nn.Module]
_ACTIVATIONS: dict[str, type[nn.Module]] = {
    "tanh": nn.Tanh, "silu": nn.SiLU, "relu": nn.ReLU, "gelu": nn.GELU, "elu": nn.ELU, "softplus": nn.Softplus,
}


def _activation_class(activation: ActivationSpec) -> type[nn.Module]:
    """Resolve a name ("tanh", "silu", ...) or an ``nn.Module`` subclass; names keep configs readable."""
    if isinstance(activation, type) and issubclass(activation, nn.Module):
        return activation
    if isinstance(activation, str) and activation.lower() in _ACTIVATIONS:
        return _ACTIVATIONS[activation.lower()]
    raise BodySchemaInputError(
        f"activation={activation!r} is not known; use one of {sorted(_ACTIVATIONS)} or an nn.Module class")


def check_dims(**dims: int) -> None:
    """Every size must be an int >= 1 (0 would build an empty layer that trains silently to nothing)."""
    for name, value in dims.items():
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise BodySchemaInputError(f"{name}={value!r} must be an integer >= 1")


def count_parameters(module: nn.Module) -> int:
    """Number of trainable scalars (what the paper's "~11k parameters" counts)."""
    return sum(p.numel() for p in module.parameters() if p.requires_grad)


class MLP(nn.Module):
    """``in_dim -> [hidden, act] x n_hidden_layers -> out_dim``: ``n_hidden_layers + 1`` ``Linear`` layers, the
    output linear."""

    def __init__(self, in_dim: int, hidden: int, out_dim: int, n_hidden_layers: int = 2,
                 activation: ActivationSpec = "tanh"):
        super().__init__()
        check_dims(in_dim=in_dim, hidden=hidden, out_dim=out_dim, n_hidden_layers=n_hidden_layers)
        act = _activation_class(activation)
        widths = [in_dim] + [hidden] * n_hidden_layers
        layers: list[nn.Module] = []
        for w_in, w_out in zip(widths[:-1], widths[1:]):
            layers += [nn.Linear(w_in, w_out), act()]
        layers.append(nn.Linear(widths[-1], out_dim))
        self.net = nn.Sequential(*layers)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x)


class AEEncoder(nn.Module):
    """h_enc^ae: x (B, x_dim) -> (z_q (B, q_dim), z_latent (B, z_latent_dim)): one MLP whose output is split (z_q
    and z_latent share the hidden features; paper: one encoder)."""

    latent_parts = 1  # outputs of size z_latent_dim after z_q

    def __init__(self, x_dim: int, q_dim: int, z_latent_dim: int, hidden: int = 64,
                 n_hidden_layers: int = 2, activation: ActivationSpec = "tanh"):
        super().__init__()
        check_dims(x_dim=x_dim, q_dim=q_dim, z_latent_dim=z_latent_dim)
        self.q_dim, self.z_latent_dim = q_dim, z_latent_dim
        self.mlp = MLP(x_dim, hidden, q_dim + self.latent_parts * z_latent_dim, n_hidden_layers, activation)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, ...]:
        return self.mlp(x).split([self.q_dim] + [self.z_latent_dim] * self.latent_parts, dim=-1)


class VAEEncoder(AEEncoder):
    """h_enc^vae: x (B, x_dim) -> (z_q, mu, logvar), mu and logvar (B, z_latent_dim): log sigma^2 rather than the
    paper's sigma (unconstrained; ``sigma = exp(0.5 * logvar)``)."""

    latent_parts = 2


class Decoder(nn.Module):
    """h_dec^{ae,vae}: (q or z_q (B, q_dim), z_latent (B, z_latent_dim)) -> x_hat (B, x_dim) (eq:ae-vae)."""

    def __init__(self, q_dim: int, z_latent_dim: int, x_dim: int, hidden: int = 64,
                 n_hidden_layers: int = 2, activation: ActivationSpec = "tanh"):
        super().__init__()
        check_dims(q_dim=q_dim, z_latent_dim=z_latent_dim, x_dim=x_dim)
        self.q_dim, self.z_latent_dim = q_dim, z_latent_dim
        self.mlp = MLP(q_dim + z_latent_dim, hidden, x_dim, n_hidden_layers, activation)

    def forward(self, q: torch.Tensor, z_latent: torch.Tensor) -> torch.Tensor:
        return self.mlp(torch.cat([q, z_latent], dim=-1))

    def frozen(self) -> Optional["FrozenMLP"]:
        """An inference-only snapshot for latent descent (``FrozenMLP``: free columns z_latent, fixed q: its
        ``first_bias(q)``); None without a hand-written derivative."""
        return FrozenMLP.of(self.mlp, slice(self.q_dim, None))


def build_autoencoder(x_dim: int, q_dim: int, latent_dim: int, variational: bool = False, hidden: int = 64,
                      n_hidden_layers: int = 2, activation: ActivationSpec = "tanh") -> tuple[AEEncoder, Decoder]:
    """Encoder and decoder for the paper's AE / VAE; ``latent_dim``: the paper's total latent size (3, 10, 30) =
    dim z_q (= q_dim) + dim z_latent, so it must exceed q_dim (no z_latent: nothing to adapt to a fault)."""
    check_dims(latent_dim=latent_dim)
    if latent_dim <= q_dim:
        raise BodySchemaInputError(
            f"latent_dim={latent_dim} must exceed q_dim={q_dim}: it counts z_q ({q_dim}) plus at least one z_latent")
    z_latent_dim = latent_dim - q_dim
    enc_cls = VAEEncoder if variational else AEEncoder
    encoder = enc_cls(x_dim, q_dim, z_latent_dim, hidden, n_hidden_layers, activation)
    return encoder, Decoder(q_dim, z_latent_dim, x_dim, hidden, n_hidden_layers, activation)


class EpsMLP(nn.Module):
    """h^diff: (x_t (B, x_dim), t (int or (B,) long), q (B, q_dim)) -> the schema's prediction (B, x_dim): eps_hat
    for the paper's eps-prediction (or x0_hat, or v; ``samplers.schedule.PREDICTIONS``).

    Time embedding: the single scalar ``t / n_timesteps`` in [0, 1), appended to the input (one input column: the
    paper's ~11k parameters exactly, 10,932 for x_dim 12, q_dim 2; DDPM and strided DDIM steps both pass integer t).
    """

    def __init__(self, x_dim: int, q_dim: int, hidden: int = 91, n_hidden: int = 2,
                 activation: ActivationSpec = "silu", n_timesteps: int = 200):
        super().__init__()
        check_dims(x_dim=x_dim, q_dim=q_dim, n_timesteps=n_timesteps)
        self.x_dim, self.q_dim, self.n_timesteps = x_dim, q_dim, n_timesteps
        self.mlp = MLP(x_dim + 1 + q_dim, hidden, x_dim, n_hidden, activation)

    def forward(self, x_t: torch.Tensor, t: int | torch.Tensor, q: torch.Tensor) -> torch.Tensor:
        if isinstance(t, torch.Tensor):
            t_feat = (t.detach().to(x_t.dtype) / self.n_timesteps).reshape(-1, 1).expand(x_t.shape[0], 1)
        else:
            t_feat = x_t.new_full((x_t.shape[0], 1), t / self.n_timesteps)
        return self.mlp(torch.cat([x_t, t_feat, q], dim=-1))

    def frozen(self) -> Optional["FrozenMLP"]:
        """An inference-only snapshot for sampling loops: free columns x_t, fixed columns [t/T, q] (``FrozenMLP``).
        None for activations without a hand-written derivative (samplers then run the autograd reference)."""
        return FrozenMLP.of(self.mlp, slice(0, self.x_dim))

    def step_biases(self, frozen: "FrozenMLP", q: torch.Tensor, timesteps: Sequence[int]) -> torch.Tensor:
        """First-layer bias of every step of a sampling loop, (S, B, H): ``b1 + (t_i / T) w_t + q W_q^T`` (the t/T
        and q columns are fixed for a whole loop: a step pays only for its x_t columns)."""
        t_feat = q.new_tensor([t / self.n_timesteps for t in timesteps])
        w_t, w_q = frozen.w1_rest_t[0], frozen.w1_rest_t[1:]  # rest columns in input order: t/T, then q
        base = torch.addmm(frozen.b1, q.detach(), w_q)  # (B, H)
        return torch.addcmul(base.unsqueeze(0), t_feat.view(-1, 1, 1), w_t.view(1, 1, -1))


_FROZEN_ACTIVATIONS = (nn.SiLU, nn.Tanh)  # activations with a hand-written derivative (ATen's fused backward)


@dataclass(frozen=True)
class ActivationOps:
    """The activation and its backward, both writing into given buffers: ``act(a, out=h)``,
    ``act_backward(g, saved, grad_input=o)`` (saved: the pre-activation for SiLU, the output for Tanh). ``eager``:
    the raw C++ bindings (less dispatch per op); ``traceable``: the ATen overloads ``torch.compile`` traces."""

    act: Callable
    act_backward: Callable


class FrozenMLP:
    """Inference-only snapshot of an ``MLP``: its forward and reverse-mode backward pass written out by hand (the
    samplers' loops; ``networks.structured.JacobianMLP`` carries forward-mode tangents instead).

    The input is split into *free* columns (a slice: what the loop updates, x_t or z_latent) and the rest (fixed for a
    whole loop: t/T and q), whose first-layer contribution is folded into a bias once (``first_bias``). Plain
    pre-transposed tensors, no autograd, no ``nn.Module`` dispatch. The weights are copied when it is built and never
    follow the module; whoever holds one decides when to rebuild.

    Blocks a sampler fuses its own arithmetic around: ``trunk``, the output layer (``out = out_b + h out_w_t``,
    ``out_w`` its transpose) and ``back`` (times ``w1_free``: dL/dx_free). Only SiLU and Tanh (``of`` returns None
    else).
    """

    @classmethod
    def of(cls, mlp: MLP, free: slice) -> Optional["FrozenMLP"]:
        """The snapshot, or None when the activation has no hand-written derivative."""
        return cls(mlp, free) if type(mlp.net[1]) in _FROZEN_ACTIVATIONS else None

    def __init__(self, mlp: MLP, free: slice):
        copy = lambda t: t.detach().clone(memory_format=torch.contiguous_format)  # noqa: E731
        first, *hidden, out = list(mlp.net)[::2]
        self.silu = type(mlp.net[1]) is nn.SiLU
        free_cols = range(*free.indices(first.in_features))
        rest_cols = [i for i in range(first.in_features) if i not in free_cols]  # in input order
        w1_free = first.weight[:, free]
        self.w1_free_t, self.w1_free = copy(w1_free.t()), copy(w1_free)  # (n_free, H), (H, n_free)
        self.w1_rest_t = copy(first.weight[:, rest_cols].t())  # (n_rest, H)
        self.b1 = copy(first.bias)
        # hidden-to-hidden layers: (W^T for the forward pass, W for the backward pass, b)
        self.hidden = [(copy(m.weight.t()), copy(m.weight), copy(m.bias)) for m in hidden]
        self.out_w_t, self.out_w = copy(out.weight.t()), copy(out.weight)
        self.out_b = copy(out.bias)
        aten = torch.ops.aten
        act, backward = (aten.silu, aten.silu_backward) if self.silu else (aten.tanh, aten.tanh_backward)
        self.traceable = ActivationOps(act.out, backward.grad_input)
        self.eager = ActivationOps(getattr(torch._C._nn, "silu", act.out) if self.silu else torch.tanh,
                                   getattr(backward.grad_input, "_op", backward.grad_input))

    def first_bias(self, rest: torch.Tensor) -> torch.Tensor:
        """First-layer pre-activation from the fixed columns ``rest (B, n_rest)``: ``b1 + rest W1_rest^T``."""
        return torch.addmm(self.b1, rest, self.w1_rest_t)

    def buffers(self, batch: int, like: torch.Tensor) -> tuple[list, list, list]:
        """(pre, post, grads): per-layer (B, H) buffers for ``trunk`` and ``back``, allocated once per loop."""
        n_layers = 1 + len(self.hidden)
        new = functools.partial(like.new_empty, (batch, self.b1.shape[0]))
        return [new() for _ in range(n_layers)], [new() for _ in range(n_layers)], [new() for _ in range(2)]

    def trunk(self, u: torch.Tensor, bias: torch.Tensor, w1_t: torch.Tensor, bufs, ops: ActivationOps):
        """Last hidden features (B, H) of free input ``u (B, n_free)`` for a first-layer weight ``w1_t``
        (``w1_free_t`` or a scaled copy) and what ``back`` needs (every layer's pre-activation for SiLU, output for
        Tanh), written into ``bufs`` (``buffers``)."""
        pre, post, _ = bufs
        ops.act(torch.addmm(bias, u, w1_t, out=pre[0]), out=post[0])
        for i, (w_t, _, b) in enumerate(self.hidden, start=1):
            ops.act(torch.addmm(b, post[i - 1], w_t, out=pre[i]), out=post[i])
        return post[-1], (pre if self.silu else post)

    def back(self, g_out: torch.Tensor, w_out: torch.Tensor, saved: list, bufs, ops: ActivationOps) -> torch.Tensor:
        """dL/d(first-layer pre-activation) (B, H) from dL/d(output) ``g_out (B, out)`` through the output weight
        ``w_out`` (``out_w`` or a scaled copy); alternates between the two gradient buffers of ``bufs``."""
        grads = bufs[2]
        g = ops.act_backward(torch.mm(g_out, w_out, out=grads[0]), saved[-1], grad_input=grads[1])
        for (_, w, _), s in zip(reversed(self.hidden), reversed(saved[:-1])):
            g = ops.act_backward(torch.mm(g, w, out=grads[0]), s, grad_input=grads[1])
        return g
