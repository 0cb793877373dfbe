"""Body schemas: one ``BodySchema`` interface, AE / VAE / diffusion / structured implementations."""
from .autoencoder import AutoEncoderSchema, VAESchema
from ..adaptation import AdaptationResult
from .base import BodySchema
from .diffusion import DiffusionSchema
from .loading import load_datamodule, load_schema
from .structured import StructuredSchema

__all__ = ["BodySchema", "AdaptationResult", "AutoEncoderSchema", "VAESchema", "DiffusionSchema", "StructuredSchema", "load_schema", "load_datamodule"]
