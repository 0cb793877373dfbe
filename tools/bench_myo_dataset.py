#!/usr/bin/env python
"""Equilibrium dataset speed on a config's robot (e.g. myoArm), on 1, 2, ... worker processes.

    python tools/bench_myo_dataset.py --config configs/myoarm.yaml --n 20000 --workers 1 2 [--repeats 1]

Builds the config's robot once (data.model, data.locked_joints, data.muscles, spring constants as the data module
resolves them), then draws the dataset's ``--n`` samples (seed data.seed) with ``sim.sampling.generate_samples`` on
each ``--workers`` count (worker start-up included). Prints per count the median wall time and samples per second,
and the sha256 of the samples (the same for every count); then the accepted fraction, the largest torque residual
|-G^T f - tau_bias| in the free joints over every sample (recomputed with MuJoCo after the draw; the target is
<= 1e-6 N m) and the peak resident memory of this process and of its workers.
"""
import argparse
import hashlib
import os
import resource
import statistics
import time

import numpy as np

from lightning_bodyschema.apps.common import exits_cleanly, require_positive, robot_from_config


def _digest(samples) -> str:
    return hashlib.sha256(samples.q.tobytes() + samples.l_motor.tobytes() + samples.f.tobytes()).hexdigest()[:16]


def _time(model, spring, n, seed, workers, repeats):
    from lightning_bodyschema.sim.sampling import generate_samples

    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        samples = generate_samples(model, n, seed, spring, workers=workers, progress=False)
        times.append(time.perf_counter() - start)
    return samples, times


@exits_cleanly
def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", default="configs/myoarm.yaml")
    parser.add_argument("--n", type=int, default=20_000)
    parser.add_argument("--workers", "--processes", type=int, nargs="+", default=[1, 2],
                        help="worker counts to time (--processes: its earlier name)")
    parser.add_argument("--repeats", type=int, default=1)
    args = parser.parse_args(argv)
    require_positive(n=args.n, repeats=args.repeats, workers=min(args.workers))
    start = time.perf_counter()
    model, spring, data = robot_from_config(args.config)
    seed = int(data.get("seed", 0))
    print(f"robot {model.n_joints} free joints, {model.n_muscles} muscles; "
          f"built in {time.perf_counter() - start:.1f} s")
    for workers in args.workers:
        samples, times = _time(model, spring, args.n, seed, workers, args.repeats)
        wall = statistics.median(times)
        runs = ", ".join(f"{t:.1f}" for t in times)
        print(f"{args.n} samples on {workers} worker(s): median {wall:.1f} s (runs {runs}), {args.n / wall:.0f} "
              f"samples/s; sha256 {_digest(samples)}; load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    _, G, tau = model.kinematics(samples.q)
    residual = np.abs(np.einsum("bmn,bm->bn", -G, samples.f) - tau).max()
    rss_mb = {who: resource.getrusage(flag).ru_maxrss / 1024 for who, flag in
              (("this process", resource.RUSAGE_SELF), ("largest worker", resource.RUSAGE_CHILDREN))}
    print(f"accepted fraction {samples.accepted_fraction:.4f}; max torque residual in the free joints "
          f"{residual:.2e} N m; peak memory: " + ", ".join(f"{who} {mb:.0f} MB" for who, mb in rss_mb.items()))


if __name__ == "__main__":
    main()
