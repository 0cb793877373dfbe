"""Per-muscle polynomial degrees under a term budget (shared by the path polynomials and their gates)."""
from __future__ import annotations

import math

import numpy as np


def muscle_degrees(crossing: np.ndarray, degree: int, max_terms: int) -> np.ndarray:
    """``(M,)`` each muscle's total degree: the largest ``d <= degree`` whose polynomial over the ``n`` joints the
    muscle crosses has at most ``max_terms`` terms (``C(n + d, n)``), at least 1."""
    n = crossing.sum(1)
    return np.array([max([1] + [d for d in range(1, degree + 1) if math.comb(k + d, k) <= max_terms]) for k in n])
