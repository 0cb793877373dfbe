"""Per-muscle polynomial degrees under a term budget (shared by the path polynomials and their gates)."""
from __future__ import annotations

import math
from typing import Optional

import numpy as np

from ..errors import BodySchemaInputError


def block_sizes(blocks: np.ndarray) -> list[tuple[int, ...]]:
    """Each muscle's groups of joints whose effects on its length add up: the number of joints in each group, from
    ``blocks (M, N)`` (a group id per crossed joint, -1 on the others)."""
    return [tuple(int((row == b).sum()) for b in np.unique(row[row >= 0])) for row in np.asarray(blocks)]


def term_count(sizes, d: int) -> int:
    """Terms of total degree ``<= d`` of a sum of one polynomial per group of ``sizes`` joints (one shared constant):
    ``1 + sum_g (C(n_g + d, n_g) - 1)``; one group of ``n`` joints: ``C(n + d, n)``."""
    return 1 + sum(math.comb(int(n) + int(d), int(n)) - 1 for n in sizes)


def muscle_degrees(crossing: np.ndarray, degree: int, max_terms: int, budget: Optional[int] = None,
                   eligible: Optional[np.ndarray] = None, blocks: Optional[np.ndarray] = None) -> np.ndarray:
    """``(M,)`` each muscle's total degree: the largest ``d <= degree`` (at least 1) whose polynomial over the joints
    it crosses (with ``blocks``, one per group) has at most ``max_terms`` terms (``term_count``); then, with a
    ``budget`` of terms over all muscles (at least what that uses), one degree at a time to the muscle of lowest
    degree (ties: the fewest new terms, then the first), up to ``degree``, while the budget holds; ``eligible (M,)``
    bool: only these rise (None: every muscle)."""
    n = [(int(k),) for k in np.asarray(crossing).sum(1)] if blocks is None else block_sizes(blocks)
    degrees = np.array([max([1] + [d for d in range(1, degree + 1) if term_count(k, d) <= max_terms]) for k in n])
    if budget is None:
        return degrees
    total = sum(term_count(k, d) for k, d in zip(n, degrees))
    if isinstance(budget, bool) or not isinstance(budget, int) or budget < total:
        raise BodySchemaInputError(f"term budget {budget!r} must be an integer >= {total} (the terms the per-muscle "
                                   f"limit of {max_terms} already gives)")
    can_rise = np.ones(len(n), dtype=bool) if eligible is None else np.asarray(eligible, dtype=bool)
    while (can_rise & (degrees < degree)).any():
        costs = [(d, term_count(k, d + 1) - term_count(k, d), i) for i, (k, d) in enumerate(zip(n, degrees))
                 if d < degree and can_rise[i]]
        _, cost, i = min(costs)
        if total + cost > budget:
            break
        degrees[i] += 1
        total += cost
    return degrees
