"""``tools/diagnose_study.py``: how well a checkpoint's diagnosis names random faults in simulated logs (RESULTS.md's
"When you don't know what broke" tables): identification over identifiable logs, the confusion table, false
alarms on healthy logs, parameter errors, and adapt with the diagnosed faults against adapt with the true ones."""
from __future__ import annotations

import json
import time

import numpy as np

from ..errors import BodySchemaInputError
from .common import argument_parser, check_out, exits_cleanly, load_checked_schema, torch_one_thread

CONDITIONS = {"healthy": 0, "single": 1, "double": 2}
LABELS = ("healthy", "cut", "jam", "weak", "band", "ambiguous", "not_identifiable")


def run_condition(schema, model, spring, pool, n_logs, n_faults, rng, load_cells: bool, noise, thresholds):
    """One condition's figures (a dict) and its raw arrays."""
    from ..diagnosis.trials import draw_trial, oracle_diagnosis, right, trial_log
    from ..status import Status

    has_f = None if load_cells else np.zeros(model.n_muscles, bool)
    trial = draw_trial(model, spring, pool, n_logs, n_faults, rng)
    oracle = oracle_diagnosis(trial, model, spring, noise, thresholds, has_f)
    ident = right(oracle, trial.truth) & trial.at_rest
    start = time.perf_counter()
    d = schema.diagnose(trial_log(trial, model, spring, noise, rng, has_f), noise, thresholds)
    seconds = time.perf_counter() - start
    ok = right(d, trial.truth)
    claimed = d.status == Status.IDENTIFIED
    out = {"logs": n_logs, "at_rest": int(trial.at_rest.sum()), "identifiable": int(ident.sum()),
           "right": int((ok & ident).sum()), "right_rate": _rate(ok & ident, ident),
           "wrong_identified": int((claimed & ~ok & ident).sum()),
           "wrong_identified_rate": _rate(claimed & ~ok & ident, ident),
           "wrong_identified_all_logs": int((claimed & ~ok & trial.at_rest).sum()),
           # on a log that cannot show the truth (a trace-less fault, a band met only at its upper edge), the physics
           # oracle's own reading is the most any diagnosis can say: a claim that differs from it is a wrong answer
           "wrong_identified_vs_oracle_all_logs": int((claimed & trial.at_rest & _differ(d, oracle)).sum()),
           "statuses": _counts(d.status[ident].astype(str)), "diagnose_ms_per_log": 1e3 * seconds / n_logs}
    if n_faults == 0:
        alarm = d.status != Status.NO_FAULT
        out.update(false_alarm_rate=_rate(alarm & trial.at_rest, trial.at_rest),
                   false_alarm_statuses=_counts(d.status[alarm & trial.at_rest].astype(str)))
    return out, trial, d, ident, ok


def confusion(trial, d, ident) -> dict:
    """Single faults: true kind -> diagnosed kind of that muscle (or the log's status where it names none)."""
    from ..diagnosis.result import KINDS, HEALTHY
    from ..status import Status

    table = {kind: {label: 0 for label in LABELS} for kind in KINDS[1:]}
    for c in np.flatnonzero(ident):
        m = int(np.flatnonzero(trial.truth[c] != HEALTHY)[0])
        status = d.status[c]
        label = KINDS[d.kind[c, m]] if status in (Status.IDENTIFIED, Status.NO_FAULT) else str(status)
        table[KINDS[trial.truth[c, m]]][label] += 1
    return table


def parameter_errors(trial, d, ok) -> dict:
    """Jam length [mm] and weak limit [%] errors over the logs diagnosed right."""
    from ..diagnosis.result import JAM, WEAK

    jam = ok[:, None] & (trial.truth == JAM)
    weak = ok[:, None] & (trial.truth == WEAK)
    jam_mm = 1e3 * np.abs(d.l_fixed_m - trial.faults.l_fixed_m)[jam]
    weak_pct = 100 * np.abs(d.f_weak_n[weak] / trial.faults.f_max_n[weak] - 1) if weak.any() else np.zeros(0)
    return {"jam_n": int(jam.sum()), "jam_err_mm_median": _q(jam_mm, 0.5), "jam_err_mm_max": _q(jam_mm, 1.0),
            "jam_within_0.2mm": _rate(jam_mm <= 0.2, np.ones(jam_mm.size, bool)),
            "weak_n": int(weak.sum()), "weak_err_pct_median": _q(weak_pct, 0.5), "weak_err_pct_max": _q(weak_pct, 1.0),
            "weak_within_3pct": _rate(weak_pct <= 3.0, np.ones(weak_pct.size, bool))}


def end_to_end(schema, model, spring, trial, d, ok) -> dict:
    """At each right log's first posture: adapt with the diagnosed faults and with the true ones, both scored by the
    evaluator under the true faults (E_q [rad])."""
    from ..evaluation import FaultCases, condition_of, evaluate_commands

    first = np.r_[0, np.flatnonzero(np.diff(trial.log_rows)) + 1]
    logs = np.flatnonzero(ok & (trial.truth != 0).any(1))
    if logs.size == 0:
        return {}
    q = trial.q_ref[first[logs]]
    true = trial.faults.take(logs)
    cases = FaultCases(q, true.cut, true.fix, true.l_fixed_m, condition_of(true.cut, true.fix, true.weak, true.band),
                       true.f_max_n, true.l_band_m)
    e_q = {}
    for name, faults in (("true", true), ("diagnosed", d.faults.take(logs))):
        result = schema.adapt(q, faults, check_physics=False)
        e_q[name] = evaluate_commands(model, cases, result.l_motor_m, result.f_n, spring)["E_q"]
    both = np.isfinite(e_q["true"]) & np.isfinite(e_q["diagnosed"]) & (e_q["true"] > 0)
    ratio = e_q["diagnosed"][both] / e_q["true"][both]
    return {"n": int(logs.size), "E_q_true_median": _q(e_q["true"], 0.5),
            "E_q_diagnosed_median": _q(e_q["diagnosed"], 0.5),
            "ratio_geometric_mean": float(np.exp(np.mean(np.log(ratio)))) if ratio.size else None,
            "ratio_max": _q(ratio, 1.0)}


def markdown(report: dict) -> str:
    """The report's tables for RESULTS.md: one row per condition, then the single faults' confusion table."""
    def pct(x):
        return "n/a" if x is None else f"{100 * x:.1f} %"

    rows = ["| condition | logs at rest | identifiable | right | statuses (identifiable) | wrong & `identified` "
            "(identifiable / all / vs oracle) | false alarms | jam within 0.2 mm | weak within 3 % (median) | "
            "E_q diagnosed / true (geo. mean ratio) |", "|---|---|---|---|---|---|---|---|---|---|"]
    for name in CONDITIONS:
        r = report.get(name)
        if r is None:
            continue
        p, e = r.get("parameters", {}), r.get("end_to_end", {})
        statuses = ", ".join(f"{k} {v}" for k, v in r["statuses"].items())
        alarms = ""
        if "false_alarm_rate" in r:
            which = ", ".join(f"{k} {v}" for k, v in r["false_alarm_statuses"].items()) or "none"
            alarms = f"{pct(r['false_alarm_rate'])} ({which})"
        jam = f"{pct(p.get('jam_within_0.2mm'))} of {p['jam_n']}" if p.get("jam_n") else ""
        weak = (f"{pct(p.get('weak_within_3pct'))} of {p['weak_n']} ({p['weak_err_pct_median']:.2f} %)"
                if p.get("weak_n") else "")
        e2e = (f"{e['E_q_diagnosed_median']:.4g} / {e['E_q_true_median']:.4g} ({e['ratio_geometric_mean']:.4f})"
               if e.get("n") else "")
        rows.append(f"| {name} | {r['at_rest']} of {r['logs']} | {r['identifiable']} | {r['right']} "
                    f"({pct(r['right_rate'])}) "
                    f"| {statuses} | {r['wrong_identified']} / {r['wrong_identified_all_logs']} / "
                    f"{r.get('wrong_identified_vs_oracle_all_logs', 'n/a')} | {alarms} | {jam} | {weak} | {e2e} |")
    for key, what in (("confusion", "identifiable logs"), ("confusion_all_logs_at_rest", "every log at rest")):
        table = report.get("single", {}).get(key)
        if table:
            rows += ["", f"| true kind \\ diagnosed ({what}) | " + " | ".join(LABELS) + " |",
                     "|---" * (len(LABELS) + 1) + "|"]
            rows += [f"| {kind} | " + " | ".join(str(table[kind][label]) for label in LABELS) + " |" for kind in table]
    return "\n".join(rows)


def _differ(d, oracle) -> np.ndarray:
    """(C,) bool: the diagnosis says something else than the physics oracle's own reading of the log."""
    return (d.kind != oracle.kind).any(1) | (oracle.status != d.status)


def _rate(hit, among) -> float | None:
    return float(hit.sum() / among.sum()) if among.sum() else None


def _q(values, q) -> float | None:
    values = np.asarray(values, float)
    values = values[np.isfinite(values)]
    return float(np.quantile(values, q)) if values.size else None


def _counts(values) -> dict:
    names, counts = np.unique(values, return_counts=True)
    return {str(n): int(c) for n, c in zip(names, counts)}


def _parser():
    parser = argument_parser("How well a checkpoint's diagnosis names random faults in logs simulated in MuJoCo "
                             "(healthy, one and two faults; with and without load cells); writes the figures (.json) "
                             "and prints the tables.", checkpoint=True)
    parser.add_argument("--ckpt", required=True, help="trained schema checkpoint (.ckpt) of a robot with its MJCF")
    parser.add_argument("--out", required=True, help="figures (.json)")
    parser.add_argument("--n", type=int, default=200, help="logs per condition (default 200)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the draws (default 0)")
    parser.add_argument("--conditions", default="healthy,single,double", help="comma-separated: healthy,single,double")
    parser.add_argument("--no-load-cells", action="store_true", help="logs without f_ columns (encoders and joints)")
    parser.add_argument("--end-to-end", action="store_true", help="also adapt with the diagnosed and the true faults")
    return parser


@exits_cleanly
def diagnose_study_main(argv=None):
    args = _parser().parse_args(argv)
    conditions = [c.strip() for c in args.conditions.split(",") if c.strip()]
    unknown = sorted(set(conditions) - set(CONDITIONS))
    if unknown or not conditions:
        raise BodySchemaInputError(f"--conditions {args.conditions!r}: unknown {unknown}; allowed {list(CONDITIONS)}")
    if args.n < 1 or args.seed < 0:
        raise BodySchemaInputError(f"--n {args.n} must be >= 1 and --seed {args.seed} >= 0")
    check_out(args.out, args.ckpt)
    torch_one_thread()
    from ..diagnosis import SensorNoise, Thresholds
    from ..schemas.loading import load_datamodule

    schema = load_checked_schema(args)
    if not schema.has_physics:
        raise BodySchemaInputError("the study simulates logs in MuJoCo: the checkpoint's robot needs its MJCF")
    datamodule = load_datamodule(args.ckpt)
    model, spring = datamodule.robot_model, datamodule.spring
    q = np.asarray(datamodule.splits["val"][0], float)
    pool = (q, *schema.infer(q))
    noise, thresholds = SensorNoise(), Thresholds()
    schema.body_error()
    report = {"checkpoint": args.ckpt, "load_cells": not args.no_load_cells, "seed": args.seed}
    for i, name in enumerate(conditions):
        print(f"{name}: simulating {args.n} logs of 1-5 held postures in MuJoCo and diagnosing them ...", flush=True)
        rng = np.random.default_rng([args.seed, i])
        figures, trial, d, ident, ok = run_condition(schema, model, spring, pool, args.n, CONDITIONS[name], rng,
                                                     not args.no_load_cells, noise, thresholds)
        if CONDITIONS[name] == 1:
            figures["confusion"] = confusion(trial, d, ident)
            figures["confusion_all_logs_at_rest"] = confusion(trial, d, trial.at_rest)
        if CONDITIONS[name] > 0:
            figures["parameters"] = parameter_errors(trial, d, ok & ident)
            if args.end_to_end:
                figures["end_to_end"] = end_to_end(schema, model, spring, trial, d, ok & ident)
        report[name] = figures
        print(json.dumps({name: figures}, indent=1), flush=True)
    from ..npz import atomic_write_bytes

    atomic_write_bytes(args.out, (json.dumps(report, indent=1) + "\n").encode())
    print(markdown(report))
    print(f"wrote {args.out}")
