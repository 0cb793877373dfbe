"""Fault constraints (rupture, jamming, length band, tension bounds; a weakened muscle lowers its bound) and the
adaptation loss. Never imports Lightning."""
from .constraints import (AdaptWeights, Constraint, Jam, LengthBand, MaxTension, MinTension, Rupture,
                          adaptation_loss)
from .faults import Faults

__all__ = ["AdaptWeights", "Constraint", "Jam", "LengthBand", "MaxTension", "MinTension", "Rupture", "adaptation_loss",
           "Faults"]
