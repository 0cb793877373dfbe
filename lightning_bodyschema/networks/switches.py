"""Where a learned path switches branch: each posture's distance to the nearest learned switch, for the adapter's flag.

MuJoCo's wrapping picks a side of each wrap object and the length jumps where the side switches (myoArm: 1-20 mm).
A two-branch muscle (``networks.branches``) places its switch from samples: its length is the second polynomial
where its gate is positive. Near the gate's zero set the learned length may sit on the wrong side of the true jump
(myoArm: the zero set lies a median 8 mrad from MuJoCo's jump where one is found nearby), so a command there is not
exact: the adapter reports such postures (``near_path_switch``) instead of commanding them as if exact.

``switch_distance`` estimates each posture's distance [rad, Euclidean over the joints] to every learned switch to
first order, ``|g(q)| / |grad_q g(q)|`` (exact for a plane; near a curved zero set, where the flag matters, close),
and keeps the switches whose two branches differ there by at least ``JUMP_FLOOR_M`` (a degree-8 gate also changes
sign where both branches agree: no jump, nothing to flag). Muscles whose cells replaced their branches
(``networks.cells``) do not switch by a gate and are not counted: a trimmed cell fits the larger side of a jump
inside it and says nothing of where the smaller side begins (RESULTS.md "Hold every posture").

Plain PyTorch, no Lightning.
"""
from __future__ import annotations

import numpy as np
import torch

from .basis import product_basis

SWITCH_REACH_RAD = 0.005  # a posture this close to a learned switch is flagged [rad] (RESULTS.md "Hold every posture":
# 0.65 % of uniform myoArm postures; 10 mrad: 1.2 %)
JUMP_FLOOR_M = 1e-4  # a gate's zero counts as a switch where its branches differ by this much [m] (evaluation.
# body_errors.BAD_LENGTH_MM: a posture whose worst muscle misses by more is a bad one)


def gated_muscles(path) -> torch.Tensor:
    """The muscles of a ``PerMusclePath`` whose length a gate switches (``branched``), ``(G,)`` long."""
    if getattr(path, "branches", 1) != 2:
        return torch.zeros(0, dtype=torch.long, device=path.coef.device)
    return torch.nonzero(path.branched).flatten()


def gate_distance(path, x: torch.Tensor, half_range: torch.Tensor) -> torch.Tensor:
    """``(B, G)`` [rad]: each gated muscle's (``gated_muscles``) first-order distance from normalized postures ``x
    (B, N)`` to its gate's zero set; ``half_range (N,)``: rad per normalized unit. Only the gates' own terms are
    evaluated (a gate has at most ``branches.GATE_TERMS``)."""
    muscles = gated_muscles(path)
    if not len(muscles):
        return x.new_zeros(len(x), 0, dtype=torch.float64)
    gate = path.gate[muscles]
    cols = torch.nonzero(gate.abs().sum(0) > 0).flatten()
    exponents = path.exponents[cols]
    phi, dphi = product_basis(x.to(torch.float64), exponents, int(exponents.max()), slopes=True)
    g = phi @ gate[:, cols].T  # (B, G)
    grad = torch.einsum("bnp,gp->bgn", dphi, gate[:, cols]) / half_range.to(torch.float64)  # d g / d q [1/rad]
    return g.abs() / grad.norm(dim=2).clamp_min(1e-300)


def branch_gap(path, x: torch.Tensor) -> torch.Tensor:
    """``(B, G)``: each gated muscle's second branch minus its first at normalized postures ``x (B, N)``, in the
    path's (normalized) length units."""
    muscles = gated_muscles(path)
    diff = (path.coef_alt[muscles] - path.coef[muscles]) * path.term_mask[muscles]
    cols = torch.nonzero(diff.abs().sum(0) > 0).flatten()
    if not len(cols):
        return x.new_zeros(len(x), len(muscles), dtype=torch.float64)
    exponents = path.exponents[cols]
    return product_basis(x.to(torch.float64), exponents, int(exponents.max()))[0] @ diff[:, cols].T


def switch_distance(path, x: torch.Tensor, half_range: torch.Tensor, length_scale_m: torch.Tensor) -> tuple[
        np.ndarray, np.ndarray]:
    """Each posture's distance [rad] to the nearest learned switch of ``path`` (a ``PerMusclePath``) whose branches
    differ there by at least ``JUMP_FLOOR_M``, and its muscle, ``(B,)`` each (``inf``, -1: none), at normalized
    postures ``x (B, N)``; ``half_range (N,)``: rad per normalized unit, ``length_scale_m (M,)``: m per normalized
    length unit."""
    with torch.no_grad():
        muscles = gated_muscles(path)
        if not len(muscles):
            return np.full(len(x), np.inf), np.full(len(x), -1, dtype=np.int64)
        jump_m = branch_gap(path, x).abs() * length_scale_m.to(torch.float64)[muscles]
        distance = torch.where(jump_m >= JUMP_FLOOR_M, gate_distance(path, x, half_range), torch.inf)
        nearest, which = distance.min(1)
        muscle = torch.where(torch.isfinite(nearest), muscles[which], -1)
        return nearest.cpu().numpy(), muscle.cpu().numpy().astype(np.int64)


def switch_diagnostics(distance_rad: np.ndarray, muscle: np.ndarray) -> dict:
    """``switch_distance``'s answer as the adapter's per-row diagnostics: ``near_path_switch`` (within
    ``SWITCH_REACH_RAD``), ``path_switch_distance_rad``, ``path_switch_muscle``."""
    return {"near_path_switch": distance_rad <= SWITCH_REACH_RAD, "path_switch_distance_rad": distance_rad,
            "path_switch_muscle": muscle}
