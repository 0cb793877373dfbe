#!/usr/bin/env python
"""Static optimization speed and checks on myoArm and myoLegs (issue 34), and the README's trajectory figure; with
``--motion``, inverse dynamics on two held-out motions (issue 50).

    python tools/bench_static_opt.py --n 2000 --repeats 3 [--bodies myoArm myoLegs] [--plot docs/static_opt.png]
    python tools/bench_static_opt.py --motion [--bodies myoArm myoLegs] [--plot docs/motion_opt.png]

Per body: the median time per posture of ``StaticBody.solve`` on ``--n`` seeded postures in one batch, of one
posture at a time (``--singles`` calls), and side by side the MuJoCo kinematics alone and the dataset's equilibrium
QP (``sim.equilibrium.solve_equilibrium_qp``, f_ref uniform in [0, f_max]) on the same postures; the status counts;
on myoArm the largest MuJoCo residual (``statics.check.mujoco_residual_nm``) of a sample of ok rows. The machine's
load average is printed with the timings: they depend on it. One torch thread.

``--motion``: a myoArm reach (elbow and shoulder, minimum jerk, 2 s) and a myoLegs squat (hips, knees, ankles, 4 s
per squat, repeated to ``--frames`` frames), frames 2 ms apart, analytic velocities and accelerations. Per body: the
time per frame of ``inverse_dynamics`` on the whole motion, side by side (alternating) with per-frame SLSQP on the
same problem as a MuJoCo user writes it (per frame: ``mj_inverse``, then scipy's SLSQP on ``min sum a^2`` with the
same muscle curves; on ``--slsqp-frames`` frames), and our MuJoCo part alone (the bound on the ratio a free QP
would give); the statuses; MuJoCo's forward check on a sample of frames
(``statics.check.mujoco_motion_error``); on myoLegs the squat again with its pelvis free (a floating root,
``statics.root``); on myoArm the tracking in MuJoCo (``statics.track``); the Savitzky-Golay
differentiator's accuracy on an analytic motion (``statics.differentiate``).
"""
import argparse
import copy
import os
import statistics

import numpy as np
import torch
import yaml

from lightning_bodyschema.apps.common import count_values
from lightning_bodyschema.apps.reproduce import _median_seconds as timed  # a warm-up call, then the median
from lightning_bodyschema.sim.equilibrium import solve_equilibrium_qp
from lightning_bodyschema.solvers import BoxQP, proxsuite_solve
from lightning_bodyschema.statics import StaticBody
from lightning_bodyschema.statics.check import mujoco_residual_nm
from lightning_bodyschema.status import status_names

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def bodies():
    with open(os.path.join(ROOT, "configs", "myoarm.yaml")) as fh:
        locks = yaml.safe_load(fh)["data"]["locked_joints"]
    return {"myoArm": lambda: StaticBody("myo:myoarm", locked_joints=locks),
            "myoLegs": lambda: StaticBody("myo:myolegs", fixed_base=True)}


def bench(name, body, n, repeats, singles, cut):
    q = body.model.sample_q(np.random.default_rng(0), n)
    result = body.solve(q)
    counts = count_values(status_names(result.status))
    held = q[result.ok]
    f_max = np.broadcast_to(np.asarray(body.spring.f_max_n, float), (len(q), body.model.n_muscles))
    f_ref = f_max * np.random.default_rng(1).random(f_max.shape)
    kin = body.model.kinematics(q)
    threaded = copy.copy(body)
    threaded.threads = 2
    rows = {
        "solve, all postures": timed(lambda: body.solve(q), repeats) / n,
        "solve, all postures, kinematics on 2 threads": timed(lambda: threaded.solve(q), repeats) / n,
        "solve, ok postures only": timed(lambda: body.solve(held), repeats) / len(held),
        f"solve, {cut} cut": timed(lambda: body.solve(q, {"cut": [cut]}), repeats) / n,
        "solve, tension objective": timed(lambda: body.solve(q, objective="tension"), repeats) / n,
        "MuJoCo kinematics alone": timed(lambda: body.model.kinematics(q), repeats) / n,
        "MuJoCo kinematics alone, 2 threads": timed(lambda: body.model.kinematics(q, 2), repeats) / n,
        "dataset QP (kinematics + solve_equilibrium_qp)": timed(
            lambda: solve_equilibrium_qp(*body.model.kinematics(q)[1:], f_ref, f_hi_n=f_max), repeats) / n,
        "one posture at a time (median call)": statistics.median(
            timed(lambda k=k: body.solve(held[k:k + 1]), 1) for k in range(min(singles, len(held)))),
    }
    print(f"\n{name}: {body.model.n_joints} free joints, {body.model.n_muscles} muscles, {n} postures; "
          f"status {counts}; load average {os.getloadavg()[0]:.1f}")
    for label, seconds in rows.items():
        print(f"  {label:48s} {1e3 * seconds:8.3f} ms per posture")
    del kin
    return result


def proxsuite_gap_n(body, result, eps_abs=1e-13):
    """Largest and median |f - f_proxsuite| [N] over the ``ok`` rows of a healthy activation-objective ``result``:
    proxsuite alone (at ``eps_abs``) on the same QP in activations, and how many rows it solved."""
    ok = result.take(result.ok)
    l_geo, G, tau = body.model.kinematics(ok.q)
    lo, hi, s, p = body.tension_bounds(l_geo, ok.faults)
    hi = np.minimum(hi, p + s)
    unit = np.where(s > 0, s, 1.0)
    a_lo, a_hi = np.where(s > 0, (lo - p) / unit, 0.0), np.where(s > 0, (hi - p) / unit, 0.0)
    problem = BoxQP.build(G * s[..., None], tau + np.einsum("bmn,bm->bn", G, p), np.zeros_like(lo), a_lo, a_hi)
    a, solved = proxsuite_solve(problem, 10000, eps_abs=eps_abs)
    gap = np.abs(s * a.numpy() + p - ok.tension_n)[solved.numpy()]
    return gap.max(), np.median(gap), int(solved.sum()), len(ok.q)


def plot(body, path, cut):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    lo, hi = body.model.q_range.T
    names = body.model.joint_names
    base = np.zeros(len(names))
    base[names.index("shoulder_elv_r")] = 0.5
    base = np.clip(base, lo, hi)
    elbow = names.index("elbow_flexion_r")
    sweep = np.linspace(max(lo[elbow], 0.1), min(hi[elbow], 2.2), 200)
    q = np.tile(base, (len(sweep), 1))
    q[:, elbow] = sweep
    healthy, ruptured = body.solve(q), body.solve(q, {"cut": [cut]})
    cut_index = body.model.muscle_names.index(cut)
    top = [cut_index] + [m for m in np.argsort(-np.nanmax(healthy.tension_n, 0)) if m != cut_index][:5]
    fig, (ax_f, ax_a) = plt.subplots(1, 2, figsize=(11, 4), constrained_layout=True)
    for k, m in enumerate(top):
        color = f"C{k}"
        label = body.model.muscle_names[m].removesuffix("_tendon")
        ax_f.plot(sweep, healthy.tension_n[:, m], color=color, label=label)
        ax_f.plot(sweep, ruptured.tension_n[:, m], color=color, ls="--")
        ax_a.plot(sweep, healthy.activation[:, m], color=color)
        ax_a.plot(sweep, ruptured.activation[:, m], color=color, ls="--")
    not_ok = ~ruptured.ok
    if not_ok.any():
        ax_a.plot(sweep[not_ok], np.full(not_ok.sum(), 1.02), "k|", label="ruptured: not ok")
    ax_f.set(xlabel="elbow_flexion_r [rad]", ylabel="tension [N]",
             title=f"myoArm tensions: healthy (solid), {cut.removesuffix('_tendon')} ruptured (dashed)")
    ax_a.set(xlabel="elbow_flexion_r [rad]", ylabel="activation", title="MuJoCo activations (min sum a^2)")
    ax_f.legend(fontsize=8)
    if not_ok.any():
        ax_a.legend(fontsize=8)
    fig.savefig(path, dpi=110)
    print(f"wrote {path}")


def minimum_jerk(t, start, end, duration_s):
    """Positions, velocities, accelerations (B, N) from ``start`` to ``end`` over ``duration_s``, held after."""
    s = np.clip(t / duration_s, 0.0, 1.0)[:, None]
    pos, vel = 10 * s ** 3 - 15 * s ** 4 + 6 * s ** 5, (30 * s ** 2 - 60 * s ** 3 + 30 * s ** 4) / duration_s
    acc = (60 * s - 180 * s ** 2 + 120 * s ** 3) / duration_s ** 2
    span = np.asarray(end) - np.asarray(start)
    return start + span * pos, span * vel, span * acc


def reach(body, step_s=0.002):
    """myoArm: shoulder elevation 0.3 -> 1.2 rad, elevation plane 0 -> 0.6, elbow 1.6 -> 0.4 in 2 s."""
    names, (lo, hi) = body.model.joint_names, body.model.q_range.T
    start = np.clip(np.zeros(len(names)), lo, hi)
    end = start.copy()
    for joint, a, b in (("shoulder_elv_r", 0.3, 1.2), ("elv_angle_r", 0.0, 0.6), ("elbow_flexion_r", 1.6, 0.4)):
        start[names.index(joint)], end[names.index(joint)] = a, b
    t = np.arange(0.0, 2.0 + step_s / 2, step_s)
    return (t, *minimum_jerk(t, start, end, 2.0))


def squat(body, frames, step_s=0.002):
    """myoLegs: both hips 0 -> 1.0 rad, knees 0 -> 1.4, ankles 0 -> 0.35 and back, 4 s per squat, ``frames`` frames
    (a raised cosine: 0.5 (1 - cos(2 pi t / 4 s)))."""
    names = body.model.joint_names
    depth = np.zeros(len(names))
    for side in "rl":
        for joint, value in (("hip_flexion", 1.0), ("knee_angle", 1.4), ("ankle_angle", 0.35)):
            depth[names.index(f"{joint}_{side}")] = value
    t = step_s * np.arange(frames)
    w = 2 * np.pi / 4.0
    shape = 0.5 * (1 - np.cos(w * t))[:, None], 0.5 * w * np.sin(w * t)[:, None], 0.5 * w ** 2 * np.cos(w * t)[:, None]
    return (t, *(depth * x for x in shape))


def pelvis_motion(t, sink_m=0.15, turn_rad=0.3, period_s=4.0):
    """myoLegs' free root over a squat: the pelvis sinks ``sink_m`` (raised cosine) and turns ``turn_rad`` sin about
    the vertical, from MyoSuite's standing pose (1 m up): MuJoCo's ``(qpos (B, 7), qvel, qacc (B, 6))``, exact."""
    w = 2 * np.pi / period_s
    z = np.stack([1.0 - sink_m * 0.5 * (1 - np.cos(w * t)), -sink_m * 0.5 * w * np.sin(w * t),
                  -sink_m * 0.5 * w ** 2 * np.cos(w * t)])
    yaw = np.stack([turn_rad * np.sin(w * t), turn_rad * w * np.cos(w * t), -turn_rad * w ** 2 * np.sin(w * t)])
    zero = np.zeros_like(t)
    qpos = np.stack([zero, zero, z[0], np.cos(yaw[0] / 2), zero, zero, np.sin(yaw[0] / 2)], 1)
    qvel, qacc = (np.stack([zero, zero, z[k], zero, zero, yaw[k]], 1) for k in (1, 2))
    return qpos, qvel, qacc


def bench_floating(body, motion, repeats):
    """The myoLegs squat with its pelvis free (``pelvis_motion``): time per frame beside the welded squat
    (alternating), the root's residual forces, MuJoCo's forward check on every dof, the root's included."""
    from lightning_bodyschema.statics import inverse_dynamics
    from lightning_bodyschema.statics.check import mujoco_motion_error

    t, q, qvel, qacc = motion
    root = pelvis_motion(t)
    kwargs = dict(t=t, root_qpos=root[0], root_qvel=root[1], root_qacc=root[2])
    result = inverse_dynamics(body, q, qvel, qacc, **kwargs)
    floating, welded = [], []
    for _ in range(repeats):
        for times, extra in ((floating, kwargs), (welded, dict(t=t))):
            times.append(thread_seconds(lambda: inverse_dynamics(body, q, qvel, qacc, **extra)) / len(t))
    sample = result.take(np.linspace(0, len(t) - 1, 50).astype(int))
    error = np.abs(mujoco_motion_error(body, sample))[sample.ok]
    force = result.root_residual
    print(f"  pelvis free (sinks 0.15 m, turns 0.3 rad): status {count_values(status_names(result.status))}; "
          f"{1e3 * statistics.median(floating):.3f} ms per frame (welded {1e3 * statistics.median(welded):.3f}); "
          f"root residual force {force[:, 2].min():.1f}..{force[:, 2].max():.1f} N up (body weight "
          f"{body.model.mj_model.body_mass.sum() * 9.81:.1f} N), torque up to {np.abs(force[:, 3:]).max():.1f} N m; "
          f"MuJoCo forward check on {len(error)} ok frames, every dof and the root's 6: <= {error.max():.1e}")


def user_inverse(body):
    """The body's ``InverseBody`` with ``mj_inverse`` on the whole model (as a MuJoCo user calls it), compiled once,
    before any timing."""
    from lightning_bodyschema.statics.dynamics import InverseBody

    if getattr(body, "_user_inverse", None) is None:
        body._user_inverse = InverseBody(body, lean=False)
    return body._user_inverse


def slsqp_frames(body, q, qvel, qacc, jacobians=True):
    """Per frame as a MuJoCo user writes it: mj_inverse (``statics.dynamics.InverseBody`` on that frame), then SLSQP
    on ``min sum a^2``, ``0 <= a <= 1``, ``-G^T (FV s a + p) = tau``, with the objective's and the constraints'
    Jacobians given (``jacobians``) or left to scipy's finite differences (as scipy's examples and most scripts
    do). Returns the activations (NaN: SLSQP failed)."""
    from scipy.optimize import minimize

    inverse, out = user_inverse(body), np.full((len(q), body.model.n_muscles), np.nan)
    for b in range(len(q)):
        l_geo, G, tau = inverse.inverse(q[b:b + 1], qvel[b:b + 1], qacc[b:b + 1])[:3]
        s, p = body.curves.affine(l_geo)
        s = (s * body.curves.velocity_factor(np.einsum("bmn,bn->bm", G, qvel[b:b + 1])))[0]
        A, need = -(G[0] * s[:, None]).T, tau[0] + G[0].T @ p[0]
        constraint = {"type": "eq", "fun": lambda a: A @ a - need} | ({"jac": lambda a: A} if jacobians else {})
        solution = minimize(lambda a: a @ a, np.full(len(s), 0.1), jac=(lambda a: 2 * a) if jacobians else None,
                            method="SLSQP", bounds=[(0.0, 1.0)] * len(s), options={"ftol": 1e-12, "maxiter": 500},
                            constraints=constraint)
        if solution.success:
            out[b] = solution.x
    return out


def bench_motion(name, body, motion, slsqp_frames_n, repeats):
    from lightning_bodyschema.statics import inverse_dynamics
    from lightning_bodyschema.statics.check import mujoco_motion_error
    from lightning_bodyschema.statics.dynamics import _inverse_body

    t, q, qvel, qacc = motion
    result = inverse_dynamics(body, q, qvel, qacc, t=t)
    pick = np.linspace(0, len(t) - 1, slsqp_frames_n).astype(int)
    batched, per_frame, finite, mujoco_part = [], [], [], []
    inverse = _inverse_body(body)
    user_inverse(body)  # compiled before the clock starts
    loads = []
    for _ in range(repeats):  # alternating, so that a change in the machine's load falls on each
        loads.append(os.getloadavg()[0])
        for times, run in ((batched, lambda: inverse_dynamics(body, q, qvel, qacc, t=t)),
                           (mujoco_part, lambda: inverse.inverse(q, qvel, qacc))):
            times.append(thread_seconds(run) / len(t))
        reference = []
        per_frame.append(thread_seconds(lambda: reference.append(slsqp_frames(body, q[pick], qvel[pick],
                                                                              qacc[pick]))) / len(pick))
        finite.append(thread_seconds(lambda: slsqp_frames(body, q[pick[:10]], qvel[pick[:10]], qacc[pick[:10]],
                                                          jacobians=False)) / 10)
        reference = reference[0]
    ours, theirs, plain, ours_mujoco = (statistics.median(x) for x in (batched, per_frame, finite, mujoco_part))
    both = result.ok[pick] & np.isfinite(reference).all(1)
    gap = np.abs(result.activation[pick][both] - reference[both]).max() if both.any() else np.nan
    sample = result.take(pick)
    error = np.abs(mujoco_motion_error(body, sample))[sample.ok]
    clipped = result.control_clipped.any(1).mean()
    print(f"\n{name}: {len(t)} frames over {t[-1] - t[0]:.3g} s, {body.model.n_joints} free joints, "
          f"{body.model.n_muscles} muscles; status {count_values(status_names(result.status))}; load average "
          f"{' / '.join(f'{x:.1f}' for x in loads)} at the {repeats} alternating rounds (medians; thread CPU time)\n"
          f"  inverse_dynamics batched {1e3 * ours:.3f} ms per frame ({len(t) * ours:.2f} s in all); per-frame "
          f"mj_inverse + SLSQP with Jacobians {1e3 * theirs:.2f} ms per frame ({theirs / ours:.0f}x) on {len(pick)} "
          f"frames, activations differ by {gap:.1e} at most on {both.sum()} frames both solve; with finite-difference "
          f"Jacobians {1e3 * plain:.1f} ms per frame ({plain / ours:.0f}x) on 10 frames\n"
          f"  of which MuJoCo's inverse dynamics and moment arms alone {1e3 * ours_mujoco:.3f} ms per frame: a free "
          f"QP would be at most {theirs / ours_mujoco:.0f}x / {plain / ours_mujoco:.0f}x faster than the two SLSQPs\n"
          f"  {hundredfold(ours, theirs, plain, ours_mujoco)}\n"
          f"  MuJoCo forward check on {len(error)} ok frames: |qacc - requested| <= {error.max():.1e} rad/s^2; frames "
          f"with an excitation clipped to [0, 1]: {100 * clipped:.0f} %")
    return result


def thread_seconds(run) -> float:
    """This thread's CPU seconds for ``run()``: the work alone, whatever else the machine runs (every part here runs
    on one thread)."""
    import time

    start = time.thread_time()
    run()
    return time.thread_time() - start


def hundredfold(ours, theirs, plain, ours_mujoco) -> str:
    """The target's line: which SLSQP baseline ``inverse_dynamics`` beats 100x, and where it cannot, why (the MuJoCo
    part both sides pay bounds the ratio)."""
    lines = []
    for label, other in (("finite-difference SLSQP", plain), ("SLSQP with Jacobians", theirs)):
        ratio, ceiling = other / ours, other / ours_mujoco
        verdict = ("reached" if ratio >= 100 else
                   f"not reached, and cannot be: our MuJoCo part alone, {1e3 * ours_mujoco:.3f} of our "
                   f"{1e3 * ours:.3f} ms per frame, bounds it at {ceiling:.0f}x" if ceiling < 100 else
                   f"not reached: the QP and the rest, {1e3 * (ours - ours_mujoco):.3f} ms, would have to fall to "
                   f"{1e3 * (other / 100 - ours_mujoco):.3f} (ceiling {ceiling:.0f}x)")
        lines.append(f"{ratio:.0f}x vs {label}: {verdict}")
    return "100x target: " + "; ".join(lines)


def differentiator_accuracy():
    """The Savitzky-Golay differentiator's default on q = 0.5 sin(2 pi t) over 2 s, 2 ms frames, with and without
    1e-5 rad noise, beside the second difference on the noisy positions."""
    from lightning_bodyschema.statics.differentiate import differentiate

    t = np.arange(0.0, 2.0 + 1e-9, 0.002)
    w = 2 * np.pi
    q = 0.5 * np.sin(w * t)[:, None]
    noisy = q + 1e-5 * np.random.default_rng(0).standard_normal(q.shape)
    qvel, qacc = differentiate(t, q)
    acc_noisy = differentiate(t, noisy)[1]
    second = np.diff(noisy[:, 0], 2) / 0.002 ** 2
    exact_acc = -0.5 * w ** 2 * np.sin(w * t)
    print(f"\nSavitzky-Golay (0.05 s, degree 3) on 0.5 sin(2 pi t), 2 ms frames: velocity error "
          f"{np.abs(qvel[:, 0] - 0.5 * w * np.cos(w * t)).max():.1e} rad/s, acceleration error "
          f"{np.abs(qacc[:, 0] - exact_acc).max():.3f} rad/s^2 (peak {0.5 * w ** 2:.1f}); with 1e-5 rad noise "
          f"{np.abs(acc_noisy[:, 0] - exact_acc).max():.3f} (second difference: "
          f"{np.abs(second - exact_acc[1:-1]).max():.1f})")


def plot_motion(body, result, path):
    from lightning_bodyschema.apps.motion_opt import plot_activations

    plot_activations(result, path)
    print(f"wrote {path}")


def motion_main(args):
    from lightning_bodyschema.statics.track import track_motion

    differentiator_accuracy()
    for name, build in bodies().items():
        if name not in args.bodies:
            continue
        body = build()
        motion = reach(body) if name == "myoArm" else squat(body, args.frames)
        result = bench_motion(name, body, motion, args.slsqp_frames, args.repeats)
        if name == "myoLegs":
            bench_floating(body, motion, args.repeats)
        if name == "myoArm":
            print("  " + track_motion(body, *motion).summary())
            if args.plot:
                plot_motion(body, result, args.plot)


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--n", type=int, default=2000)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--singles", type=int, default=30)
    parser.add_argument("--plot", help="write the README's trajectory figure (myoArm) to this path")
    parser.add_argument("--bodies", nargs="+", choices=["myoArm", "myoLegs"], default=["myoArm", "myoLegs"])
    parser.add_argument("--motion", action="store_true", help="inverse dynamics on the held-out motions (issue 50)")
    parser.add_argument("--frames", type=int, default=10000, help="--motion: frames of the myoLegs squat")
    parser.add_argument("--slsqp-frames", type=int, default=50, help="--motion: frames of the per-frame SLSQP")
    args = parser.parse_args()
    torch.set_num_threads(1)
    if args.motion:
        return motion_main(args)
    cuts = {"myoArm": "BIClong_tendon", "myoLegs": "soleus_r_tendon"}
    for name, build in bodies().items():
        if name not in args.bodies:
            continue
        body = build()
        result = bench(name, body, args.n, args.repeats, args.singles, cuts[name])
        if name == "myoArm":
            sample = result.take(np.flatnonzero(result.ok)[:50])
            residual, miss = mujoco_residual_nm(body, sample)
            print(f"  MuJoCo check on {len(sample.q)} ok postures: max residual {np.max(residual):.2e} N m, "
                  f"max tension miss {np.max(miss):.2e} N")
            worst, median, solved, rows = proxsuite_gap_n(body, result)
            print(f"  proxsuite alone (eps 1e-13) on the {rows} ok postures: solved {solved}, tensions differ by "
                  f"{worst:.2e} N at most (median {median:.1e} N)")
            if args.plot:
                plot(body, args.plot, cuts[name])


if __name__ == "__main__":
    main()
