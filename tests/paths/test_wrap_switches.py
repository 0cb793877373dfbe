"""Every jump of MuJoCo's muscle lengths is at a sign change of one of that muscle's wrap margins
(``GeometricPath.margins`` at the MJCF's numbers): seeded straight lines through the joint box of myoArm and myoLegs,
1e-4 of the line per step, MuJoCo's own ``kinematics`` lengths. The converse (margin sign changes where nothing jumps:
the flag firing for nothing) is counted, not asserted."""
import numpy as np
import pytest
import torch

from lightning_bodyschema.apps.common import robot_from_config
from lightning_bodyschema.paths.layout import path_layout
from lightning_bodyschema.paths.module import GeometricPath

STEPS = 10_000  # 1e-4 of the line per step
# a jump: a step of a length above 0.1 mm between neighbours; the smooth change per step is at most ~0.025 mm here
# (moment arms <= ~50 mm/rad over <= ~5e-4 rad per step on these lines)
JUMP_M = 1e-4
# (config, line seeds): myoArm's cross 11 jumps (seed 4: DELT1's 1.85 mm where its end site enters the sphere;
# 7 of them at a side margin, 4 at an end margin); myoLegs' lines (no jump on 200 lines at 1/2000) keep it honest
LINES = [("configs/myoarm.yaml", (4, 11, 12)), ("configs/myolegs-per-muscle.yaml", (0, 1))]


def _line_changes(body, path, seed):
    """On one seeded line: ``jump (S, M)`` (a length step > JUMP_M), ``sign (S, M)`` (a margin of the muscle changes
    sign between finite values) and ``onoff (S, M)`` (a margin turns from finite to +inf or back)."""
    lo, hi = body.q_range.T
    a, b = lo + (hi - lo) * np.random.default_rng(seed).random((2, len(lo)))
    q = a + np.linspace(0, 1, STEPS + 1)[:, None] * (b - a)
    length = body.kinematics(q)[0]
    with torch.no_grad():
        margins = torch.stack(path.margins(torch.as_tensor(q))).numpy()  # (kinds, S + 1, M, K)
    finite = np.isfinite(margins)
    both = finite[:, 1:] & finite[:, :-1]
    sign = (both & (np.signbit(margins[:, 1:]) != np.signbit(margins[:, :-1]))).any(axis=(0, 3))
    onoff = (finite[:, 1:] != finite[:, :-1]).any(axis=(0, 3))
    return np.abs(np.diff(length, axis=0)) > JUMP_M, sign, onoff


# myoLegs' lines hold no jump (its half only checks that nothing goes unmarked): a slow test
@pytest.mark.parametrize("config, seeds", [pytest.param(*line, marks=[pytest.mark.slow] if i else [])
                                           for i, line in enumerate(LINES)], ids=["myoArm", "myoLegs"])
def test_every_jump_is_at_a_margin_sign_change(config, seeds):
    body = robot_from_config(config)[0]
    path = GeometricPath(path_layout(body))
    counts = dict(jumps=0, unexplained=0, sign_changes=0, sign_changes_without_jump=0)
    for seed in seeds:
        jump, sign, onoff = _line_changes(body, path, seed)
        unexplained = jump & ~sign & ~onoff
        assert not unexplained.any(), [(seed, int(i), body.muscle_names[m]) for i, m in zip(*np.nonzero(unexplained))]
        counts["jumps"] += int(jump.sum())
        counts["sign_changes"] += int(sign.sum())
        counts["sign_changes_without_jump"] += int((sign & ~jump).sum())
    if "myoarm" in config:  # the lines cross real jumps (DELT1's at least), else the test could not fail
        assert counts["jumps"] >= 5, counts
    print(config, counts)
