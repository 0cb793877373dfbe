#!/usr/bin/env python
"""Dataset generation speed: MuJoCo kinematics + one proxsuite QP per posture, paper arm.

    python tools/bench_dataset.py [--repeats 3]

Prints the median wall time for 800 and 100,000 samples (targets: < 1 s and < 10 s) and the split
between MuJoCo kinematics and the QPs.
"""
import argparse
import statistics
import time

import numpy as np

from lightning_bodyschema.sim import MusculoskeletalModel, SpringParams, generate_equilibrium_samples, solve_equilibrium_qp


def _median_time(fn, repeats):
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times), times


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    model = MusculoskeletalModel("paper_arm")
    for n, target in ((800, 1.0), (100_000, 10.0)):
        med, runs = _median_time(lambda: generate_equilibrium_samples(model, n, seed=0), args.repeats)
        print(f"{n:7d} samples: median {med:6.3f} s (runs {', '.join(f'{t:.3f}' for t in runs)}); "
              f"target < {target:g} s: {'met' if med < target else 'MISSED'}")
    q = model.sample_q(np.random.default_rng(0), 100_000)
    kin, _ = _median_time(lambda: model.kinematics(q), args.repeats)
    _, G, tau = model.kinematics(q)
    f_ref = 150.0 * np.random.default_rng(1).random((len(q), model.n_muscles))
    qp, _ = _median_time(lambda: solve_equilibrium_qp(G, tau, f_ref, f_hi_n=SpringParams().f_max_n), args.repeats)
    print(f"100000 postures: MuJoCo kinematics {kin:.3f} s ({1e6 * kin / len(q):.1f} us each), "
          f"QPs {qp:.3f} s ({1e6 * qp / len(q):.1f} us each)")


if __name__ == "__main__":
    main()
