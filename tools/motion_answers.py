#!/usr/bin/env python
"""The answers of ``inverse_dynamics`` on the benchmark's motions, written to a file or compared with one: a check
that a speed change leaves every number where it was (run it on two checkouts; only the public API is used).

    PYTHONPATH=<checkout A> python tools/motion_answers.py --write /tmp/a.npz
    PYTHONPATH=<checkout B> python tools/motion_answers.py --against /tmp/a.npz [--tol 1e-12]

Cases (``tools/bench_static_opt.py``'s motions): the myoArm reach healthy, with BIClong cut, BIClong weakened to
100 N, with the tension objective, with a residual actuator on the elbow, and ``muscles_for_torque`` on the reach's
torques; the myoLegs squat (``--frames`` frames) healthy, with soleus_r cut, and with its pelvis free. Compared per
case: the statuses (equal), and the largest difference of activations, tensions [N], controls, residuals [N m] and
root residuals [N, N m] where both are finite; a NaN on one side only counts as a difference. Exit status 1 where
a status differs, an activation by more than ``--tol`` or a control by more than ``CONTROL_GAIN`` times it.
"""
import argparse
import os
import sys

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from bench_static_opt import bodies, pelvis_motion, reach, squat  # noqa: E402

from lightning_bodyschema.statics import inverse_dynamics, muscles_for_torque  # noqa: E402

FIELDS = ("activation", "tension_n", "control", "residual_nm", "root_residual")
# a control is a0 + (a1 - a0) tau / h: an activation's difference comes back times up to 1 + 2 tau / h on it, with
# MyoSuite's deactivation tau of up to 0.04 s / (0.5 + 1.5 a) = 0.08 s and 2 ms frames: 81
CONTROL_GAIN = 100.0


def arm_cases(body):
    t, q, qvel, qacc = reach(body)
    run = lambda **kw: inverse_dynamics(body, q, qvel, qacc, t=t, **kw)  # noqa: E731
    healthy = run()
    return {"arm healthy": healthy, "arm BIClong cut": run(faults={"cut": ["BIClong_tendon"]}),
            "arm BIClong weak 100 N": run(faults={"weak": {"BIClong_tendon": 100.0}}),
            "arm tension objective": run(objective="tension"),
            "arm elbow residual": run(residual_dofs=["elbow_flexion_r"], residual_weight=10.0),
            "arm muscles_for_torque": muscles_for_torque(body, q, healthy.tau_nm, qvel=qvel)}


def leg_cases(body, frames):
    t, q, qvel, qacc = squat(body, frames)
    root = pelvis_motion(t)
    return {"legs healthy": inverse_dynamics(body, q, qvel, qacc, t=t),
            "legs soleus_r cut": inverse_dynamics(body, q, qvel, qacc, t=t, faults={"cut": ["soleus_r_tendon"]}),
            "legs pelvis free": inverse_dynamics(body, q, qvel, qacc, t=t, root_qpos=root[0], root_qvel=root[1],
                                                 root_qacc=root[2])}


def answers(frames: int) -> dict:
    """``{"<case>/<field>": array}`` of every case (statuses as their names)."""
    made = bodies()
    cases = {**arm_cases(made["myoArm"]()), **leg_cases(made["myoLegs"](), frames)}
    out = {}
    for case, result in cases.items():
        out[f"{case}/status"] = np.array([str(s) for s in result.status])
        for name in FIELDS:
            value = getattr(result, name)
            if value is not None:
                out[f"{case}/{name}"] = np.asarray(value, dtype=np.float64)
    return out


def difference(a: np.ndarray, b: np.ndarray) -> float:
    """The largest |a - b| where both are finite; inf where their shapes or their NaN patterns differ."""
    if a.shape != b.shape or not np.array_equal(np.isnan(a), np.isnan(b)):
        return np.inf
    both = np.isfinite(a) & np.isfinite(b)
    return float(np.abs(a[both] - b[both]).max(initial=0.0))


def compare(mine: dict, theirs: dict, tol: float) -> bool:
    """Prints each case's differences; True where statuses agree and activations and controls are within ``tol``."""
    good = set(mine) == set(theirs)
    if not good:
        print(f"fields differ: only here {sorted(set(mine) - set(theirs))}, only there "
              f"{sorted(set(theirs) - set(mine))}")
    for case in sorted({key.split("/")[0] for key in mine}):
        same = np.array_equal(mine[f"{case}/status"], theirs.get(f"{case}/status"))
        gaps = {name: difference(mine[f"{case}/{name}"], theirs[f"{case}/{name}"]) for name in FIELDS
                if f"{case}/{name}" in mine and f"{case}/{name}" in theirs}
        good &= same and gaps.get("activation", 0.0) <= tol and gaps.get("control", 0.0) <= CONTROL_GAIN * tol
        print(f"  {case:26s} statuses {'equal' if same else 'DIFFER'}; "
              + ", ".join(f"{name} {gap:.1e}" for name, gap in gaps.items()))
    return good


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    group = parser.add_mutually_exclusive_group(required=True)
    group.add_argument("--write", help="write this checkout's answers to this .npz")
    group.add_argument("--against", help="compare this checkout's answers with this .npz")
    parser.add_argument("--frames", type=int, default=10000, help="frames of the myoLegs squat")
    parser.add_argument("--tol", type=float, default=1e-12, help="largest activation difference (controls: x100)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    mine = answers(args.frames)
    if args.write:
        tmp = f"{args.write}.tmp.npz"
        np.savez(tmp, **mine)
        os.replace(tmp, args.write)
        print(f"wrote {len(mine)} arrays to {args.write}")
        return 0
    with np.load(args.against) as stored:
        theirs = {key: stored[key] for key in stored.files}
    good = compare(mine, theirs, args.tol)
    print(f"answers agree (activations within {args.tol:g}, controls within {CONTROL_GAIN * args.tol:g})" if good else
          f"answers DIFFER (statuses, or activations beyond {args.tol:g} / controls beyond {CONTROL_GAIN * args.tol:g})")
    return 0 if good else 1


if __name__ == "__main__":
    sys.exit(main())
