"""Box QPs on muscle tensions, one problem type and one solution type for every caller (torch, any device).

``newton``: the batched dual semismooth Newton (exportable with a fixed iteration count). No Lightning, no schemas.
"""
from .newton import NEWTON_MAX_ITER, NEWTON_TOL_NM, NewtonResult, dual_newton

__all__ = ["NEWTON_MAX_ITER", "NEWTON_TOL_NM", "NewtonResult", "dual_newton"]
