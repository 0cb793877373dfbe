"""Noise schedule and update rules (denoising, guidance, latent optimization). Imports no model, no Lightning."""
from .guided import GuidanceConfig, LatentConfig, guided_denoise, optimize_latent
from .schedule import NoiseSchedule

__all__ = ["NoiseSchedule", "GuidanceConfig", "LatentConfig", "guided_denoise", "optimize_latent"]
