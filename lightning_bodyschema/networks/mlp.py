"""Plain ``nn.Module`` networks for the body schemas (paper section IV-A); no Lightning here.

Sizes, with x = [l_motor, f] (2M), q (N) and z_latent (L):

- AE / VAE encoder and decoder: "three-layer MLP, 64 hidden, Tanh" read as three ``Linear`` layers
  (two hidden layers of 64). That reading reproduces the paper's totals for M = 6, N = 2:
  AE latent 3/10/30 -> 10,383 / 11,286 / 13,866 parameters (paper ~10k/11k/14k),
  VAE -> 10,448 / 11,806 / 15,686 (paper ~11k/12k/15k). Three hidden layers would add 8,320
  (two 64x64 layers) and miss every figure by > 70%.
- Diffusion eps-predictor: two hidden layers of 91 SiLU units on (x_t, t/T, q): 10,932 (paper ~11k).

All tensors are batched ``(B, D)``; x is z-scored (dimensionless), q in rad.
"""
from __future__ import annotations

import functools

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


def _check_dims(**dims: int) -> None:
    """Every size must be an int >= 1 (0 would build an empty layer that trains silently to nothing)."""
    for name, value in dims.items():
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise BodySchemaInputError(f"{name}={value!r} must be an integer >= 1")


def count_parameters(module: nn.Module) -> int:
    """Number of trainable scalars (what the paper's "~11k parameters" counts)."""
    return sum(p.numel() for p in module.parameters() if p.requires_grad)


class MLP(nn.Module):
    """``in_dim -> [hidden, act] x n_hidden_layers -> out_dim`` (linear output, no output activation).

    ``n_hidden_layers`` counts hidden layers, so the number of ``Linear`` layers is n_hidden_layers + 1.
    """

    def __init__(self, in_dim: int, hidden: int, out_dim: int, n_hidden_layers: int = 2,
                 activation: ActivationSpec = "tanh"):
        super().__init__()
        _check_dims(in_dim=in_dim, hidden=hidden, out_dim=out_dim, n_hidden_layers=n_hidden_layers)
        act = _activation_class(activation)
        widths = [in_dim] + [hidden] * n_hidden_layers
        layers: list[nn.Module] = []
        for w_in, w_out in zip(widths[:-1], widths[1:]):
            layers += [nn.Linear(w_in, w_out), act()]
        layers.append(nn.Linear(widths[-1], out_dim))
        self.net = nn.Sequential(*layers)
        self.in_dim, self.out_dim = in_dim, out_dim

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x (B, in_dim) -> (B, out_dim)."""
        return self.net(x)

    def frozen(self, free: slice) -> Optional["FrozenMLP"]:
        """Inference-only view for fast loops over the input columns ``free`` (see ``FrozenMLP``).

        None when an activation has no hand-written derivative (callers fall back to autograd). Cached
        until a parameter changes (in-place optimizer steps bump the tensors' versions) or moves.
        """
        modules = list(self.net._modules.values())  # plain dict access: nn.Module attribute lookup is slow
        if type(modules[1]) not in _ACT_AND_GRAD:
            return None
        params = [p for layer in modules[::2] for p in layer._parameters.values()]
        key = [free.indices(self.in_dim)] + [(p.data_ptr(), p._version, p.dtype) for p in params]
        cached = self.__dict__.get("_frozen")
        if cached is None or cached[0] != key:
            # the entry keeps the parameters' storages alive, so no new tensor can reuse their addresses
            cached = (key, FrozenMLP(self, free), [p.detach() for p in params])
            self.__dict__["_frozen"] = cached
        return cached[1]


class AEEncoder(nn.Module):
    """h_enc^ae: x (B, x_dim) -> (z_q (B, q_dim), z_latent (B, z_latent_dim)).

    One MLP whose output is split, so z_q and z_latent share the hidden features (paper: one encoder).
    """

    def __init__(self, x_dim: int, q_dim: int, z_latent_dim: int, hidden: int = 64,
                 n_hidden_layers: int = 2, activation: ActivationSpec = "tanh"):
        super().__init__()
        _check_dims(x_dim=x_dim, q_dim=q_dim, z_latent_dim=z_latent_dim)
        self.q_dim, self.z_latent_dim = q_dim, z_latent_dim
        self.mlp = MLP(x_dim, hidden, q_dim + self._n_latent_outputs(), n_hidden_layers, activation)

    def _n_latent_outputs(self) -> int:
        return self.z_latent_dim

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        out = self.mlp(x)
        return out[..., :self.q_dim], out[..., self.q_dim:]


class VAEEncoder(AEEncoder):
    """h_enc^vae: x (B, x_dim) -> (z_q, mu, logvar), mu and logvar (B, z_latent_dim).

    Outputs log sigma^2 rather than the paper's sigma: unconstrained, so no positivity clamp is
    needed, and the KL term is closed-form in it. ``sigma = exp(0.5 * logvar)``.
    """

    def _n_latent_outputs(self) -> int:
        return 2 * self.z_latent_dim

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        out = self.mlp(x)
        q_end, mu_end = self.q_dim, self.q_dim + self.z_latent_dim
        return out[..., :q_end], out[..., q_end:mu_end], out[..., mu_end:]


class Decoder(nn.Module):
    """h_dec^{ae,vae}: (q or z_q (B, q_dim), z_latent (B, z_latent_dim)) -> x_hat (B, x_dim) (eq:ae-vae)."""

    def __init__(self, q_dim: int, z_latent_dim: int, x_dim: int, hidden: int = 64,
                 n_hidden_layers: int = 2, activation: ActivationSpec = "tanh"):
        super().__init__()
        _check_dims(q_dim=q_dim, z_latent_dim=z_latent_dim, x_dim=x_dim)
        self.q_dim, self.z_latent_dim = q_dim, z_latent_dim
        self.mlp = MLP(q_dim + z_latent_dim, hidden, x_dim, n_hidden_layers, activation)

    def forward(self, q: torch.Tensor, z_latent: torch.Tensor) -> torch.Tensor:
        return self.mlp(torch.cat([q, z_latent], dim=-1))

    def bind(self, q: torch.Tensor) -> Optional[tuple["FrozenMLP", torch.Tensor]]:
        """``(frozen, bias)`` for fast loops over z_latent at fixed ``q (B, q_dim)``:
        ``frozen.forward(z, bias)`` is ``self(q, z)``; ``frozen.forward_vjp`` adds d x_hat / d z_latent.
        None for activations without a hand-written derivative.
        """
        frozen = self.mlp.frozen(slice(self.q_dim, None))
        return None if frozen is None else (frozen, frozen.first_bias(q.detach()))


def build_autoencoder(x_dim: int, q_dim: int, latent_dim: int, variational: bool = False, hidden: int = 64,
                      n_hidden_layers: int = 2, activation: ActivationSpec = "tanh") -> tuple[AEEncoder, Decoder]:
    """Encoder and decoder for the paper's AE / VAE.

    ``latent_dim`` is the paper's total latent size (3, 10, 30) = dim z_q (= q_dim) + dim z_latent,
    so it must exceed q_dim: with no z_latent there is nothing left to adapt to a fault.
    """
    _check_dims(latent_dim=latent_dim)
    if latent_dim <= q_dim:
        raise BodySchemaInputError(
            f"latent_dim={latent_dim} must exceed q_dim={q_dim}: it counts z_q ({q_dim}) plus at least one z_latent")
    z_latent_dim = latent_dim - q_dim
    enc_cls = VAEEncoder if variational else AEEncoder
    encoder = enc_cls(x_dim, q_dim, z_latent_dim, hidden, n_hidden_layers, activation)
    return encoder, Decoder(q_dim, z_latent_dim, x_dim, hidden, n_hidden_layers, activation)


def _silu_and_grad(a: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """silu(a) and silu'(a) = s (1 + a (1 - s)) = s + silu(a) (1 - s), sharing the sigmoid s."""
    s = torch.sigmoid(a)
    h = a * s
    return h, s + h - h * s  # tensor-tensor ops only: ``1.0 - s`` goes through a slow Python rsub


def _tanh_and_grad(a: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    h = torch.tanh(a)
    return h, (h * h).neg_().add_(1.0)  # 1 - h^2 without the Python-level rsub


# activations with a hand-written derivative for EpsMLP.eps_and_vjp; others fall back to autograd
_ACT_AND_GRAD: dict[type[nn.Module], Callable[[torch.Tensor], tuple[torch.Tensor, torch.Tensor]]] = {
    nn.SiLU: _silu_and_grad, nn.Tanh: _tanh_and_grad}


class EpsMLP(nn.Module):
    """h^diff: (x_t (B, x_dim), t (int or (B,) long), q (B, q_dim)) -> eps_hat (B, x_dim).

    Time embedding: the single scalar ``t / n_timesteps`` in [0, 1), appended to the input. Why:
    it is the cheapest choice (one input column, 91 weights), it reproduces the paper's ~11k
    parameters exactly (10,932 for x_dim 12, q_dim 2; 16 sinusoidal features would add ~1.4k), the
    noise level varies smoothly with t so 91 SiLU units can build their own features from it, and it
    is already O(1) like the z-scored x. Both DDPM and strided DDIM steps pass integer t, so a
    scalar in the same units serves both.
    """

    def __init__(self, x_dim: int, q_dim: int, hidden: int = 91, n_hidden: int = 2,
                 activation: ActivationSpec = "silu", n_timesteps: int = 200):
        super().__init__()
        _check_dims(x_dim=x_dim, q_dim=q_dim, n_timesteps=n_timesteps)
        self.x_dim, self.q_dim, self.n_timesteps = x_dim, q_dim, n_timesteps
        self.mlp = MLP(x_dim + 1 + q_dim, hidden, x_dim, n_hidden, activation)

    def _inputs(self, x_t: torch.Tensor, t: int | torch.Tensor, q: torch.Tensor) -> torch.Tensor:
        """Concatenate [x_t, t/T, q] -> (B, x_dim + 1 + q_dim)."""
        if isinstance(t, torch.Tensor):
            t_feat = (t.detach().to(x_t.dtype) / self.n_timesteps).reshape(-1, 1).expand(x_t.shape[0], 1)
        else:
            t_feat = x_t.new_full((x_t.shape[0], 1), t / self.n_timesteps)
        return torch.cat([x_t, t_feat, q], dim=-1)

    def forward(self, x_t: torch.Tensor, t: int | torch.Tensor, q: torch.Tensor) -> torch.Tensor:
        return self.mlp(self._inputs(x_t, t, q))

    def eps_and_vjp(self, x_t: torch.Tensor, t: int | torch.Tensor, q: torch.Tensor
                    ) -> tuple[torch.Tensor, Callable[[torch.Tensor], torch.Tensor]]:
        """eps_hat (B, x_dim) and ``vjp: v (B, x_dim) -> v^T d eps_hat / d x_t`` (B, x_dim), without autograd.

        For guided denoising (eq:diff-adapt): with g = dL/dx0_hat, grad_{x_t} L(x0_hat(x_t)) is
        ``(g - sqrt(1 - abar_t) * vjp(g)) / sqrt(abar_t)``. A hand-written backward pass through the
        stored activation derivatives skips autograd's graph bookkeeping, which dominates for an
        11k-parameter MLP: measured ~2x faster than ``torch.autograd.grad`` on the 2-core CPU (forward
        + vjp: ~100 vs ~200 us at batch 1, ~160 vs ~270 us at batch 40; one thread, machine busy).
        Inference only: outputs carry no graph. Activations other than SiLU and Tanh use autograd.
        """
        act_and_grad = _ACT_AND_GRAD.get(type(self.mlp.net[1]))
        if act_and_grad is None:
            return self._eps_and_vjp_autograd(x_t, t, q)
        # plain tensors sharing the parameters' storage: ops on nn.Parameter pay a dispatch toll
        ws = [(m.weight.detach(), m.bias.detach()) for m in list(self.mlp.net)[::2]]
        # all operands are detached, so no graph is built even with grad mode on
        h, dacts = self._inputs(x_t.detach(), t, q.detach()), []
        for w, b in ws[:-1]:
            h, dact = act_and_grad(torch.addmm(b, h, w.t()))
            dacts.append(dact)  # act'(pre-activation), needed by the backward pass
        eps = torch.addmm(ws[-1][1], h, ws[-1][0].t())

        def vjp(v: torch.Tensor) -> torch.Tensor:
            g = v.detach() @ ws[-1][0]
            for (w, _), dact in zip(reversed(ws[1:-1]), reversed(dacts[1:])):
                g = (g * dact) @ w
            # only the x_t columns of the first layer: t and q are not differentiated
            return (g * dacts[0]) @ ws[0][0][:, :self.x_dim]
        return eps, vjp

    def bind(self, q: torch.Tensor, timesteps: Sequence[int]) -> Optional[BoundEps]:
        """Fast evaluator for a sampling loop over ``timesteps`` at fixed conditions ``q (B, q_dim)``.

        Same maths as ``forward``/``eps_and_vjp`` (up to float rounding), None for activations without a
        hand-written derivative. Inference only; weights are read when called (cached until they change).
        """
        frozen = self.mlp.frozen(slice(0, self.x_dim))
        if frozen is None:
            return None
        q = q.detach()
        t_key = (tuple(timesteps), q.dtype, q.device)
        cached = self.__dict__.get("_t_feat")
        if cached is None or cached[0] != t_key:
            cached = (t_key, torch.tensor([t / self.n_timesteps for t in timesteps], dtype=q.dtype, device=q.device))
            self.__dict__["_t_feat"] = cached
        t_feat = cached[1]
        # bias of step i: b1 + (t_i / T) w_t + q W_q^T, all steps in one broadcast op
        w_t = frozen.w1_rest_t[0]  # (H,): the t/T column
        base = torch.addmm(frozen.b1, q, frozen.w1_rest_t[1:])  # (B, H)
        stacked = torch.addcmul(base.unsqueeze(0), t_feat.view(-1, 1, 1), w_t.view(1, 1, -1))  # (S, B, H)
        return BoundEps(frozen, stacked)

    def _eps_and_vjp_autograd(self, x_t, t, q):
        with torch.enable_grad():
            x = x_t.detach().requires_grad_(True)
            eps = self(x, t, q)

        def vjp(v: torch.Tensor) -> torch.Tensor:
            return torch.autograd.grad(eps, x, v, retain_graph=True)[0]
        return eps.detach(), vjp


class FrozenMLP:
    """Inference-only copy of an ``MLP``'s weights for fast loops (guided denoising, latent descent).

    The input is split into *free* columns (a slice: what the loop updates, e.g. x_t or z_latent)
    and the rest (fixed for the whole loop, e.g. t/T and q), whose first-layer contribution is
    folded into a bias computed once with ``first_bias``. Plain tensors, pre-transposed contiguous
    weights, no autograd and no ``nn.Module`` dispatch: at batch 1 every tensor op costs a few
    microseconds of dispatch, so the op count is the cost. One ``addmm`` and one activation per
    layer forward; the backward pass uses ATen's fused activation backward (``silu_backward`` /
    ``tanh_backward``: one op instead of four for SiLU's derivative).

    Building blocks, so that a sampler can fuse its own arithmetic into the layers (``samplers.guided``'s
    fused loops inline them): ``trunk(x, bias) -> (h, saved)`` (last hidden features), ``out_w_t``/``out_w``/
    ``out_b`` (output layer, out = out_b + h out_w_t), ``back(g_h, saved)`` (dL/dh_last -> dL/d first
    pre-activation; times ``w1_free`` it is dL/dx_free), ``hidden`` (W^T, W, b) per hidden-to-hidden layer,
    ``_act``/``_act_backward``. Only SiLU and Tanh; ``MLP.frozen`` returns None otherwise.
    """

    def __init__(self, mlp: MLP, free: slice):
        linears = list(mlp.net)[::2]
        self.silu = type(mlp.net[1]) is nn.SiLU
        w1 = linears[0].weight.detach()
        free_cols = range(*free.indices(mlp.in_dim))
        rest_cols = [i for i in range(mlp.in_dim) if i not in free_cols]  # in input order
        self.w1_free_t = w1[:, free].t().contiguous()  # (n_free, H): forward
        self.w1_free = w1[:, free].contiguous()  # (H, n_free): backward
        self.w1_rest_t = w1[:, rest_cols].t().contiguous()  # (n_rest, H)
        self.b1 = linears[0].bias.detach().clone()
        # hidden-to-hidden layers: (W^T for forward, W for backward, b)
        self.hidden = [(m.weight.detach().t().contiguous(), m.weight.detach().contiguous(), m.bias.detach().clone())
                       for m in linears[1:-1]]
        out = linears[-1]
        self.out_w_t, self.out_w = out.weight.detach().t().contiguous(), out.weight.detach().contiguous()
        self.out_b = out.bias.detach().clone()
        # silu without F.silu's Python wrapper (private binding; the public function if it ever goes away)
        self._act = getattr(torch._C._nn, "silu", torch.nn.functional.silu) if self.silu else torch.tanh
        # grad * act'(.) from what ``trunk`` saved: the pre-activation (SiLU) or the output (Tanh); the raw
        # overload skips OpOverload.__call__'s Python frame (~0.4 us per call at batch 1)
        backward = torch.ops.aten.silu_backward.default if self.silu else torch.ops.aten.tanh_backward.default
        self._act_backward = getattr(backward, "_op", backward)
        # the same two ops writing into given buffers (``act(a, out=h)``, ``act_backward(g, s, grad_input=o)``)
        # for loops that allocate once, and as public ops that torch.compile can trace
        self.act_out = self._act
        self.act_backward_out = (torch.ops.aten.silu_backward if self.silu else torch.ops.aten.tanh_backward).grad_input
        self.traceable_act = (torch.nn.functional.silu if self.silu else torch.tanh), backward

    def first_bias(self, rest: torch.Tensor) -> torch.Tensor:
        """First-layer pre-activation from the fixed columns ``rest (B, n_rest)``: ``b1 + rest W1_rest^T``."""
        return torch.addmm(self.b1, rest, self.w1_rest_t)

    def trunk(self, x_free: torch.Tensor, bias: torch.Tensor) -> tuple[torch.Tensor, list]:
        """Last hidden features (B, H) and what ``back`` needs, for ``x_free (B, n_free)`` and a ``first_bias``."""
        a = torch.addmm(bias, x_free, self.w1_free_t)
        h = self._act(a)
        saved = [a if self.silu else h]
        for w_t, _, b in self.hidden:
            a = torch.addmm(b, h, w_t)
            h = self._act(a)
            saved.append(a if self.silu else h)
        return h, saved

    def back(self, g_h: torch.Tensor, saved: list) -> torch.Tensor:
        """dL/dh_last (B, H) -> dL/d(first-layer pre-activation) (B, H)."""
        g = self._act_backward(g_h, saved[-1])
        for (_, w, _), s in zip(reversed(self.hidden), reversed(saved[:-1])):
            g = self._act_backward(g @ w, s)
        return g

    def forward(self, x_free: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
        """Output (B, out)."""
        return torch.addmm(self.out_b, self.trunk(x_free, bias)[0], self.out_w_t)

    def forward_vjp(self, x_free: torch.Tensor, bias: torch.Tensor
                    ) -> tuple[torch.Tensor, Callable[[torch.Tensor], torch.Tensor]]:
        """Output and ``vjp: v (B, out) -> v^T d out / d x_free`` (B, n_free)."""
        h, saved = self.trunk(x_free, bias)

        def vjp(v: torch.Tensor) -> torch.Tensor:
            return self.back(v @ self.out_w, saved) @ self.w1_free

        return torch.addmm(self.out_b, h, self.out_w_t), vjp


class BoundEps:
    """``EpsMLP`` bound to one batch's conditions q and a list of timesteps (``EpsMLP.bind``).

    ``eps(x, i)`` and ``eps_and_vjp(x, i)`` evaluate h^diff(x, timesteps[i], q); the t/T and q columns of
    the first layer are precomputed for every step at once, so a step costs only the x_t columns.
    """

    def __init__(self, frozen: FrozenMLP, stacked_biases: torch.Tensor):
        self.frozen, self.stacked_biases = frozen, stacked_biases  # (S, B, H): step i's first-layer bias

    @functools.cached_property
    def biases(self) -> tuple[torch.Tensor, ...]:
        """Step i's first-layer bias (B, H), as separate views."""
        return self.stacked_biases.unbind(0)

    def eps(self, x_t: torch.Tensor, i: int) -> torch.Tensor:
        return self.frozen.forward(x_t, self.biases[i])

    def eps_and_vjp(self, x_t: torch.Tensor, i: int):
        return self.frozen.forward_vjp(x_t, self.biases[i])
