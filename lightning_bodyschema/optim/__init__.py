from .lean_adam import LeanFusedAdam

__all__ = ["LeanFusedAdam"]
