#!/usr/bin/env python
"""MuJoCo settle check speed on a config's robot: one thread vs several, side by side, same cases.

    python tools/bench_settle.py --config configs/myoarm-diff.yaml --n 32 --repeats 3
    python tools/bench_settle.py --config configs/diff.yaml --n 120 --repeats 3

Draws ``--n`` healthy equilibrium samples of the config's robot (data.model, data.locked_joints, data.muscles,
spring constants as the data module resolves them), lengthens every muscle's command by ``--offset-mm`` so the
arm has somewhere to go, and settles them with ``SettleParams(n_threads=1)`` and ``n_threads=--threads``,
alternating, ``--repeats`` times. Prints the medians, the ratio, the statuses, and whether both results are
byte-identical (they must be: a case's result does not depend on where it runs).
"""
import argparse
import os
import statistics
import time

import numpy as np

from lightning_bodyschema.apps.common import exits_cleanly, require_positive, robot_from_config

FIELDS = ("q_settle", "E_q_phys", "status", "time_s", "qvel_rad_s", "f_settle_n")


@exits_cleanly
def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", default="configs/myoarm-diff.yaml")
    parser.add_argument("--n", type=int, default=32)
    parser.add_argument("--threads", type=int, default=len(os.sched_getaffinity(0)))
    parser.add_argument("--offset-mm", type=float, default=1.0)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args(argv)
    require_positive(n=args.n, threads=args.threads, repeats=args.repeats)
    from lightning_bodyschema.sim import generate_equilibrium_samples
    from lightning_bodyschema.sim.settle import SettleParams, settle

    model, spring, data = robot_from_config(args.config)
    samples = generate_equilibrium_samples(model, args.n, int(data.get("seed", 0)), spring)
    command = (samples.l_motor + 1e-3 * args.offset_mm, samples.f, samples.q)
    print(f"robot {model.n_joints} free joints (nv {model.mj_model.nv}), {model.n_muscles} muscles; {args.n} cases")
    times, results = {1: [], args.threads: []}, {}
    for _ in range(args.repeats):
        for threads in times:
            start = time.perf_counter()
            results[threads] = settle(model, *command, spring=spring, params=SettleParams(n_threads=threads))
            times[threads].append(time.perf_counter() - start)
    med = {k: statistics.median(v) for k, v in times.items()}
    for threads, value in med.items():
        print(f"n_threads={threads}: median {value:.2f} s (runs {', '.join(f'{t:.2f}' for t in times[threads])})")
    one, many = results[1], results[args.threads]
    same = all(np.array_equal(getattr(one, f), getattr(many, f), equal_nan=True) for f in FIELDS)
    statuses = {str(k): int(v) for k, v in zip(*np.unique(one.status_names, return_counts=True))}
    print(f"speed-up {med[1] / med[args.threads]:.2f}x; statuses {statuses}; results byte-identical: {same}; "
          f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")


if __name__ == "__main__":
    main()
