"""Plain PyTorch networks for the body schemas (no Lightning)."""
from .mlp import MLP, AEEncoder, Decoder, EpsMLP, VAEEncoder, build_autoencoder, count_parameters

__all__ = ["MLP", "AEEncoder", "VAEEncoder", "Decoder", "EpsMLP", "build_autoencoder", "count_parameters"]
