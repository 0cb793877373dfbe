#!/usr/bin/env python
"""One markdown row per trained checkpoint: how well it learned its body and how well it adapts (no settle runs).

    python tools/bench_body_table.py --ckpt plain=runs/a/last.ckpt --ckpt residual=runs/b/last.ckpt \
        [--fit-seconds plain=1130 --fit-seconds residual=1190] [--postures 2000] [--n-per-condition 20]

Columns, each a median: the healthy commands' equilibrium residual ||-G^T f - tau_bias|| [N m] at the first
``--postures`` validation postures and its ratio to the median ||tau_bias|| there (issue target <= 0.05), their
length residual |l_motor + delta(f) - l_geo| [mm]; for a structured schema the learned body's errors against
MuJoCo (l_geo [mm], moment arms [mm/rad], torque [N m]); the binding protocol's adapted and unadapted E_q [rad]
and E_tau [N m] per condition (the Gauss-Newton evaluator's phys reading, feasible cases); with ``--settle`` also
E_q_phys, each command dropped into MuJoCo (``sim.settle``: every fault kind, as the posture solve models them,
with the spring's own stiffness); and the fit's wall time when given. One torch thread.
"""
import argparse

import numpy as np
import torch

from lightning_bodyschema.apps.common import add_device_argument, exits_cleanly
from lightning_bodyschema.errors import BodySchemaInputError


def _labelled(pairs, what):
    out = {}
    for pair in pairs or ():
        label, sep, value = pair.partition("=")
        if not sep or not label or not value:
            raise BodySchemaInputError(f"{what} {pair!r}: expected LABEL=VALUE")
        out[label] = value
    return out


def healthy_row(schema, q, x) -> dict:
    """Healthy residuals at ``q`` and, for a schema with ``body_si``, its learned body's errors against MuJoCo."""
    errors = schema.physical_errors(q, x)
    l_geo, G, tau = schema.robot_model.kinematics(q.numpy())
    row = {"eq_nm": errors["eq_residual_N_m"], "ratio": errors["eq_residual_N_m"] /
           float(np.median(np.linalg.norm(tau, axis=1))), "length_mm": errors["length_residual_mm"]}
    if hasattr(schema, "body_si"):
        l_hat, G_hat, tau_hat = schema.body_si(q)
        row.update(l_geo_mm=1e3 * float(np.median(np.abs(l_hat - l_geo))),
                   arm_mm=1e3 * float(np.median(np.abs(G_hat - G))),
                   tau_nm=float(np.median(np.linalg.norm(tau_hat - tau, axis=1))))
    return row


def binding_row(schema, q, x, n_per_condition: int, settle: bool = False) -> dict:
    """Median E_q [rad] and E_tau [N m] (then E_q_phys with ``settle``) of adapted and unadapted commands, binding
    protocol, phys reading, feasible cases."""
    from lightning_bodyschema.evaluation.benchmark import run_fault_benchmark
    from lightning_bodyschema.evaluation.cases import HealthyPool, make_binding_cases

    m = schema.n_muscles
    pool = HealthyPool(q.numpy(), x[:, :m].numpy(), x[:, m:2 * m].numpy())
    cases = make_binding_cases(schema.robot_model, pool, n_per_condition, 0, schema.spring)[0]
    result = run_fault_benchmark(schema.robot_model, schema.spring, cases, schema.infer,
                                 lambda qq, ff: schema.adapt(qq, ff, check_physics=False), oracle=False,
                                 settle_check=settle)
    summary = result.summary()
    metrics = ("E_q", "E_tau") + (("E_q_phys", "n_unsettled") if settle else ())  # settle runs never at rest: apart
    return {cond: tuple(summary[kind]["phys"][cond]["feasible"][metric] for metric in metrics
                        for kind in ("adapted", "unadapted")) for cond in summary["adapted"]["phys"]}


def _pairs(by_cond: dict, first: int) -> str:
    """``COND a / u`` for every condition: adapted and unadapted medians."""
    return "; ".join(f"{cond} {_fmt(v[first])} / {_fmt(v[first + 1])}" for cond, v in by_cond.items())


def _fmt(value, digits=3):
    return "—" if value is None else f"{value:.{digits}g}"


@exits_cleanly
def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ckpt", action="append", required=True, help="LABEL=PATH (repeat)")
    parser.add_argument("--fit-seconds", action="append", help="LABEL=SECONDS: the fit's wall time (repeat)")
    parser.add_argument("--postures", type=int, default=2000)
    parser.add_argument("--n-per-condition", type=int, default=20)
    parser.add_argument("--cache-dir", default="runs/cache", help="the fits' data.cache_dir (default: runs/cache)")
    parser.add_argument("--settle", action="store_true",
                        help="also E_q_phys: every binding command dropped into MuJoCo (sim.settle)")
    add_device_argument(parser)
    args = parser.parse_args(argv)
    ckpts, seconds = _labelled(args.ckpt, "--ckpt"), _labelled(args.fit_seconds, "--fit-seconds")
    torch.set_num_threads(1)
    torch.set_flush_denormal(True)
    from lightning_bodyschema.schemas.loading import load_datamodule, load_schema

    print("| choice | eq residual [N m] | ratio | length [mm] | l_geo [mm] | arms [mm/rad] | torque [N m] | "
          "binding E_q adapted / unadapted [rad] | binding E_tau adapted / unadapted [N m] | "
          + ("binding E_q_phys adapted / unadapted [rad] | " if args.settle else "") + "fit [s] |")
    print("|---" * (11 if args.settle else 10) + "|")
    for label, path in ckpts.items():
        schema = load_schema(path, map_location=args.device).eval()
        datamodule = load_datamodule(path, cache_dir=args.cache_dir)
        datamodule.setup("test")
        q, x = datamodule.splits["val"]
        h = healthy_row(schema, q[:args.postures], x[:args.postures])
        b = binding_row(schema, q, x, args.n_per_condition, args.settle)
        settled = f"{_pairs(b, 4)}; runs not at rest (left out) {_pairs(b, 6)} | " if args.settle else ""
        print(f"| {label} | {_fmt(h['eq_nm'])} | {_fmt(h['ratio'])} | {_fmt(h['length_mm'])} | "
              f"{_fmt(h.get('l_geo_mm'))} | {_fmt(h.get('arm_mm'))} | {_fmt(h.get('tau_nm'))} | "
              f"{_pairs(b, 0)} | {_pairs(b, 2)} | {settled}{seconds.get(label, '—')} |", flush=True)


if __name__ == "__main__":
    main()
