"""The polynomial part of a per-muscle path: which product terms each muscle uses (over the joints it crosses, within
its groups of ``blocks``, up to its own total degree) and the least squares of every muscle's coefficients from one
set of normal equations. Plain numpy and PyTorch, no Lightning."""
from __future__ import annotations

import itertools

import numpy as np
import torch

from ..errors import BodySchemaInputError
from .branches import group_system, solve_systems


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
    length do not add up sharing one (``sim.separable.separable_blocks``); None: one group of every crossed
    joint. One ``BodySchemaInputError`` unless it marks exactly the crossed joints."""
    crossing = np.asarray(crossing, dtype=bool)
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
