"""Noise schedule and update rules (guided denoising, latent descent). Imports no model, no loss, no Lightning."""
from .guided import DenoisePlan, GuidanceConfig, PlanStep, denoise, plan_denoising, reference_loop
from .latent import LatentConfig, latent_descent, reference_latent_descent
from .schedule import PREDICTIONS, NoiseSchedule, OutputAffine

__all__ = ["NoiseSchedule", "OutputAffine", "PREDICTIONS", "GuidanceConfig", "DenoisePlan", "PlanStep",
           "plan_denoising", "denoise", "reference_loop", "LatentConfig", "latent_descent", "reference_latent_descent"]
