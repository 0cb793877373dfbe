"""Fault constraints (rupture, jamming, length band, tension bounds; a weakened muscle lowers its bound) and the
adaptation loss. Never imports Lightning; torch only when the constraints are used (``evaluation/`` stays light)."""
from .faults import Faults

_TORCH_NAMES = ("AdaptWeights", "Constraint", "Jam", "LengthBand", "MaxTension", "MinTension", "Rupture",
                "adaptation_loss")
__all__ = [*_TORCH_NAMES, "Faults"]


def __getattr__(name):  # PEP 562: the torch-based constraint classes load on first use
    if name in _TORCH_NAMES:
        from . import constraints

        return getattr(constraints, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
