"""Body schemas: one ``BodySchema`` interface, AE / VAE / diffusion implementations."""
from .autoencoder import AutoEncoderSchema, VAESchema
from ..adaptation import AdaptationResult
from .base import BodySchema
from .diffusion import DiffusionSchema
from .loading import load_datamodule, load_schema

__all__ = ["BodySchema", "AdaptationResult", "AutoEncoderSchema", "VAESchema", "DiffusionSchema", "load_schema", "load_datamodule"]
