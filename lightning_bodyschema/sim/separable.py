"""Which of a muscle's crossed joints act on its length separately: the groups whose effects add up.

A MuJoCo path's segments between bodies each depend only on the joints between those bodies, so a length is often
a sum of one function per group of joints (BIClong: the shoulder's three plus elbow_flexion and pro_sup). Two crossed
joints share a group when the length's mixed second derivative in them is more than rounding, and transitively.
``networks.per_muscle.PerMusclePath(blocks=...)`` then writes the length as one polynomial per group. Never imports
Lightning.
"""
from __future__ import annotations

import numpy as np

# [m/rad^2]: a mixed second derivative of a length at most this large is rounding. On myoArm the pairs of joints
# that do not interact measure below 1e-10 and those that do above 1e-3 (central differences of MuJoCo's Jacobian).
SEPARABLE_TOL_M = 1e-6
_SEPARABLE_STEP = 1e-5  # [rad or m] central-difference step of the moment arms


def separable_blocks(model, crossing, n_postures: int = 64, seed: int = 0) -> np.ndarray:
    """``(M, N)`` int: each muscle's crossed joints of ``model`` (a ``MusculoskeletalModel``) in groups whose effects
    on its length add up, -1 on uncrossed joints: two crossed joints share a group when the mixed second derivative
    exceeds ``SEPARABLE_TOL_M`` at the range midpoint or ``n_postures`` seeded postures (central differences of
    MuJoCo's moment arms), and transitively (``joint_groups``)."""
    crossing = np.asarray(crossing, dtype=bool)
    q = np.vstack([model.q_range.mean(axis=1), model.sample_q(np.random.default_rng(seed), n_postures)])
    mixed = np.zeros(crossing.shape + (model.n_joints,))
    for j in range(model.n_joints):  # a loop over joints: d G / d q_j, every muscle and posture at once
        step = np.zeros(model.n_joints)
        step[j] = _SEPARABLE_STEP
        slope = (model.kinematics(q + step)[1] - model.kinematics(q - step)[1]) / (2 * _SEPARABLE_STEP)
        mixed[:, :, j] = np.abs(slope).max(axis=0)
    return joint_groups(crossing, np.maximum(mixed, mixed.transpose(0, 2, 1)) > SEPARABLE_TOL_M)


def joint_groups(crossing: np.ndarray, linked: np.ndarray) -> np.ndarray:
    """``(M, N)`` int: the connected groups of each muscle's crossed joints under ``linked (M, N, N)`` bool, numbered
    0, 1, ... in joint order; -1 on uncrossed joints."""
    n = crossing.shape[1]
    label = np.where(crossing, np.arange(n), n)
    linked = linked & crossing[:, None, :] & crossing[:, :, None]
    for _ in range(n):  # the smallest joint index spreads along the links: n rounds reach every joint of a group
        label = np.minimum(label, np.where(linked, label[:, None, :], n).min(-1))
    present = np.zeros((len(label), n + 1), dtype=bool)  # which labels (a group's smallest joint) each muscle has
    present[np.nonzero(crossing)[0], label[crossing]] = True
    smaller = np.cumsum(present, 1) - present  # per label, how many of the muscle's labels are smaller: its rank
    return np.where(crossing, np.take_along_axis(smaller, label, 1), -1)
