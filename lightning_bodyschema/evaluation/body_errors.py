"""A learned body against MuJoCo's, posture by posture: a posture is only as good as its worst muscle.

Per-muscle percentiles pool every (posture, muscle) pair, so one muscle off by centimetres at a few postures hides in
them (myoArm: per-muscle length p99 0.067 mm, worst muscle per posture p99 9.2 mm). ``worst_per_posture`` takes, at
each posture, the largest length error over the muscles, the largest moment-arm error over the muscle-joint pairs a
muscle crosses, and the largest torque error over the joints, with the muscle (and joint) where each is reached;
``bad_regions`` says where the bad postures are: which muscle is worst there and which of its joints they bunch on;
``jump_distance`` how far a posture is from a jump of the true path (a wrap switching sides), probed in the simulator.

numpy only; never imports Lightning or torch.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

BAD_LENGTH_MM = 0.1  # a posture whose worst muscle misses its length by more than this is "bad" [mm]
JUMP_MM = 0.5  # a second difference of a true length above this at STEP_RAD is a jump, not a bend [mm] (a smooth
# path bends by ~1e-4 mm there: curvatures up to 100 mm/rad^2; myoArm's wraps jump by 0.7-20 mm)
STEP_RAD = 1e-3  # the probe's step along a joint [rad]


class WorstPerPosture(NamedTuple):
    """(B,) arrays: each posture's worst muscle and its errors."""

    length_mm: np.ndarray  # largest |l_hat - l_true| over the muscles [mm]
    length_muscle: np.ndarray  # the muscle where it is reached (int)
    arm_mm_per_rad: np.ndarray  # largest |G_hat - G_true| over the crossed muscle-joint pairs [mm/rad]
    arm_muscle: np.ndarray  # its muscle (int)
    arm_joint: np.ndarray  # its joint (int)
    torque_nm: np.ndarray  # largest |tau_hat - tau_true| over the joints [N m]
    torque_joint: np.ndarray  # its joint (int)


def worst_per_posture(learned, true, crossed: np.ndarray) -> WorstPerPosture:
    """``learned`` and ``true``: (l_geo (B, M) [m], G (B, M, N) [m/rad], tau (B, N) [N m]); ``crossed`` (M, N) bool:
    the pairs a muscle crosses (an uncrossed pair's moment arm is 0 and not counted here)."""
    (l_hat, g_hat, tau_hat), (l_true, g_true, tau_true) = learned, true
    length = 1e3 * np.abs(l_hat - l_true)
    arm = np.where(crossed, 1e3 * np.abs(g_hat - g_true), 0.0).reshape(len(length), -1)
    torque = np.abs(tau_hat - tau_true)
    rows, pair = np.arange(len(length)), np.argmax(arm, axis=1)
    muscle, joint = np.divmod(pair, crossed.shape[1])
    return WorstPerPosture(length.max(axis=1), np.argmax(length, axis=1), arm[rows, pair], muscle, joint,
                           torque.max(axis=1), np.argmax(torque, axis=1))


def summary(worst: WorstPerPosture) -> dict[str, float]:
    """Median, p90, p99 and max of each worst-per-posture error, and the share of bad postures (scalars to log)."""
    out = {}
    for field, key in (("length_mm", "length_mm"), ("arm_mm_per_rad", "arm_mm_per_rad"), ("torque_nm", "torque_N_m")):
        for label, p in (("p50", 50), ("p90", 90), ("p99", 99), ("max", 100)):  # N_m: "nm" reads as nanometres
            out[f"worst_{key}_{label}"] = float(np.percentile(getattr(worst, field), p))
    out["bad_posture_fraction"] = float(np.mean(worst.length_mm > BAD_LENGTH_MM))
    return out


def bad_regions(worst: WorstPerPosture, q: np.ndarray, q_range: np.ndarray, crossed: np.ndarray, k: int = 5):
    """Where the bad postures are: up to ``k`` rows ``(muscle, n_bad, largest_mm, joint, lo_rad, hi_rad)``, the muscles
    most often worst at a bad posture, and for each the joint it crosses on which those postures bunch most (the
    smallest spread relative to the joint's range) with their 10-90 % interval there [rad]."""
    bad = worst.length_mm > BAD_LENGTH_MM
    muscles, counts = np.unique(worst.length_muscle[bad], return_counts=True)
    rows = []
    for i in np.argsort(-counts)[:k]:
        m = int(muscles[i])
        at = bad & (worst.length_muscle == m)
        joints = np.flatnonzero(crossed[m]) if crossed[m].any() else np.arange(q.shape[1])
        lo, hi = np.percentile(q[at][:, joints], 10, axis=0), np.percentile(q[at][:, joints], 90, axis=0)
        j = int(np.argmin((hi - lo) / np.maximum(q_range[joints, 1] - q_range[joints, 0], 1e-12)))
        rows.append((m, int(counts[i]), float(worst.length_mm[at].max()), int(joints[j]), float(lo[j]), float(hi[j])))
    return rows


def bad_regions_table(rows, muscle_names, joint_names) -> str:
    """``bad_regions`` as a markdown table."""
    lines = [f"| worst muscle at a bad posture (> {BAD_LENGTH_MM} mm) | postures | largest [mm] | "
             "where they bunch: joint, 10-90 % [rad] |", "|---|---|---|---|"]
    lines += [f"| {muscle_names[m]} | {n} | {big:.4g} | {joint_names[j]} {lo:.3f} .. {hi:.3f} |"
              for m, n, big, j, lo, hi in rows]
    return "\n".join(lines)


def jump_distance(model, q: np.ndarray, muscle: np.ndarray, crossed: np.ndarray, reach_rad: float = 0.3) -> np.ndarray:
    """``(K,)`` [rad]: how far each posture ``q (K, N)`` is from a jump of its ``muscle (K,)``'s true length along any
    joint the muscle crosses (``crossed (M, N)``), within ``reach_rad`` (``inf``: none): the true length on a line
    through the posture along each such joint at ``STEP_RAD`` steps (one batched ``model.kinematics`` call, inside the
    joint's range), a jump where its second difference exceeds ``JUMP_MM``."""
    offsets = np.arange(-reach_rad, reach_rad + STEP_RAD / 2, STEP_RAD)
    case, joint = np.nonzero(crossed[muscle])  # one line per (posture, crossed joint)
    if not len(case):  # no posture (or none whose muscle crosses a joint): nothing to probe
        return np.full(len(q), np.inf)
    lines = np.repeat(q[case][:, None, :], len(offsets), 1)  # (P, T, N)
    lo, hi = model.q_range[joint, 0][:, None], model.q_range[joint, 1][:, None]
    along = q[case, joint][:, None] + offsets[None, :]
    inside = (along >= lo) & (along <= hi)
    lines[np.arange(len(case)), :, joint] = np.clip(along, lo, hi)
    length_mm = 1e3 * model.kinematics(lines.reshape(-1, q.shape[1]))[0].reshape(len(case), len(offsets), -1)
    length_mm = np.take_along_axis(length_mm, muscle[case][:, None, None], 2)[..., 0]  # (P, T)
    bend = np.abs(np.diff(length_mm, 2, axis=1))
    jump = (bend > JUMP_MM) & inside[:, :-2] & inside[:, 1:-1] & inside[:, 2:]
    per_line = np.where(jump, np.abs(offsets[1:-1])[None, :], np.inf).min(1, initial=np.inf)
    out = np.full(len(q), np.inf)
    np.minimum.at(out, case, per_line)
    return out
