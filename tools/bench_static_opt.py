#!/usr/bin/env python
"""Static optimization speed and checks on myoArm and myoLegs (issue 34), and the README's trajectory figure.

    python tools/bench_static_opt.py --n 2000 --repeats 3 [--bodies myoArm myoLegs] [--plot docs/static_opt.png]

Per body: the median time per posture of ``StaticBody.solve`` on ``--n`` seeded postures in one batch, of one
posture at a time (``--singles`` calls), and side by side the MuJoCo kinematics alone and the dataset's equilibrium
QP (``sim.equilibrium.solve_equilibrium_qp``, f_ref uniform in [0, f_max]) on the same postures; the status counts;
on myoArm the largest MuJoCo residual (``statics.check.mujoco_residual_nm``) of a sample of ok rows. The machine's
load average is printed with the timings: they depend on it. One torch thread.
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


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--n", type=int, default=2000)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--singles", type=int, default=30)
    parser.add_argument("--plot", help="write the README's trajectory figure (myoArm) to this path")
    parser.add_argument("--bodies", nargs="+", choices=["myoArm", "myoLegs"], default=["myoArm", "myoLegs"])
    args = parser.parse_args()
    torch.set_num_threads(1)
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
