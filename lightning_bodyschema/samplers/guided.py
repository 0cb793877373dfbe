"""Gradient-guided denoising (paper section III-C) and latent-space optimization (section III-B).

Update rules only: the networks, the loss and the schedule come in as arguments; no Lightning.
Everything is batched over cases: one tensor op per step for all cases, each case its own loss.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Optional, Sequence

import torch

from ..errors import BodySchemaInputError

LossFn = Callable[[torch.Tensor], torch.Tensor]  # normalized x0 (B, D) -> loss per case (B,)


@dataclass(frozen=True)
class GuidanceConfig:
    """How eq:diff-adapt scales its step.

    lr: C_lr^adapt. step_scale: the factor s_t multiplying the step at noise level t:
      ``"none"``   s_t = 1           the paper as printed (diverges early in SI units, DESIGN §5);
      ``"sqrt_abar"`` s_t = sqrt(abar_t)  damps the noisy steps by the x0_hat sensitivity (DESIGN §5's fix);
      ``"abar"``   s_t = abar_t      x0_hat moves by -lr * grad_{x0} L at every t, whatever the noise level
                                     (d x0_hat / d x_t ~ 1/sqrt(abar_t) cancels: a Newton-like step in x0).
    """

    lr: float = 0.01
    step_scale: str = "none"


def _step_scale(schedule, t: int, mode: str) -> float:
    if mode == "none":
        return 1.0
    if mode == "abar":
        return float(schedule.alpha_bars[t])
    if mode == "sqrt_abar":
        return float(schedule.sqrt_alpha_bars[t])
    raise BodySchemaInputError(f"unknown step_scale {mode!r}; allowed: 'none', 'sqrt_abar', 'abar'")


def guided_denoise(eps_model, schedule, q_n: torch.Tensor, x_T: torch.Tensor, loss_fn: Optional[LossFn],
                   guidance: GuidanceConfig = GuidanceConfig(), timesteps: Optional[Sequence[int]] = None):
    """Deterministic denoising from x_T, guided by ``loss_fn`` on the predicted x0 at every step.

    ``timesteps``: descending steps; None runs all T DDPM mean steps (eq:diff-2), a strided list runs
    DDIM steps (eta = 0) between them. ``loss_fn=None`` gives the unguided sample.
    Returns x0 (B, D) (rows may be non-finite if guidance diverged: the caller checks).
    """
    steps = list(range(schedule.n_timesteps - 1, -1, -1)) if timesteps is None else [int(t) for t in timesteps]
    strided = timesteps is not None and len(steps) < schedule.n_timesteps
    x = x_T
    for i, t in enumerate(steps):
        if loss_fn is None:
            with torch.no_grad():
                eps = eps_model(x, t, q_n)
        else:
            x, eps = _guide(eps_model, schedule, q_n, x, t, loss_fn, guidance)
        with torch.no_grad():
            t_prev = steps[i + 1] if i + 1 < len(steps) else -1
            # 3. eq:diff-2 (eta = 0) with the eps computed before guidance, or its strided DDIM form
            x = schedule.ddim_step(x, eps, t, t_prev) if strided else schedule.ddpm_mean_step(x, eps, t)
    return x


def _guide(eps_model, schedule, q_n, x_t, t, loss_fn, guidance):
    """One guidance step at t: returns the guided x_t and the eps predicted before it."""
    x_t = x_t.detach().requires_grad_(True)
    with torch.enable_grad():
        eps = eps_model(x_t, t, q_n)
        # 1. eq:diff-1: x0_hat = (x_t - sqrt(1 - abar_t) eps) / sqrt(abar_t)
        x0_hat = schedule.predict_x0(x_t, eps, t)
        # 2. eq:diff-adapt: x_t <- x_t - C_lr s_t grad_{x_t} L(x0_hat)   (cases are independent: sum)
        grad, = torch.autograd.grad(loss_fn(x0_hat).sum(), x_t)
    scale = guidance.lr * _step_scale(schedule, t, guidance.step_scale)
    return (x_t - scale * grad).detach(), eps.detach()


@dataclass(frozen=True)
class LatentConfig:
    """eq:latent-opt: ``z <- z - lr grad_z L(dec(q, z))`` for ``n_steps`` (``optimizer="adam"`` optional)."""

    lr: float = 0.01
    n_steps: int = 200
    optimizer: str = "sgd"


def optimize_latent(decoder, q_n: torch.Tensor, z0: torch.Tensor, loss_fn: LossFn,
                    config: LatentConfig = LatentConfig()) -> torch.Tensor:
    """Gradient descent on z_latent (B, L), q fixed to q_ref; returns the final z."""
    z = z0.detach().clone().requires_grad_(True)
    if config.optimizer not in ("sgd", "adam"):
        raise BodySchemaInputError(f"unknown latent optimizer {config.optimizer!r}; allowed: 'sgd', 'adam'")
    opt = (torch.optim.SGD if config.optimizer == "sgd" else torch.optim.Adam)([z], lr=config.lr)
    with torch.enable_grad():
        for _ in range(config.n_steps):
            opt.zero_grad(set_to_none=True)
            loss_fn(decoder(q_n, z)).sum().backward()
            opt.step()
    return z.detach()
