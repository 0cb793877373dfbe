"""``tools/guidance_study.py``: adaptation variants side by side on one case set, physical reading, medians.

Each variant adapts every case in one batch; the commands are scored by the evaluator with the physical reading
(a jammed winch reels in but never pays out) and dropped into MuJoCo (E_q_phys). Beside each median: the paired
bootstrap 95 % interval of its difference to the first variant's (same cases), so "worse" can be told from noise.
"""
from __future__ import annotations

import json
import time

import numpy as np

from .common import argument_parser, check_out, exits_cleanly, load_checked_schema, torch_one_thread

METRICS = ("E_cut", "E_fix", "E_weak", "E_band", "E_tau", "E_q", "E_q_phys")
CONDITIONS = ("CUT", "FIX", "BOTH", "WEAK", "BAND")


def draw(protocol: str, schema, datamodule, seeds, n_per_condition: int):
    """The cases of every seed, concatenated (paper: 40 per condition; binding: ``n_per_condition``)."""
    from ..evaluation.cases import FaultCases, HealthyPool, make_binding_cases, make_fault_cases

    q, x = (np.asarray(t) for t in datamodule.splits["val"])
    m = schema.n_muscles
    if protocol == "paper":
        parts = [make_fault_cases(q, x[:, :m], n_per_condition, s) for s in seeds]
    else:
        pool = HealthyPool(q, x[:, :m], x[:, m:])
        parts = [make_binding_cases(schema.robot_model, pool, n_per_condition, s, schema.spring)[0] for s in seeds]
    join = lambda k: None if getattr(parts[0], k) is None else np.concatenate([getattr(p, k) for p in parts])  # noqa: E731
    return FaultCases(*(join(k) for k in ("q_ref", "cut", "fix", "l_fixed", "cond", "f_max", "l_band")))


def score(schema, cases, l_motor, f) -> dict:
    """Per-case metrics of one command batch, physical reading, with E_q_phys from the settle check."""
    from ..evaluation.benchmark import settle_metrics
    from ..evaluation.forward_solver import ForwardSolverParams
    from ..evaluation.metrics import evaluate_commands
    from ..sim.settle import settle

    metrics = evaluate_commands(schema.robot_model, cases, l_motor, f, schema.spring,
                                ForwardSolverParams(jammed_tension_in_torque=True))
    # E_q_phys of the runs that came to rest; the others (still moving, blown up) NaN and in settle_unsettled
    metrics.update(settle_metrics(settle(schema.robot_model, l_motor, f, cases, spring=schema.spring)))
    return metrics


def paired_interval(a: np.ndarray, b: np.ndarray, rng, n_boot: int = 1000) -> tuple[float, float]:
    """95 % bootstrap interval of median(a) - median(b) over paired cases (finite pairs only)."""
    ok = np.isfinite(a) & np.isfinite(b)
    a, b = a[ok], b[ok]
    if not a.size:
        return float("nan"), float("nan")
    idx = rng.integers(0, a.size, (n_boot, a.size))
    diffs = np.median(a[idx], axis=1) - np.median(b[idx], axis=1)
    return tuple(float(v) for v in np.percentile(diffs, [2.5, 97.5]))


def table(cases, runs: dict, keep=None, seed: int = 0) -> list[dict]:
    """One row per (variant, condition): n, medians, and E_tau / E_q intervals against the first variant, over the
    cases in ``keep`` (default all)."""
    rng, first = np.random.default_rng(seed), next(iter(runs.values()))["metrics"]
    keep = np.ones(len(cases.cond), bool) if keep is None else keep
    rows = []
    for name, run in runs.items():
        for cond in CONDITIONS:
            sel = (cases.cond == cond) & keep
            if not sel.any():
                continue
            row = {"variant": name, "condition": cond, "n": int(sel.sum()), "ms_per_case": run["ms_per_case"],
                   "not_ok": int((run["status"][sel] != "ok").sum()),  # NaN rows: left out of the medians
                   "not_at_rest": int(np.asarray(run["metrics"]["settle_unsettled"])[sel].sum())}  # nor in E_q_phys
            for k in METRICS:
                values = np.asarray(run["metrics"][k], float)[sel]
                row[k] = float(np.nanmedian(values)) if np.isfinite(values).any() else None
            for k in ("E_tau", "E_q"):
                row[f"d{k}_95"] = paired_interval(np.asarray(run["metrics"][k], float)[sel],
                                                  np.asarray(first[k], float)[sel], rng)
            rows.append(row)
    return rows


def markdown(rows: list[dict]) -> str:
    fmt = lambda v: "-" if v is None else f"{v:.3g}"  # noqa: E731
    out = ["| variant | cond | n | not ok | settle not at rest | " + " | ".join(METRICS)
           + " | dE_tau 95% | dE_q 95% | ms/case |", "|---|---|---|---|---|" + "---|" * (len(METRICS) + 3)]
    for r in rows:
        out.append(f"| {r['variant']} | {r['condition']} | {r['n']} | {r['not_ok']} | {r['not_at_rest']} | "
                   + " | ".join(fmt(r[k]) for k in METRICS)
                   + " | " + " | ".join("[{:+.3g}, {:+.3g}]".format(*r[f"d{k}_95"]) for k in ("E_tau", "E_q"))
                   + f" | {r['ms_per_case']:.3g} |")
    return "\n".join(out)


def parse_variant(spec: str) -> tuple[str, str, dict]:
    """``name`` or ``label=name:{json options}`` -> (label, variant, options)."""
    label, _, rest = spec.partition("=") if "=" in spec else (spec, "", spec)
    name, _, options = rest.partition(":")
    return label, name, (json.loads(options) if options else {})


@exits_cleanly
def main(argv=None):
    parser = argument_parser("Adaptation variants side by side on the paper or binding protocol: medians of every "
                             "metric (physical reading, settle check) and paired bootstrap intervals.", checkpoint=True,
                             device=True)
    parser.add_argument("--ckpt", required=True, help="trained schema checkpoint (.ckpt)")
    parser.add_argument("--protocol", default="binding", choices=("binding", "paper"))
    parser.add_argument("--seeds", default="0,1,2", help="case seeds, comma separated (default 0,1,2)")
    parser.add_argument("--n", type=int, default=None, help="cases per condition (binding 100, paper 40)")
    parser.add_argument("--variants", nargs="+", default=["guided", "default"],
                        help='variants, each `name` or `label=name:{"json": "options"}`, e.g. '
                             '\'s20=default:{"n_steps": 20}\'; the first is the reference of the intervals')
    parser.add_argument("--subset", default="all", choices=("all", "feasible"),
                        help="score all cases or only those with a physical solution (the paper protocol's claims "
                             "use the feasible ones; every binding case is feasible)")
    parser.add_argument("--json", default=None, help="also write the rows here")
    args = parser.parse_args(argv)
    if args.json:
        check_out(args.json, args.ckpt)
    torch_one_thread()
    from ..evaluation.benchmark import scored_command
    from ..schemas.loading import load_datamodule

    schema = load_checked_schema(args)
    datamodule = load_datamodule(args.ckpt)
    seeds = [int(s) for s in args.seeds.split(",")]
    cases = draw(args.protocol, schema, datamodule, seeds, args.n or (100 if args.protocol == "binding" else 40))
    runs = {}
    for spec in args.variants:
        label, variant, options = parse_variant(spec)
        start = time.perf_counter()
        result = schema.adapt(cases.q_ref, cases.faults, variant=variant, check_physics=False, **options)
        ms = 1e3 * (time.perf_counter() - start) / len(cases.q_ref)
        runs[label] = {"metrics": score(schema, cases, *scored_command(result)), "ms_per_case": ms,
                       "status": result.status}
    keep = None
    if args.subset == "feasible":
        from ..evaluation.feasibility import check_feasible

        keep = check_feasible(schema.robot_model, cases, schema.spring)[0]
    rows = table(cases, runs, keep)
    print(f"{args.protocol} protocol, seeds {seeds}, {len(cases.q_ref)} cases ({args.subset}), {args.ckpt}")
    print(markdown(rows))
    if args.json:
        from ..npz import atomic_write_bytes

        atomic_write_bytes(args.json, json.dumps(rows, indent=1).encode())
