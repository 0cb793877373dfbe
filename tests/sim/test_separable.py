"""``sim.separable.separable_blocks``: the groups of a muscle's joints whose effects on its length add up,
checked on MuJoCo's own lengths (a mixed second difference that vanishes across groups and not within one)."""
from __future__ import annotations

import numpy as np
import pytest

from lightning_bodyschema.sim import MusculoskeletalModel
from lightning_bodyschema.sim.separable import separable_blocks


def _mixed_difference(model, q, i, j, step=0.3):
    """``l(q + a + b) - l(q + a) - l(q + b) + l(q)`` per muscle ``(B, M)`` with steps a, b on joints i, j: zero for
    every posture exactly when the length is a function of joint i plus a function of joint j (locally)."""
    a, b = np.zeros(q.shape[1]), np.zeros(q.shape[1])
    a[i], b[j] = step, step
    length = lambda p: model.kinematics(p)[0]  # noqa: E731
    return length(q + a + b) - length(q + a) - length(q + b) + length(q)


def test_the_paper_arms_biarticular_muscles_add_a_shoulder_part_and_an_elbow_part():
    model = MusculoskeletalModel("paper_arm")
    blocks = separable_blocks(model, model.crossing())
    assert blocks.tolist() == [[0, -1], [0, -1], [-1, 0], [-1, 0], [0, 1], [0, 1]]
    q = model.sample_q(np.random.default_rng(0), 50) * 0.8  # room for the steps inside the ranges
    assert np.abs(_mixed_difference(model, q, 0, 1)[:, 4:]).max() < 1e-12


def test_myoarm_splits_biclong_and_keeps_the_shoulders_joints_together():
    pytest.importorskip("myo_sim")
    import yaml

    locks = yaml.safe_load(open("configs/myoarm.yaml"))["data"]["locked_joints"]
    model = MusculoskeletalModel("myo:myoarm", locked_joints=locks)
    blocks = dict(zip(model.muscle_names, separable_blocks(model, model.crossing()).tolist()))
    assert blocks["BIClong_tendon"] == [0, 0, 0, 1, 1, -1, -1] and blocks["DELT1_tendon"] == [0, 0, 0, -1, -1, -1, -1]
    q = model.sample_q(np.random.default_rng(1), 50)
    q = np.clip(q, model.q_range[:, 0] + 0.1, model.q_range[:, 1] - 0.4)
    biclong, delt1 = model.muscle_names.index("BIClong_tendon"), model.muscle_names.index("DELT1_tendon")
    assert np.abs(_mixed_difference(model, q, 1, 3, 0.2)[:, biclong]).max() < 1e-12  # shoulder_elv x elbow
    assert np.abs(_mixed_difference(model, q, 0, 1, 0.2)[:, delt1]).max() > 1e-5  # elv_angle x shoulder_elv
