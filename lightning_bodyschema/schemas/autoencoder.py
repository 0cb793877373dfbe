"""AE and VAE body schemas (paper section II-B): x = [l_motor, f] -> (z_q, z_latent) -> x_hat."""
from __future__ import annotations

from typing import Optional

import torch

from ..networks import build_autoencoder
from ..samplers import LatentConfig, latent_descent, reference_latent_descent
from ..contract import ADAPTS_NORMALIZED, EPOCH_HOOK, REFRESHES_DERIVED_STATE
from ..training.fit_loop import fit_ends_with_this_epoch
from .base import BodySchema


class AutoEncoderSchema(BodySchema):
    """Autoencoder body schema. Loss ``||x - x_hat||^2 + C_q ||q - z_q||^2`` (sums over dims, batch mean).

    Args:
        latent_dim: total latent size = dim z_q (joint count) + dim z_latent (paper: 3, 10, 30).
        c_q: weight of the joint-angle term C_q^train (paper: 2.0).
        hidden: hidden units per layer (paper: 64, Tanh).
        The healthy command decodes (q, z_ref) where z_ref is the mean z_latent of the train split.
    """

    capabilities = frozenset({ADAPTS_NORMALIZED, EPOCH_HOOK, REFRESHES_DERIVED_STATE})
    variational = False
    # eq:latent-opt settings per variant; see BodySchema.adapt and README "Design decisions"
    ADAPT = {"literal": LatentConfig(lr=0.01, n_steps=200, optimizer="sgd"),
             "default": LatentConfig(lr=0.05, n_steps=200, optimizer="sgd")}

    def __init__(self, latent_dim: int = 10, c_q: float = 2.0, hidden: int = 64, robot: Optional[dict] = None,
                 lr: float = 1e-3, lr_final: Optional[float] = 1e-5, batch_size: int = 64):
        super().__init__(robot=robot, lr=lr, lr_final=lr_final, batch_size=batch_size)
        self.save_hyperparameters()
        self.encoder, self.decoder = build_autoencoder(self.x_dim, self.n_joints, latent_dim,
                                                       variational=self.variational, hidden=hidden)
        self.z_latent_dim = latent_dim - self.n_joints
        self.register_buffer("z_latent_ref", torch.zeros(self.z_latent_dim))

    def _encode(self, x_n):
        z_q, z_latent = self.encoder(x_n)
        return z_q, z_latent, {}

    def training_loss(self, q_n, x_n):
        z_q, z_latent, extra = self._encode(x_n)
        recon = (x_n - self.decoder(z_q, z_latent)).pow(2).sum(-1).mean()
        joint = (q_n - z_q).pow(2).sum(-1).mean()
        loss = recon + self.hparams.c_q * joint + sum(extra.values())
        return loss, {"recon": recon.detach(), "joint": joint.detach(), **{k: v.detach() for k, v in extra.items()}}

    def on_epoch_trained(self, q_n, x_n):
        if self.current_epoch % 10 == 0 or fit_ends_with_this_epoch(self.trainer):  # cheap, and exact at the end of training
            self.refresh_from_train_split(q_n, x_n)

    @torch.no_grad()
    def refresh_from_train_split(self, q_n, x_n):
        """z_ref: before every validation and checkpoint of a fit too (BodySchema.refresh_from_train_split)."""
        self.z_latent_ref.copy_(self.latent_reference(x_n))

    def latent_reference(self, x_n):
        """Mean z_latent of the train split: where latent adaptation starts."""
        return self.encoder(x_n)[1].mean(0)

    def generate(self, q_n):
        return self.decoder(q_n, self.z_latent_ref.expand(len(q_n), -1))

    def adapt_normalized(self, q_n, penalty, variant, lr=None, n_steps=None, optimizer=None, fast=True,
                         inference_mode=True):
        """Latent-space optimization (eq:ae-vae, eq:latent-opt) from z_ref, q fixed to q_ref.

        fast: descent through the decoder's frozen snapshot (hand-written backward, analytic loss gradient; default)
        or the autograd reference (``fast=False``); same commands (tested). inference_mode: run the fast loop under
        ``torch.inference_mode`` (False: for benchmarks of that choice).
        """
        base = self.ADAPT[variant]
        config = LatentConfig(lr=base.lr if lr is None else lr, n_steps=base.n_steps if n_steps is None else n_steps,
                              optimizer=base.optimizer if optimizer is None else optimizer)
        z0 = self.z_latent_ref.expand(len(q_n), -1)
        frozen = self.inference_cache.get(("frozen_decoder",), self.decoder.frozen) if fast else None
        if frozen is None:
            z = reference_latent_descent(self.decoder, q_n, z0, penalty, config)
        else:
            z = latent_descent(frozen, frozen.first_bias(q_n.detach()), z0, penalty, config, inference_mode)
        return self.decoder(q_n, z)


class VAESchema(AutoEncoderSchema):
    """Variational autoencoder body schema: adds ``KL(N(mu, sigma^2) || N(0, I))``; z_ref is the prior mean 0."""

    variational = True

    def _encode(self, x_n):
        z_q, mu, logvar = self.encoder(x_n)
        z_latent = mu + torch.randn_like(mu) * (0.5 * logvar).exp() if self.training else mu
        kl = 0.5 * (mu.pow(2) + logvar.exp() - 1.0 - logvar).sum(-1).mean()
        return z_q, z_latent, {"kl": kl}

    def latent_reference(self, x_n):
        return torch.zeros(self.z_latent_dim, device=x_n.device, dtype=x_n.dtype)
