#!/usr/bin/env python
"""Issue-15 targets of a trained checkpoint: healthy accuracy at its test postures and prepared-adapter latency.

    python tools/bench_myo_targets.py --ckpt CKPT --cases cases.npz [--steps 20] [--repeats 9] [--compiled]

Prints (1) the median equilibrium residual ||-G^T f - tau_bias|| of the healthy commands at the test split, the
median ||tau_bias|| there and their ratio (target <= 5 %), and the median length residual (target <= 1 mm);
(2) the median time per case of a prepared ``--steps``-step adapter (``schema.adapter(faults)(q)``, no physics
check) on the BOTH cases of ``--cases`` at batch 1 and batch 4000 (cases repeated), one torch thread; with
``--compiled`` also through ``torch.compile`` (the sampler's ``compiled=True``, as BENCHMARKS.md's "Diff-fast
prepared+compiled"; the first call per batch size compiles and is not timed).
Timings depend on the machine's load: the load average and the CPU time per case are printed with them.
"""
import argparse
import os
import statistics
import time

import numpy as np
import torch

from lightning_bodyschema.apps.common import add_device_argument, exits_cleanly
from lightning_bodyschema.errors import BodySchemaInputError


def healthy(schema, ckpt):
    from lightning_bodyschema.schemas.loading import load_datamodule

    datamodule = load_datamodule(ckpt)
    datamodule.setup("test")
    q, x = datamodule.splits["val"]
    errors = schema.physical_errors(q, x)
    tau = schema.robot_model.kinematics(q.numpy())[2]
    median_tau = float(np.median(np.linalg.norm(tau, axis=1)))
    print(f"healthy at {len(q)} test postures: median eq residual {errors['eq_residual_N_m']:.4g} N m, median "
          f"|tau_bias| {median_tau:.4g} N m, ratio {errors['eq_residual_N_m'] / median_tau:.3f} (target <= 0.05); "
          f"median length residual {errors['length_residual_mm']:.4g} mm (target <= 1)")


def latency(schema, cases, steps, repeats, compiled=False):
    from lightning_bodyschema.faults import Faults

    schema.hparams.sample_steps = steps
    both = np.flatnonzero(np.array([str(c) == "BOTH" for c in cases["cond"]]))
    kind = "prepared+compiled" if compiled else "prepared"
    for n, inner in ((1, 20), (4000, 1)):
        idx = np.resize(both, n)
        adapter = schema.adapter(Faults(cases["cut"][idx], cases["fix"][idx], cases["l_fixed"][idx]),
                                 check_physics=False, compiled=compiled)
        q = cases["q_ref"][idx]
        adapter(q)  # warm-up (and, compiled, the compilation)
        times, cpu = [], []
        for _ in range(repeats):
            start, start_cpu = time.perf_counter(), time.process_time()
            for _ in range(inner):
                adapter(q)
            times.append((time.perf_counter() - start) / inner / n)
            cpu.append((time.process_time() - start_cpu) / inner / n)
        print(f"{kind} {steps}-step adapter, batch {n}: median {1e3 * statistics.median(times):.3f} ms per case "
              f"(CPU {1e3 * statistics.median(cpu):.3f} ms; load average {os.getloadavg()[0]:.1f} on "
              f"{os.cpu_count()} cores)")


@exits_cleanly
def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ckpt", required=True)
    parser.add_argument("--cases", required=True, help="a tools/make_cases.py file of this checkpoint")
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--repeats", type=int, default=9)
    parser.add_argument("--compiled", action="store_true", help="also time the torch.compile'd sampler")
    add_device_argument(parser)
    args = parser.parse_args(argv)
    if not os.path.isfile(args.cases):
        raise BodySchemaInputError(f"--cases {args.cases!r} does not exist; give a tools/make_cases.py file (.npz)")
    torch.set_num_threads(1)
    torch.set_flush_denormal(True)
    from lightning_bodyschema.schemas.loading import load_schema

    schema = load_schema(args.ckpt, map_location=args.device)
    schema.eval()
    healthy(schema, args.ckpt)
    cases = np.load(args.cases)
    latency(schema, cases, args.steps, args.repeats)
    if args.compiled:
        latency(schema, cases, args.steps, args.repeats, compiled=True)


if __name__ == "__main__":
    main()
