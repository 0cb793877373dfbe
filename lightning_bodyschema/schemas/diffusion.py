"""Diffusion (DDPM) body schema (paper section II-C): eps-prediction conditioned on q."""
from __future__ import annotations

from typing import Optional

import torch

from ..networks import EpsMLP
from ..samplers import GuidanceConfig, NoiseSchedule, guided_denoise
from .base import BodySchema


class DiffusionSchema(BodySchema):
    """DDPM over x = [l_motor, f] conditioned on q, trained with ``||eps - h_diff(x_t, t, q)||^2``.

    Args:
        n_timesteps: T (paper: 200), linear schedule rescaled so x_T is noise (see ``NoiseSchedule``).
        hidden, n_hidden: eps-MLP width/depth (paper: 2 x 91 SiLU, ~11k parameters).
        sample_seed: seed of the x_T shared by all cases, so the same q always gives the same command.
    The healthy command runs the deterministic denoising eq:diff-1/eq:diff-2 (eta = 0) from x_T.
    """

    # eq:diff-adapt settings per variant; see BodySchema.adapt and README "Design decisions"
    ADAPT = {"literal": GuidanceConfig(lr=0.01, step_scale="none"),
             "default": GuidanceConfig(lr=0.5, step_scale="abar")}

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
        """x_T for n cases: ONE seeded draw shared by every case.

        A command then depends only on its own q (and faults), never on the batch it was computed in:
        torch draws different normals for a (6, D) and a (1, D) request from the same seed.
        """
        gen = torch.Generator().manual_seed(self.hparams.sample_seed)
        x_T = torch.randn(self.x_dim, generator=gen, dtype=torch.float64)
        return x_T.to(like.device, like.dtype).expand(n, -1).clone()

    def generate(self, q_n):
        x = self.initial_noise(len(q_n), q_n)
        for t in range(self.schedule.n_timesteps - 1, -1, -1):
            eps = self.eps_model(x, t, q_n)
            x = self.schedule.ddpm_mean_step(x, eps, t)  # eq:diff-2 with eta = 0
        return x

    def adapt_normalized(self, q_n, loss_fn, variant, lr=None, step_scale=None, n_steps=None):
        """Gradient-guided denoising (eq:diff-1, eq:diff-adapt, eq:diff-2) from the same x_T as ``generate``.

        n_steps: None runs all T DDPM steps; fewer runs strided DDIM steps with the same guidance.
        """
        base = self.ADAPT[variant]
        guidance = GuidanceConfig(lr=base.lr if lr is None else lr,
                                  step_scale=base.step_scale if step_scale is None else step_scale)
        steps = None if n_steps is None else self.schedule.timesteps(n_steps).tolist()
        return guided_denoise(self.eps_model, self.schedule, q_n, self.initial_noise(len(q_n), q_n), loss_fn,
                              guidance, steps)
