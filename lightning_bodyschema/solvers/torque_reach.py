"""The torque-reach screen: torques that no tension in a box can give, settled for a whole batch at once.

The torques ``-G^T f`` over a tension box form a zonotope; a torque outside it has no equilibrium, and an iterative
QP solver would spend its whole iteration limit finding that out. torch only (any device).
"""
from __future__ import annotations

import itertools
import math

import torch

from .least_squares import box_least_squares
from .problem import separation_gap_nm

MAX_SCREEN_NORMALS = 256  # at most this many facet normals (else: the joint axes and a residual direction)


def screen_is_exact(n_muscles: int, n_joints: int) -> bool:
    """True where the screen enumerates every facet normal of the torque zonotope of ``n_muscles`` muscles over
    ``n_joints`` joints (C(M, N-1) <= ``MAX_SCREEN_NORMALS``): then a torque it does not put out of reach is reached
    (to its tolerance)."""
    return math.comb(n_muscles, n_joints - 1) <= MAX_SCREEN_NORMALS


def _facet_normals(G: torch.Tensor) -> torch.Tensor | None:
    """(B, K, N) unit normals of the facets of the torque zonotope {-G^T f : f in a box} (K = C(M, N-1)
    subsets of N-1 muscle torque vectors, each normal orthogonal to them), or None when K is too large."""
    batch, n_muscles, n_joints = G.shape
    if not screen_is_exact(n_muscles, n_joints):  # count first: C(31, 14) subsets fill no memory
        return None
    if n_joints == 1:
        return torch.ones((batch, 1, 1), dtype=G.dtype, device=G.device)
    if n_joints == 2:  # a planar arm: each muscle's torque vector turned by 90 degrees (what the SVD gives, up to sign)
        turned = torch.stack([-G[..., 1], G[..., 0]], dim=-1)
        return turned / torch.linalg.vector_norm(turned, dim=-1, keepdim=True).clamp_min(1e-300)
    subsets = torch.tensor(list(itertools.combinations(range(n_muscles), n_joints - 1)), device=G.device)
    spans = G[:, subsets, :]  # (B, K, N-1, N)
    return torch.linalg.svd(spans)[2][..., -1, :]  # the right singular vector of the zero singular value


def screen_normals(G: torch.Tensor) -> torch.Tensor:
    """(B, K, N) the screen's own test directions: every facet normal of the torque zonotope where there are at most
    ``MAX_SCREEN_NORMALS`` of them, else the joint axes."""
    normals = _facet_normals(G)
    return torch.eye(G.shape[2], dtype=G.dtype, device=G.device).expand(G.shape[0], -1, -1) if normals is None \
        else normals


def residual_direction(G, tau, f_n) -> torch.Tensor:
    """(B, N) unit vectors along ``tau + G^T f``: for the box least-squares tensions f of a torque outside the
    zonotope, close to the normal of the hyperplane that separates them (any direction is a valid test; this one
    is a sharp one)."""
    gap = tau + (G.transpose(1, 2) @ f_n.unsqueeze(-1)).squeeze(-1)
    return gap / torch.clamp(torch.linalg.vector_norm(gap, dim=1, keepdim=True), min=1e-300)


def outside_torque_reach(G, tau, lo, hi, tol_nm: float, direction: torch.Tensor | None = None) -> torch.Tensor:
    """(B,) True where no tension f in [lo, hi] (B, M) can give -G^T f = tau to ``tol_nm`` on every joint.

    The torques -G^T f over the box form a zonotope; tau is outside it iff some facet normal u has
    u . tau > max_f u . (-G^T f) = sum_m max(lo_m c_m, hi_m c_m), c = -G u. Every such inequality is valid for any
    u, so a True is always right (no feasible case is ever dropped); with all facet normals the test is exact up to
    the tolerance. A body with too many facets (C(M, N-1) > MAX_SCREEN_NORMALS) is tested along the joint axes and
    ``direction`` (B, N) (default: ``residual_direction`` of the box least squares about the box's middle);
    ``direction`` is added to the facet normals when given.
    """
    if direction is None and not screen_is_exact(*G.shape[1:]):
        direction = residual_direction(G, tau, box_least_squares(G, tau, 0.5 * (lo + hi), lo, hi).f)
    extra = [] if direction is None else [direction.unsqueeze(1)]
    normals = torch.cat(extra + [screen_normals(G)], dim=1)
    normals = torch.cat([normals, -normals], dim=1)  # both orientations of every direction
    gap = separation_gap_nm(G, tau, lo, hi, normals)
    # a gap d forces |u . residual| >= d, so some joint's residual >= d / sqrt(N): the QP's own tolerance
    return (gap > math.sqrt(G.shape[2]) * tol_nm).any(1)
