#!/usr/bin/env python
"""A checkpoint's learned body against MuJoCo's: muscle lengths, moment arms, torque (median and p99).

    python tools/body_errors.py --ckpt runs/myoarm/.../last.ckpt [--postures 2000] [--seed 1] [--worst 5]
                                [--near-jumps] [--holdable]

At ``--postures`` seeded uniform postures of the checkpoint's robot (its MJCF; a checkpoint without a model stops
with one line; ``--holdable``: uniform among the postures its true muscles can hold, the data's own distribution):
|l_geo - l_mujoco| [mm]; |G - G_mujoco| [mm/rad] on the muscle-joint pairs the muscle crosses
(MuJoCo's tendon Jacobian is nonzero), and the largest |G| on the pairs it does not cross (truly 0); the torque
error ||tau - tau_bias|| [N m] and its ratio to the median ||tau_bias||; then the ``--worst`` muscles by length
p99 (their share of postures off by more than 0.1 mm and their largest error: where a pooled p99 comes from).
Then the worst muscle per posture (``evaluation.body_errors``: a posture is only as good as its worst muscle): the
largest length, moment-arm and torque error at each posture, median / p90 / p99 / max over the postures, the share of
postures whose worst muscle is off by more than 0.1 mm, and where those bad postures are (the muscle worst there most
often, the joint they bunch on and their interval). Then the postures the adapter flags as near a learned path
switch (``StructuredSchema.path_switches``: ``near_path_switch``), counted, and the worst muscle per posture over the
others. ``--near-jumps``: is the tail at the true path's jumps? For the postures whose worst muscle misses by at
least its p99, for up to 100 of those missing by 0.1-1 mm and for as many postures drawn at random (the tail's
muscles), the share within 0.01 / 0.05 / 0.1 / 0.3 rad of a jump
of that muscle's true length along a joint it crosses (``evaluation.body_errors.jump_distance``). Any schema with
``body_si`` (``StructuredSchema``). One torch thread.
"""
import argparse

import numpy as np
import torch

from lightning_bodyschema.apps.common import exits_cleanly
from lightning_bodyschema.errors import BodySchemaInputError
from lightning_bodyschema.evaluation.body_errors import BAD_LENGTH_MM, bad_regions, bad_regions_table, jump_distance, \
    summary, worst_per_posture


def body_errors(schema, q: np.ndarray) -> dict:
    """The learned body's errors against MuJoCo at postures ``q (B, N)`` [rad] (module docstring)."""
    l_true, G_true, tau_true = schema.robot_model.kinematics(q)
    l_hat, G_hat, tau_hat = schema.body_si(torch.as_tensor(q))
    crossed = np.abs(G_true).max(0) > 1e-12  # (M, N)
    length_mm, arm_mm = 1e3 * np.abs(l_hat - l_true), 1e3 * np.abs(G_hat - G_true)[:, crossed]
    tau_nm, tau_ref = np.linalg.norm(tau_hat - tau_true, axis=1), float(np.median(np.linalg.norm(tau_true, axis=1)))
    pct = lambda a, p: float(np.percentile(a, p))  # noqa: E731
    return {"length_mm": (pct(length_mm, 50), pct(length_mm, 99)),
            "arm_mm_per_rad": (pct(arm_mm, 50), pct(arm_mm, 99)),
            "uncrossed_max_mm_per_rad": 1e3 * float(np.abs(G_hat[:, ~crossed]).max(initial=0.0)),
            "pairs": (int(crossed.sum()), int((~crossed).sum())), "torque_nm": (pct(tau_nm, 50), pct(tau_nm, 99)),
            "torque_ratio": pct(tau_nm, 50) / tau_ref, "tau_bias_median_nm": tau_ref,
            "per_muscle_length_mm": length_mm,
            "worst": worst_per_posture((l_hat, G_hat, tau_hat), (l_true, G_true, tau_true), crossed), "crossed": crossed}


def worst_report(errors: dict, model, k: int) -> str:
    """The worst muscle per posture: its errors over the postures, then where the bad postures are."""
    s, n = summary(errors["worst"]), len(errors["worst"].length_mm)
    lines = [f"| worst per posture ({n} postures) | median | p90 | p99 | max |", "|---|---|---|---|---|"]
    for label, key in (("muscle length [mm]", "length_mm"), ("moment arm [mm/rad]", "arm_mm_per_rad"),
                       ("joint torque [N m]", "torque_N_m")):
        lines.append(f"| {label} | " + " | ".join(f"{s[f'worst_{key}_{p}']:.4g}" for p in ("p50", "p90", "p99", "max"))
                     + " |")
    lines += ["", f"postures whose worst muscle is off by > 0.1 mm: {100 * s['bad_posture_fraction']:.3g} %", "", ""]
    rows = bad_regions(errors["worst"], errors["q"], model.q_range, errors["crossed"], max(k, 1))
    return "\n".join(lines) + bad_regions_table(rows, model.muscle_names, model.joint_names)


def flagged_report(worst, flagged: np.ndarray) -> str:
    """The share of postures flagged near a learned path switch and the worst muscle per posture over the others."""
    rest = summary(type(worst)(*(a[~flagged] for a in worst))) if (~flagged).any() else None
    lines = [f"postures flagged near a learned path switch: {int(flagged.sum())} of {len(flagged)} "
             f"({100 * float(flagged.mean()):.3g} %)"]
    if rest is not None:
        lines.append("the others, worst muscle per posture: length p99 {:.4g} mm, max {:.4g} mm; moment arm p99 {:.4g} "
                     "mm/rad".format(rest["worst_length_mm_p99"], rest["worst_length_mm_max"],
                                     rest["worst_arm_mm_per_rad_p99"]))
    return "\n".join(lines)


def near_jumps_report(worst, q: np.ndarray, model, crossed: np.ndarray) -> str:
    """``--near-jumps`` (module docstring): the tail's and the 0.1-1 mm postures' distance to a true jump."""
    bulk = np.flatnonzero((worst.length_mm > BAD_LENGTH_MM) & (worst.length_mm <= 1.0))[:100]
    lines = ["| postures (worst muscle's length error) | n | within 0.01 / 0.05 / 0.1 / 0.3 rad of a true jump |",
             "|---|---|---|"]
    tail = np.flatnonzero(worst.length_mm >= np.percentile(worst.length_mm, 99))
    anywhere = np.random.default_rng(0).choice(len(q), len(tail), replace=False)
    for label, rows, muscles in (("p99 tail", tail, worst.length_muscle[tail]),
                                 (f"{BAD_LENGTH_MM}-1 mm", bulk, worst.length_muscle[bulk]),
                                 ("any posture, the tail's muscles", anywhere, worst.length_muscle[tail])):
        reach = jump_distance(model, q[rows], muscles, crossed)
        shares = " / ".join(f"{100 * float(np.mean(reach <= x)):.0f} %" if len(rows) else "-"
                            for x in (0.01, 0.05, 0.1, 0.3))
        lines.append(f"| {label} | {len(rows)} | {shares} |")
    return "\n".join(lines)


def worst_muscles(errors: dict, names, k: int) -> str:
    """The ``k`` muscles with the largest length p99 (``errors["per_muscle_length_mm"] (B, M)``), a table."""
    length_mm = errors["per_muscle_length_mm"]
    p99 = np.percentile(length_mm, 99, axis=0)
    lines = ["| muscle | length p99 [mm] | postures off by > 0.1 mm | largest [mm] |", "|---|---|---|---|"]
    for i in np.argsort(-p99)[:k]:
        lines.append(f"| {names[i]} | {p99[i]:.4g} | {100 * float((length_mm[:, i] > 0.1).mean()):.3g} % | "
                     f"{float(length_mm[:, i].max()):.4g} |")
    return "\n".join(lines)


def report(errors: dict) -> str:
    (crossed, uncrossed), e = errors["pairs"], errors
    return "\n".join([
        "| quantity | median | p99 |", "|---|---|---|",
        f"| muscle length [mm] | {e['length_mm'][0]:.4g} | {e['length_mm'][1]:.4g} |",
        f"| moment arms, {crossed} crossed pairs [mm/rad] | {e['arm_mm_per_rad'][0]:.4g} | "
        f"{e['arm_mm_per_rad'][1]:.4g} |",
        f"| moment arms, {uncrossed} uncrossed pairs (truly 0), largest [mm/rad] | "
        f"{e['uncrossed_max_mm_per_rad']:.3g} | |",
        f"| torque error [N m] | {e['torque_nm'][0]:.4g} | {e['torque_nm'][1]:.4g} |",
        f"| torque error / median abs(tau_bias) ({e['tau_bias_median_nm']:.4g} N m) | "
        f"{100 * e['torque_ratio']:.3g} % | |"])


def postures(schema, n: int, seed: int, holdable: bool) -> np.ndarray:
    """``n`` seeded uniform postures of the checkpoint's robot, or with ``holdable`` uniform among those its true
    muscles can hold (``generate_equilibrium_samples``: the distribution the data is drawn from; a posture no tension
    holds never appears in the data, and its learned body there is an extrapolation)."""
    if not holdable:
        return schema.robot_model.sample_q(np.random.default_rng(seed), n)
    from lightning_bodyschema.sim import generate_equilibrium_samples

    return generate_equilibrium_samples(schema.robot_model, n, seed, schema.spring).q


@exits_cleanly
def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ckpt", required=True)
    parser.add_argument("--postures", type=int, default=2000)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--worst", type=int, default=5, help="muscles listed by length p99 (0: none)")
    parser.add_argument("--near-jumps", action="store_true", help="the tail's distance to the true path's jumps")
    parser.add_argument("--holdable", action="store_true",
                        help="postures uniform among those the true muscles can hold (the data's distribution)")
    args = parser.parse_args(argv)
    if args.postures < 1 or args.worst < 0:
        raise BodySchemaInputError(f"--postures {args.postures} / --worst {args.worst}: expected integers >= 1 / >= 0")
    torch.set_num_threads(1)
    from lightning_bodyschema.schemas.loading import load_schema

    schema = load_schema(args.ckpt).eval()
    if not hasattr(schema, "body_si"):
        raise BodySchemaInputError(f"{args.ckpt}: a {type(schema).__name__} has no learned body (body_si); "
                                   "only StructuredSchema checkpoints have one")
    if not schema.has_physics:
        raise BodySchemaInputError(f"{args.ckpt}: its robot has no model (recorded data): there is no MuJoCo body "
                                   "to compare with")
    q = postures(schema, args.postures, args.seed, args.holdable)
    errors = dict(body_errors(schema, q), q=q)
    print(report(errors))
    if args.worst:
        print()
        print(worst_muscles(errors, schema.robot_model.muscle_names, args.worst))
    print()
    print(worst_report(errors, schema.robot_model, args.worst))
    if hasattr(schema, "path_switches"):
        print()
        print(flagged_report(errors["worst"], schema.path_switches(q)["near_path_switch"]))
    if args.near_jumps:
        print()
        print(near_jumps_report(errors["worst"], q, schema.robot_model, errors["crossed"]))


if __name__ == "__main__":
    main()
