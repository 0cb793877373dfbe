"""The torque-reach screen: postures whose torque no tension in a box can give, settled for a whole batch at once.

The torques ``-G^T f`` over a tension box form a zonotope; a torque outside it has no equilibrium, and proxsuite would
spend its whole iteration limit finding that out. numpy only; of the package it imports only ``sim.dual_newton``
(sim.equilibrium and sim.feasibility both use it).
"""
from __future__ import annotations

import itertools
import math

import numpy as np

from .dual_newton import box_least_squares

MAX_SCREEN_NORMALS = 256  # at most this many facet normals (else: the joint axes and a residual direction)


def _facet_normals(G) -> np.ndarray | None:
    """(B, K, N) unit normals of the facets of the torque zonotope {-G^T f : f in a box} (K = C(M, N-1)
    subsets of N-1 muscle torque vectors, each normal orthogonal to them), or None when K is too large."""
    batch, n_muscles, n_joints = G.shape
    if math.comb(n_muscles, n_joints - 1) > MAX_SCREEN_NORMALS:  # count first: C(31, 14) subsets fill no memory
        return None
    subsets = list(itertools.combinations(range(n_muscles), n_joints - 1))
    if n_joints == 1:
        return np.ones((batch, 1, 1))
    spans = G[:, np.asarray(subsets), :]  # (B, K, N-1, N)
    return np.linalg.svd(spans)[2][..., -1, :]  # the right singular vector of the zero singular value


def _residual_direction(G, tau_bias, lo, hi, reg: float = 1e-6) -> np.ndarray:
    """(B, N) unit vectors along ``tau_bias + G^T f`` for the box least-squares tensions f
    (``sim.dual_newton.box_least_squares``, ``reg`` on ``||f - f_mid||``): where tau_bias lies outside the torque
    zonotope this is close to the normal of the hyperplane that separates them (any direction is a valid test; this
    one is a sharp one)."""
    f, _ = box_least_squares(G, tau_bias, 0.5 * (lo + hi), lo, hi, reg)
    gap = tau_bias + np.einsum("bmn,bm->bn", G, f)
    return gap / np.maximum(np.linalg.norm(gap, axis=1, keepdims=True), 1e-300)


def outside_torque_reach(G, tau_bias, lo, hi, tol_nm: float) -> np.ndarray:
    """(B,) True where no tension f in [lo, hi] (B, M) can give -G^T f = tau_bias to ``tol_nm`` on every joint.

    Why: the QP solver spends many iterations on an infeasible case before giving up; this batched test settles
    most of them at once. The torques -G^T f over the box form a zonotope; tau_bias is outside it iff some
    facet normal w has w . tau_bias > max_f w . (-G^T f) = sum_m max(lo_m c_m, hi_m c_m), c = -G w. Every
    such inequality is valid for any w, so a True is always right (no feasible case is ever dropped); with
    all facet normals the test is exact up to the tolerance, and cases it cannot settle go to the QP. A body with
    too many facets (C(M, N-1) > MAX_SCREEN_NORMALS) is tested along the joint axes and ``_residual_direction``.
    """
    normals = _facet_normals(G)
    if normals is None:  # too many facets: the joint axes and the direction a projected-gradient fit leaves open
        normals = np.concatenate([_residual_direction(G, tau_bias, lo, hi)[:, None, :],
                                  np.broadcast_to(np.eye(G.shape[2]), (len(G),) + (G.shape[2],) * 2)], axis=1)
    normals = np.concatenate([normals, -normals], axis=1)  # both orientations of every direction
    reach = np.einsum("bmn,bkn->bkm", -G, normals)  # c_m per direction
    support = np.maximum(lo[:, None, :] * reach, hi[:, None, :] * reach).sum(-1)
    gap = np.einsum("bn,bkn->bk", tau_bias, normals) - support
    # a gap d forces |w . residual| >= d, so some joint's residual >= d / sqrt(N): the QP's own tolerance
    return np.any(gap > np.sqrt(G.shape[2]) * tol_nm, axis=1)
