"""The polynomial part of a per-muscle path: each muscle's degree under a term budget (the gates' too), the product
terms it uses (over the joints it crosses, within its groups of ``blocks``, up to its degree) and the least squares of
every muscle's coefficients from one set of normal equations. Plain numpy and PyTorch, no Lightning."""
from __future__ import annotations

import itertools
import math
from typing import Optional

import numpy as np
import torch

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


def term_exponents(blocks: np.ndarray, degrees: np.ndarray) -> np.ndarray:
    """``(P, N)`` exponents of every product term some muscle uses (nonzero exponents only on the joints it
    crosses, all within one of its groups of ``blocks``: ``check_blocks``'s, total degree at most its own), ordered
    by total degree then lexicographically, the constant first."""
    terms = set()
    for pattern, degree in {(tuple(b), int(d)) for b, d in zip(blocks.tolist(), degrees)}:  # per pattern, once
        for group in sorted(set(pattern) - {-1}):
            joints = [j for j, b in enumerate(pattern) if b == group]
            for e in itertools.product(range(degree + 1), repeat=len(joints)):
                if sum(e) <= degree:
                    terms.add(tuple(dict(zip(joints, e)).get(j, 0) for j in range(len(pattern))))
    return np.array(sorted(terms, key=lambda e: (sum(e), e)), dtype=np.int64).reshape(-1, blocks.shape[1])


def term_mask(blocks: np.ndarray, exponents: np.ndarray, degrees: np.ndarray) -> np.ndarray:
    """``(M, P)`` bool: the terms of ``exponents`` each muscle uses (as ``term_exponents``)."""
    blocks = blocks.astype(np.int16)
    support = exponents > 0
    lowest = np.where(support[None], blocks[:, None, :], np.iinfo(np.int16).max).min(-1)  # (M, P)
    highest = np.where(support[None], blocks[:, None, :], -1).max(-1)
    inside = ((lowest == highest) & (lowest >= 0)) | ~support.any(1)[None, :]
    return inside & (exponents.sum(1)[None, :] <= degrees[:, None])


def check_blocks(crossing: np.ndarray, blocks) -> np.ndarray:
    """``blocks (M, N)`` int: a group id per crossed joint (-1 on the others), the joints whose effects on a muscle's
    length do not add up sharing one (``sim.separable.separable_blocks``); None: one group of every crossed joint
    (``crossing``: ``check_crossing``'s). One ``BodySchemaInputError`` unless it marks exactly the crossed joints."""
    if blocks is None:
        return np.where(crossing, 0, -1)
    values = np.asarray(blocks)
    if values.shape != crossing.shape or values.dtype.kind not in "iu" or not np.array_equal(values >= 0, crossing) \
            or (values < -1).any():
        raise BodySchemaInputError(f"path blocks {blocks!r} must be {crossing.shape[0]} rows of {crossing.shape[1]} "
                                   f"integers: a group id >= 0 on each joint the muscle crosses, -1 on the others")
    return values.astype(np.int64)


def check_crossing(crossing) -> np.ndarray:
    """``crossing (M, N)`` as a bool array; one ``BodySchemaInputError`` if a muscle crosses no joint."""
    crossing = np.asarray(crossing, dtype=bool)
    if crossing.ndim != 2 or not crossing.any(1).all():
        raise BodySchemaInputError(f"crossing must be (muscles, joints) with every muscle crossing a joint; got "
                                   f"shape {crossing.shape}")
    return crossing


def check_degrees(degrees, n_muscles: int, least: int = 1, name: str = "degrees") -> np.ndarray:
    """``degrees`` (array-like or a tensor) as an ``(M,)`` int64 array; one ``BodySchemaInputError`` naming ``name``
    unless M integers >= ``least``."""
    values = np.asarray(degrees.cpu() if torch.is_tensor(degrees) else degrees)
    if values.shape != (n_muscles,) or values.dtype.kind not in "iu" or (values < least).any():
        raise BodySchemaInputError(f"{name}={degrees!r} must be {n_muscles} integers >= {least}, one per muscle"
                                   + (" (0: no cells)" if name == "cell_degrees" else ""))
    return values.astype(np.int64)


def solve_systems(system, b, valid, ridge, scale=None):
    """Each muscle's ridge-regularized normal equations ``(M, K, K) x = (M, K)``, padded terms (``~valid``) 0; the
    ridge is ``ridge`` times ``scale (M, 1)`` (default: the mean of the system's diagonal)."""
    if scale is None:
        scale = system.diagonal(dim1=1, dim2=2).mean(1, keepdim=True).clamp_min(1e-300)
    system = system + torch.diag_embed(torch.where(valid, ridge * scale, torch.ones_like(scale)))
    return torch.linalg.solve(system, (b * valid).unsqueeze(-1)).squeeze(-1) * valid


def group_system(gram, rhs, muscles, terms, valid):
    """The normal equations of ``muscles`` over their own ``terms (G, K)`` (indices into every term's ``gram (P, P)``
    and ``rhs (P, M)``): ``(G, K, K)`` and ``(G, K)``, padded entries (``~valid (G, K)``) 0."""
    system, b = gram[terms[:, :, None], terms[:, None, :]], rhs.T[muscles].gather(1, terms)
    return system * (valid[:, :, None] & valid[:, None, :]), b * valid


def solve_normal_equations(mask: torch.Tensor, gram: torch.Tensor, rhs: torch.Tensor, ridge: float):
    """Every muscle's coefficients ``(M, P)`` on its terms ``mask (M, P)`` (exactly zero elsewhere) from every term's
    normal equations, and ``order (M, P)``: each muscle's terms first. A loop over groups of muscles with the same
    number of terms; the maths in a group is batched."""
    order = torch.argsort((~mask).to(torch.int8), dim=1, stable=True)
    counts, coef = mask.sum(1), torch.zeros(mask.shape, dtype=torch.float64, device=mask.device)
    for k in torch.unique(counts).tolist():
        muscles = torch.nonzero(counts == k).flatten()
        terms = order[muscles, :k]
        every = torch.ones_like(terms, dtype=torch.bool)  # no padding: each muscle of the group has k terms
        solution = solve_systems(*group_system(gram, rhs, muscles, terms, every), every, ridge)
        coef[muscles] = coef[muscles].scatter(1, terms, solution)
    return coef * mask, order
