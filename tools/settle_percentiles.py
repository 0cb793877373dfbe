#!/usr/bin/env python
"""E_q_phys per fault condition, its median, p90 and max: the binding protocol's adapted commands dropped into MuJoCo.

    python tools/settle_percentiles.py --ckpt runs/myolegs/.../last.ckpt [--n-per-condition 40] [--cache-dir runs/cache]

The checkpoint's validation split is the pool of healthy postures; ``make_binding_cases`` (seed 0) draws
``--n-per-condition`` cases per condition; each adapted command (``schema.adapt``, no physics check) is scored by the
fault benchmark with ``settle_check`` (``sim.settle``: one MuJoCo simulation per command). Per condition: the feasible
cases, those that came to rest (a run still moving is counted apart, never scored) and E_q_phys median / p90 / max
[mrad] over those. ``tools/bench_body_table.py --settle`` prints the medians beside the rest of a checkpoint's row.
One torch thread.
"""
import argparse

import numpy as np
import torch

from lightning_bodyschema.apps.common import exits_cleanly
from lightning_bodyschema.errors import BodySchemaInputError


@exits_cleanly
def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--ckpt", required=True, help="a trained checkpoint (.ckpt)")
    parser.add_argument("--n-per-condition", type=int, default=40)
    parser.add_argument("--cache-dir", default="runs/cache", help="the fit's data.cache_dir (default: runs/cache)")
    args = parser.parse_args(argv)
    if args.n_per_condition < 1:
        raise BodySchemaInputError(f"--n-per-condition {args.n_per_condition}: must be >= 1")
    torch.set_num_threads(1)
    from lightning_bodyschema.evaluation.benchmark import run_fault_benchmark
    from lightning_bodyschema.evaluation.cases import HealthyPool, make_binding_cases
    from lightning_bodyschema.schemas.loading import load_datamodule, load_schema

    schema = load_schema(args.ckpt).eval()
    datamodule = load_datamodule(args.ckpt, cache_dir=args.cache_dir)
    datamodule.setup("test")
    q, x = datamodule.splits["val"]
    m = schema.n_muscles
    pool = HealthyPool(q.numpy(), x[:, :m].numpy(), x[:, m:2 * m].numpy())
    cases = make_binding_cases(schema.robot_model, pool, args.n_per_condition, 0, schema.spring)[0]
    result = run_fault_benchmark(schema.robot_model, schema.spring, cases, schema.infer,
                                 lambda qq, ff: schema.adapt(qq, ff, check_physics=False), oracle=False,
                                 settle_check=True)
    e_q_phys, feasible = result.metrics["adapted"]["phys"]["E_q_phys"], result.feasible["phys"]
    print("| condition | feasible | at rest | E_q_phys median / p90 / max [mrad] |\n|---|---|---|---|")
    for cond in np.unique(cases.cond):
        scored = e_q_phys[(cases.cond == cond) & feasible]
        rest = scored[np.isfinite(scored)]  # NaN: the run never came to rest
        figures = " / ".join(f"{v:.3f}" for v in 1e3 * np.percentile(rest, [50, 90, 100])) if len(rest) else "-"
        print(f"| {cond} | {len(scored)} | {len(rest)} | {figures} |")


if __name__ == "__main__":
    main()
