"""Diffusion (DDPM) body schema (paper section II-C): eps-prediction conditioned on q."""
from __future__ import annotations

from typing import Optional

import torch

from ..networks import EpsMLP
from ..samplers import NoiseSchedule
from .base import BodySchema


class DiffusionSchema(BodySchema):
    """DDPM over x = [l_motor, f] conditioned on q, trained with ``||eps - h_diff(x_t, t, q)||^2``.

    Args:
        n_timesteps: T (paper: 200), linear schedule rescaled so x_T is noise (see ``NoiseSchedule``).
        hidden, n_hidden: eps-MLP width/depth (paper: 2 x 91 SiLU, ~11k parameters).
        sample_seed: seed of x_T in ``generate``, so the same q always gives the same command.
    The healthy command runs the deterministic denoising eq:diff-1/eq:diff-2 (eta = 0) from x_T.
    """

    def __init__(self, n_timesteps: int = 200, hidden: int = 91, n_hidden: int = 2, sample_seed: int = 0,
                 robot: Optional[dict] = None, lr: float = 1e-3, lr_final: Optional[float] = 1e-5,
                 batch_size: int = 64):
        super().__init__(robot=robot, lr=lr, lr_final=lr_final, batch_size=batch_size)
        self.save_hyperparameters()
        self.eps_model = EpsMLP(self.x_dim, self.n_joints, hidden=hidden, n_hidden=n_hidden, n_timesteps=n_timesteps)
        self.schedule = NoiseSchedule(n_timesteps)

    def training_loss(self, q_n, x_n):
        t = torch.randint(0, self.schedule.n_timesteps, (len(x_n),), device=x_n.device)
        eps = torch.randn_like(x_n)
        x_t = self.schedule.add_noise(x_n, eps, t)
        loss = (eps - self.eps_model(x_t, t, q_n)).pow(2).mean()
        return loss, {}

    def initial_noise(self, n: int, like: torch.Tensor) -> torch.Tensor:
        """x_T for n cases, from ``sample_seed``: same inputs, same command."""
        gen = torch.Generator().manual_seed(self.hparams.sample_seed)
        return torch.randn(n, self.x_dim, generator=gen, dtype=like.dtype).to(like.device)

    def generate(self, q_n):
        x = self.initial_noise(len(q_n), q_n)
        for t in range(self.schedule.n_timesteps - 1, -1, -1):
            eps = self.eps_model(x, t, q_n)
            x = self.schedule.ddpm_mean_step(x, eps, t)  # eq:diff-2 with eta = 0
        return x
