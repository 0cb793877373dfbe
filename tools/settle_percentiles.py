#!/usr/bin/env python
"""E_q_phys per fault condition, its median, p90 and max: the binding protocol's adapted commands dropped into MuJoCo.

    python tools/settle_percentiles.py --ckpt runs/myolegs/.../last.ckpt [--n-per-condition 40] [--cache-dir runs/cache]
                                       [--healthy 120] [--healthy-seed 12345]

The checkpoint's validation split is the pool of healthy postures; ``make_binding_cases`` (seed 0) draws
``--n-per-condition`` cases per condition; each adapted command (``schema.adapt``, no physics check) is scored by the
fault benchmark with ``settle_check`` (``sim.settle``: one MuJoCo simulation per command). Per condition: the feasible
cases, those that came to rest (a run still moving is counted apart, never scored) and E_q_phys median / p90 / max
[mrad] over those. ``--healthy N``: first a HEALTHY row, N fresh equilibrium postures (``generate_equilibrium_samples``
with ``--healthy-seed``, postures none of the data holds), the healthy command (``solve_si``; its rows whose status
is not ``ok`` counted apart) dropped into MuJoCo, with the postures the adapter flags at a path switch
(``path_switches``) counted and scored apart. ``tools/bench_body_table.py --settle`` prints the medians beside the
rest of a checkpoint's row.
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
    parser.add_argument("--healthy", type=int, default=0, help="healthy held-out postures to settle first (0: none)")
    parser.add_argument("--healthy-seed", type=int, default=12345)
    parser.add_argument("--cache-dir", default="runs/cache", help="the fit's data.cache_dir (default: runs/cache)")
    args = parser.parse_args(argv)
    if args.n_per_condition < 1 or args.healthy < 0:
        raise BodySchemaInputError(f"--n-per-condition {args.n_per_condition} must be >= 1 and --healthy "
                                   f"{args.healthy} >= 0")
    torch.set_num_threads(1)
    from lightning_bodyschema.evaluation.benchmark import run_fault_benchmark
    from lightning_bodyschema.evaluation.cases import HealthyPool, make_binding_cases
    from lightning_bodyschema.schemas.loading import load_datamodule, load_schema

    schema = load_schema(args.ckpt).eval()
    if args.healthy:
        healthy_row(schema, args.healthy, args.healthy_seed)
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


def mrad(values: np.ndarray) -> str:
    """``median / p90 / max`` [mrad] of radians, or ``-``."""
    return " / ".join(f"{v:.3f}" for v in 1e3 * np.percentile(values, [50, 90, 100])) if len(values) else "-"


def healthy_row(schema, n: int, seed: int) -> None:
    """The HEALTHY table (module docstring)."""
    from lightning_bodyschema.sim.equilibrium import generate_equilibrium_samples
    from lightning_bodyschema.sim.settle import settle
    from lightning_bodyschema.status import Status

    q_ref = generate_equilibrium_samples(schema.robot_model, n, seed, schema.spring).q
    l_motor, f, status = schema.solve_si(torch.as_tensor(q_ref))
    ok = np.array([s == Status.OK for s in status])
    flagged = schema.path_switches(q_ref)["near_path_switch"]
    result = settle(schema.robot_model, l_motor[ok], f[ok], q_ref[ok], spring=schema.spring)
    rest = result.E_q_rest
    print("| healthy | postures | ok | at rest | flagged | E_q_phys median / p90 / max [mrad] | unflagged |\n"
          "|---|---|---|---|---|---|---|")
    kept = flagged[ok]
    print(f"| HEALTHY | {n} | {int(ok.sum())} | {int(np.isfinite(rest).sum())} | {int(flagged.sum())} | "
          f"{mrad(rest[np.isfinite(rest)])} | {mrad(rest[np.isfinite(rest) & ~kept])} |\n")


if __name__ == "__main__":
    main()
