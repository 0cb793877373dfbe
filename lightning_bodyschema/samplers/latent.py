"""Latent-space optimization (paper section III-B, eq:ae-vae and eq:latent-opt): the autograd reference and the fast loop.

``z <- z - lr grad_z L(h_dec(q_ref, z))`` with q fixed to q_ref; the loss comes in as a penalty value
(``faults.penalty.BoxPenalty`` or alike), nothing here imports Lightning or ``faults``. Batched over cases.

* ``reference_latent_descent``: autograd through the decoder and the loss, ``torch.optim.SGD``/``Adam``.
* ``latent_descent``: the same through the decoder's ``FrozenMLP`` snapshot (its hand-written backward) and the
  penalty's analytic residual, with SGD and Adam written out as torch.optim's single-tensor formulas (no weight
  decay). For SGD and a penalty of uniform weight c the update is one ``addmm`` with W = -lr c W1_z.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from ..errors import BodySchemaInputError

OPTIMIZERS = ("sgd", "adam")


@dataclass(frozen=True)
class LatentConfig:
    """eq:latent-opt: ``n_steps`` steps of ``optimizer`` ("sgd", the paper's, or "adam") with learning rate ``lr``."""

    lr: float = 0.01
    n_steps: int = 200
    optimizer: str = "sgd"

    def __post_init__(self):
        if self.optimizer not in OPTIMIZERS:
            raise BodySchemaInputError(f"unknown latent optimizer {self.optimizer!r}; allowed: {list(OPTIMIZERS)}")
        if isinstance(self.n_steps, bool) or not isinstance(self.n_steps, int) or self.n_steps < 0:
            raise BodySchemaInputError(f"n_steps={self.n_steps!r} must be an integer >= 0")


def reference_latent_descent(decoder, q_n: torch.Tensor, z0: torch.Tensor, penalty,
                             config: LatentConfig = LatentConfig()) -> torch.Tensor:
    """Gradient descent on z_latent (B, L) with autograd and torch.optim; returns the final z."""
    z = z0.detach().clone().requires_grad_(True)
    opt = (torch.optim.SGD if config.optimizer == "sgd" else torch.optim.Adam)([z], lr=config.lr)
    with torch.enable_grad():
        for _ in range(config.n_steps):
            opt.zero_grad(set_to_none=True)
            penalty(decoder(q_n, z)).sum().backward()
            opt.step()
    return z.detach()


def latent_descent(net, bias: torch.Tensor, z0: torch.Tensor, penalty, config: LatentConfig = LatentConfig(),
                   inference_mode: bool = True, betas=(0.9, 0.999), eps: float = 1e-8) -> torch.Tensor:
    """The fast loop: ``net`` the decoder's ``FrozenMLP`` (free columns z_latent), ``bias`` its ``first_bias(q)``
    (B, H), ``z0 (B, L)``; returns the final z. Same result as ``reference_latent_descent`` (tested)."""
    c = 1.0 if penalty.uniform_weight is None else penalty.uniform_weight  # dL/dx = c * penalty.residual
    sgd = config.optimizer == "sgd"
    with torch.inference_mode(inference_mode):
        w_z = (-config.lr * c) * net.w1_free if sgd else c * net.w1_free
        z, x_shape = z0.detach().clone(), (len(z0), net.out_b.shape[0])
        bufs, x, res = net.buffers(len(z), z), z.new_empty(x_shape), (z.new_empty(x_shape), z.new_empty(x_shape))
        if not sgd:
            m, v = torch.zeros_like(z), torch.zeros_like(z)
        for step in range(1, config.n_steps + 1):
            h, saved = net.trunk(z, bias, net.w1_free_t, bufs, net.eager)
            r = penalty.residual(torch.addmm(net.out_b, h, net.out_w_t, out=x), res)  # dL/dx_hat / c
            g1 = net.back(r, net.out_w, saved, bufs, net.eager)
            if sgd:  # z -= lr c (J^T r)
                z = torch.addmm(z, g1, w_z)
                continue
            grad = torch.mm(g1, w_z)
            m.lerp_(grad, 1.0 - betas[0])
            v.mul_(betas[1]).addcmul_(grad, grad, value=1.0 - betas[1])
            denom = (v.sqrt() / math.sqrt(1.0 - betas[1] ** step)).add_(eps)
            z.addcdiv_(m, denom, value=-config.lr / (1.0 - betas[0] ** step))
    return z.clone()
