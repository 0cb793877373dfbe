#!/usr/bin/env python
"""Equilibrium dataset speed on a config's robot (e.g. myoArm), on 1, 2, ... worker processes.

    python tools/bench_myo_dataset.py --config configs/myoarm.yaml --n 20000 --workers 1 2 [--repeats 1]

Builds the config's robot once (data.model, data.locked_joints, data.muscles, spring constants as the data module
resolves them), then draws the dataset's ``--n`` samples (seed data.seed) with ``sim.sampling.generate_samples`` on
each ``--workers`` count (worker start-up included). Prints per count the median wall time, samples per second, the
CPU time of this process and its workers, the sha256 of the samples (the same for every count) and the peak resident
memory of this process so far; with ``--out``, the time to write the file; then the accepted fraction and the largest
torque residual |-G^T f - tau_bias| in the free joints, recomputed with MuJoCo after the draw on every sample (on
about 20000 evenly spread ones past that; the target is <= 1e-6 N m).
"""
import argparse
import hashlib
import os
import resource
import statistics
import time

import numpy as np

from lightning_bodyschema.apps.common import exits_cleanly, require_positive, robot_from_config

CHECKED = 20_000  # samples whose residual is recomputed: all of a dataset up to this size, else evenly spread


def _digest(samples) -> str:
    """sha256 of q, l_motor and f one after the other, hashed from the arrays' own memory (no copy)."""
    digest = hashlib.sha256()
    for array in (samples.q, samples.l_motor, samples.f):
        digest.update(array)
    return digest.hexdigest()[:16]


def _cpu_s() -> float:
    """User + system CPU seconds of this process and of its finished workers."""
    return sum(r.ru_utime + r.ru_stime for r in map(resource.getrusage, (resource.RUSAGE_SELF,
                                                                         resource.RUSAGE_CHILDREN)))


def _time(model, spring, n, seed, workers, repeats):
    from lightning_bodyschema.sim.sampling import generate_samples

    times, cpu = [], []
    for _ in range(repeats):
        start, start_cpu = time.perf_counter(), _cpu_s()
        samples = generate_samples(model, n, seed, spring, workers=workers, progress=False)
        times.append(time.perf_counter() - start)
        cpu.append(_cpu_s() - start_cpu)
    return samples, times, statistics.median(cpu)


def _peak_memory() -> str:
    """This process's peak resident memory (a worker's own is not visible here: its fork before exec counts)."""
    return f"{resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB"


def _save(path, samples) -> None:
    from lightning_bodyschema.npz import save_npz

    start = time.perf_counter()
    save_npz(path, q=samples.q, l_motor=samples.l_motor, f=samples.f)
    print(f"wrote {path} ({os.path.getsize(path) / 1e6:.0f} MB) in {time.perf_counter() - start:.1f} s; "
          f"peak memory: {_peak_memory()}")


def _residual(model, q, f) -> float:
    _, G, tau = model.kinematics(q)
    return float(np.abs(np.einsum("bmn,bm->bn", -G, f) - tau).max())


@exits_cleanly
def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", default="configs/myoarm.yaml")
    parser.add_argument("--n", type=int, default=20_000)
    parser.add_argument("--workers", "--processes", type=int, nargs="+", default=[1, 2],
                        help="worker counts to time (--processes: its earlier name)")
    parser.add_argument("--repeats", type=int, default=1)
    parser.add_argument("--out", help="also write the last draw as an .npz (q, l_motor, f) and time that")
    args = parser.parse_args(argv)
    require_positive(n=args.n, repeats=args.repeats, workers=min(args.workers))
    start = time.perf_counter()
    model, spring, data = robot_from_config(args.config)
    seed = int(data.get("seed", 0))
    print(f"robot {model.n_joints} free joints, {model.n_muscles} muscles; "
          f"built in {time.perf_counter() - start:.1f} s")
    for workers in args.workers:
        samples, times, cpu_s = _time(model, spring, args.n, seed, workers, args.repeats)
        wall = statistics.median(times)
        runs = ", ".join(f"{t:.1f}" for t in times)
        print(f"{args.n} samples on {workers} worker(s): median {wall:.1f} s (runs {runs}), {args.n / wall:.0f} "
              f"samples/s, CPU {cpu_s:.1f} s; sha256 {_digest(samples)}; load average {os.getloadavg()[0]:.1f} on "
              f"{os.cpu_count()} cores; peak memory: {_peak_memory()}")
    if args.out:
        _save(args.out, samples)
    rows = np.arange(0, args.n, max(1, args.n // CHECKED))  # every chunk's rows are among them
    residual = max(_residual(model, samples.q[part], samples.f[part])
                   for part in np.array_split(rows, len(rows) // 5000 + 1))
    print(f"accepted fraction {samples.accepted_fraction:.4f}; max torque residual in the free joints "
          f"{residual:.2e} N m over {len(rows)} samples")


if __name__ == "__main__":
    main()
