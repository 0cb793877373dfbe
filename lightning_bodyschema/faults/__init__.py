"""Fault constraints (rupture, jamming, tension bounds) and the adaptation loss. Never imports Lightning."""
from .constraints import (AdaptWeights, Constraint, Jam, MaxTension, MinTension, Rupture, adaptation_loss)
from .faults import Faults

__all__ = ["AdaptWeights", "Constraint", "Jam", "MaxTension", "MinTension", "Rupture", "adaptation_loss", "Faults"]
