"""Noise schedules and update rules for the diffusion body schema (no model, no Lightning)."""
from .schedule import NoiseSchedule

__all__ = ["NoiseSchedule"]
