#!/usr/bin/env python
"""Does an exported package answer as the Python adapter of the checkpoint it came from? Mixed cut/jam cases.

    python tools/check_package.py --ckpt CKPT --package runs/adapter.pt2 [--cases 500] [--seed 0]

Draws ``--cases`` postures inside the joint ranges, each with one cut muscle and (seven cases in ten) a jammed one,
its ``l_fixed`` 6 mm below to 3 mm above the learned or healthy length there (binding and not), and compares the
package (``load_exported``) with ``schema.adapter(faults, check_physics=False)`` (diffusion: the package's steps):
prints the statuses of each, how many agree, and the largest difference of the ok rows [m, N], once per program
the package holds: a dynamic package answers all cases in one call (its dynamic program) and one case per call
(its batch-1 program, ``"programs": "dynamic,1"``); a static batch-1 package one case per call. Exits 1 when a
status differs or an ok row is off by more than 1e-5 m or 1e-2 N (the package's contract), 2 on bad input.
"""
import sys

import numpy as np

from lightning_bodyschema.apps.common import argument_parser, exits_cleanly, load_checked_schema, torch_one_thread
from lightning_bodyschema.errors import BodySchemaInputError

TOL_M, TOL_N = 1e-5, 1e-2


def mixed_cases(schema, n: int, seed: int):
    """(q (n, N) [rad], Faults): one cut per case, a jam in seven of ten near the schema's healthy motor length."""
    from lightning_bodyschema.faults import Faults

    rng = np.random.default_rng(seed)
    lo, hi = np.asarray(schema.robot_model.q_range, float).T
    q = lo + (hi - lo) * rng.random((n, len(lo)))
    m = schema.n_muscles
    l_healthy = schema.infer(q)[0]
    cut, fix = np.zeros((n, m), bool), np.zeros((n, m), bool)
    i = rng.integers(0, m, n)
    cut[np.arange(n), i] = True
    jammed = np.flatnonzero(rng.random(n) < 0.7)
    fix[jammed, ((i + rng.integers(1, m, n)) % m)[jammed]] = True
    l_fixed = np.where(fix, l_healthy + rng.uniform(-0.006, 0.003, (n, m)), np.nan)
    return q, Faults(cut, fix, l_fixed).validate(m, schema.spring.f_max_n)


def counts(status) -> dict:
    names, number = np.unique([str(s) for s in status], return_counts=True)
    return dict(zip(names.tolist(), number.tolist()))


@exits_cleanly
def main(argv=None):
    parser = argument_parser("Compare an exported package with the Python adapter on mixed cut/jam cases.",
                             checkpoint=True)
    parser.add_argument("--ckpt", required=True, help="the checkpoint the package was exported from")
    parser.add_argument("--package", required=True, help="the package (tools/export_adapter.py)")
    parser.add_argument("--cases", type=int, default=500, help="cases (default 500)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the cases (default 0)")
    args = parser.parse_args(argv)
    if args.cases < 1:
        raise BodySchemaInputError(f"--cases {args.cases}: give at least 1")
    torch_one_thread()
    from lightning_bodyschema.deploy import load_exported

    schema = load_checked_schema(args)
    package = load_exported(args.package, schema.robot_model.muscle_names, schema.robot_model.joint_names)
    q, faults = mixed_cases(schema, args.cases, args.seed)
    options = {"n_steps": package.metadata["n_steps"]} if package.kind == "diffusion" else {}
    ref = schema.adapter(faults, check_physics=False, **options)(q)
    failed = False
    for key in package.programs:
        got = package(q, faults) if key == "dynamic" else _one_by_one(package, q, faults)
        same = got.status == ref.status
        ok = same & (got.status == "ok")
        dl = float(np.abs(got.l_motor_m[ok] - ref.l_motor_m[ok]).max(initial=0.0))
        df = float(np.abs(got.f_n[ok] - ref.f_n[ok]).max(initial=0.0))
        print(f"{package.kind} package, program for batch {key}, {args.cases} cases: package {counts(got.status)}, "
              f"python {counts(ref.status)}; {int(same.sum())}/{args.cases} statuses equal; ok rows: max |dl| "
              f"{dl:.3g} m, max |df| {df:.3g} N")
        failed |= not same.all() or dl > TOL_M or df > TOL_N
    if failed:
        sys.exit(1)


def _one_by_one(package, q, faults):
    """One call per case (a one-case call runs the package's batch-1 program)."""
    from lightning_bodyschema.adaptation.command import AdaptationResult

    rows = [package(q[i:i + 1], faults.take([i])) for i in range(len(q))]
    return AdaptationResult(np.concatenate([r.l_motor_m for r in rows]), np.concatenate([r.f_n for r in rows]),
                            np.concatenate([r.status for r in rows]), {})


if __name__ == "__main__":
    main()
