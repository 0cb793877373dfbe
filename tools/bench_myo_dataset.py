#!/usr/bin/env python
"""Equilibrium dataset speed on a config's robot (e.g. myoArm), in parallel processes.

    python tools/bench_myo_dataset.py --config configs/myoarm-diff.yaml --n 100000 --processes 2 [--repeats 1]

Builds the config's robot once (data.model, data.locked_joints, data.muscles, spring constants as the
data module resolves them), then draws ``--n`` samples split over ``--processes`` worker processes (chunk
i seeded seed + i), each rebuilding the robot from its self-contained XML. Prints the median wall time,
the accepted fraction, and the largest torque residual |-G^T f - tau_bias| in the free joints over every
sample (recomputed with MuJoCo after the draw; the target is <= 1e-6 N m).
"""
import argparse
import multiprocessing
import os
import statistics
import time

import numpy as np

from lightning_bodyschema.apps.common import exits_cleanly, require_positive, robot_from_config


def _chunk(args):
    xml, muscles, spring_dict, n, seed = args
    import torch  # noqa: F401  (imported by the package anyway; keep one thread per worker)
    from lightning_bodyschema.sim import MusculoskeletalModel, SpringParams, generate_equilibrium_samples

    torch.set_num_threads(1)
    model = MusculoskeletalModel(xml, muscles=muscles)
    spring = SpringParams(**spring_dict)
    samples = generate_equilibrium_samples(model, n, seed, spring)
    _, G, tau = model.kinematics(samples.q)
    residual = np.abs(np.einsum("bmn,bm->bn", -G, samples.f) - tau).max()
    return len(samples.q), samples.n_redrawn, float(residual)


@exits_cleanly
def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", default="configs/myoarm-diff.yaml")
    parser.add_argument("--n", type=int, default=100_000)
    parser.add_argument("--processes", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=1)
    args = parser.parse_args(argv)
    require_positive(n=args.n, processes=args.processes, repeats=args.repeats)
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    start = time.perf_counter()
    model, spring, data = robot_from_config(args.config)
    print(f"robot {model.n_joints} free joints {model.joint_names}, {model.n_muscles} muscles; "
          f"built in {time.perf_counter() - start:.1f} s")
    sizes = np.diff(np.linspace(0, args.n, args.processes + 1).astype(int))
    jobs = [(model.xml, model.muscle_names, spring.as_dict(), int(k), int(data.get("seed", 0)) + i)
            for i, k in enumerate(sizes)]
    times = []
    for _ in range(args.repeats):
        start = time.perf_counter()
        with multiprocessing.get_context("fork").Pool(args.processes) as pool:
            results = pool.map(_chunk, jobs)
        times.append(time.perf_counter() - start)
    kept = sum(r[0] for r in results)
    redrawn = sum(r[1] for r in results)
    print(f"{kept} samples in {args.processes} processes: median {statistics.median(times):.1f} s "
          f"(runs {', '.join(f'{t:.1f}' for t in times)}; includes the residual re-check); accepted fraction "
          f"{kept / (kept + redrawn):.4f}; max torque residual in the free joints {max(r[2] for r in results):.2e} N m; "
          f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")


if __name__ == "__main__":
    main()
