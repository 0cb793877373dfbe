"""Faults of a robot (ruptured, jammed, weakened and length-banded muscles), their constraints as intervals, and the
adaptation loss built from them. Never imports Lightning; torch only for the penalty (``evaluation/`` stays light)."""
from .constraints import AdaptWeights, Constraint, Jam, LengthBand, MaxTension, MinTension, Rupture
from .faults import Faults, muscle_index

_TORCH_NAMES = ("BoxPenalty", "PenaltyBuilder")
__all__ = ["AdaptWeights", "Constraint", "Jam", "LengthBand", "MaxTension", "MinTension", "Rupture", "Faults",
           "muscle_index", *_TORCH_NAMES]


def __getattr__(name):  # PEP 562: the torch-based penalty loads on first use
    if name in _TORCH_NAMES:
        from . import penalty

        return getattr(penalty, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
