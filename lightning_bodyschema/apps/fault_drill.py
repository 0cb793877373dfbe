"""``tools/fault_drill.py``: a fault strikes a robot holding a posture in MuJoCo; the monitor must find it from the
simulated sensors and the adapter re-command (``diagnosis.drill``). One drill writes its trace, summary and figure;
``--n N`` runs N random drills and prints the table."""
from __future__ import annotations

import json
import os
import time

import numpy as np

from ..errors import BodySchemaInputError
from .common import argument_parser, exits_cleanly, load_checked_schema, torch_one_thread

KINDS = ("cut", "jam", "weak", "band")
TOLERANCE = 0.10  # "as well as the true faults": within 10 % of the true-fault adapter's posture error ...
FLOOR_RAD = 1e-4  # ... or within this of it (the settle check's own resolution is ~3e-5 rad)


def parse_fault(text: str) -> dict:
    """``cut:NAME``, ``jam:NAME=L_M``, ``weak:NAME=F_N``, ``band:NAME=LO,HI`` as a request dict (predict's keys)."""
    kind, _, rest = text.partition(":")
    name, _, value = rest.partition("=")
    if kind not in KINDS or not name:
        raise BodySchemaInputError(f"--fault {text!r}: expected cut:NAME, jam:NAME=L_M, weak:NAME=F_N or "
                                   f"band:NAME=LO,HI")
    if kind == "cut":
        return {"cut": [name]}
    try:
        numbers = [float(v) for v in value.split(",")]
    except ValueError:
        numbers = []
    if len(numbers) != (2 if kind == "band" else 1):
        raise BodySchemaInputError(f"--fault {text!r}: {kind} needs {'=LO,HI [m]' if kind == 'band' else '=VALUE'}")
    return {kind: {name: numbers if kind == "band" else numbers[0]}}


def _faults(specs: list, muscles):
    from ..diagnosis.result import merge_requests
    from ..faults import Faults

    request = merge_requests({}, specs)
    return Faults.from_names(muscles, n_cases=1, **{k: [v] if k == "cut" else v for k, v in request.items()})


def _parser():
    parser = argument_parser("A fault strikes the robot holding a posture in MuJoCo; the monitor reads the simulated "
                             "sensors and, on a diagnosis, the adapter re-commands. Writes trace.csv (a sensor log "
                             "tools/diagnose.py reads, with x_error_rad), summary.json and drill.png in --out.",
                             checkpoint=True)
    parser.add_argument("--ckpt", required=True, help="trained schema checkpoint (.ckpt) of a robot with its MJCF")
    parser.add_argument("--fault", action="append", default=[], help="cut:NAME, jam:NAME=L_M, weak:NAME=F_N or "
                        "band:NAME=LO,HI (repeatable)")
    parser.add_argument("--q-ref", default=None, help="the held posture, comma-separated [rad] (default: the first of "
                        "the checkpoint's held-out split)")
    parser.add_argument("--at", type=float, default=1.0, help="when the fault strikes [s] (default 1.0)")
    parser.add_argument("--seconds", type=float, default=4.0, help="the drill's length [s] (default 4)")
    parser.add_argument("--tick", type=float, default=0.01, help="the controller's period [s] (default 0.01)")
    parser.add_argument("--window", type=int, default=5, help="the monitor's window [ticks] (default 5)")
    parser.add_argument("--confirm", type=int, default=3, help="consistent ticks before a fault is declared (3)")
    parser.add_argument("--noise", default=None, help="sensor noise q_rad,l_m,f_frac (default 1e-3,5e-5,0.005)")
    parser.add_argument("--no-load-cells", action="store_true", help="the robot reads no tensions")
    parser.add_argument("--n", type=int, default=0, help="run N random drills (1-2 faults of random kinds) instead")
    parser.add_argument("--seed", type=int, default=0, help="seed of the noise and of the random drills")
    parser.add_argument("--tensorboard", default=None, help="also log the trace's scalars to this TensorBoard dir")
    parser.add_argument("--out", required=True, help="output directory")
    return parser


def _settings(args):
    from ..diagnosis import SensorNoise
    from ..diagnosis.drill import DrillSettings

    if not (0 <= args.at < args.seconds) or not (0 < args.tick <= args.seconds):
        raise BodySchemaInputError(f"--at {args.at} must lie in [0, --seconds {args.seconds}) and --tick {args.tick} "
                                   f"in (0, --seconds]")
    noise = SensorNoise()
    if args.noise:
        try:
            noise = SensorNoise(*(float(v) for v in args.noise.split(",")))
        except (TypeError, ValueError):
            raise BodySchemaInputError(f"--noise {args.noise!r}: give q_rad,l_m,f_frac, three numbers") from None
    return DrillSettings(args.at, args.seconds, args.tick, args.window, args.confirm), noise


@exits_cleanly
def fault_drill_main(argv=None):
    args = _parser().parse_args(argv)
    settings, noise = _settings(args)
    if (args.n > 0) == bool(args.fault):
        raise BodySchemaInputError("give --fault KIND:NAME (one drill) or --n N (random drills), one of the two")
    if os.path.isfile(args.out):
        raise BodySchemaInputError(f"--out {args.out!r} is a file; give a directory")
    specs = [parse_fault(text) for text in args.fault]  # the format, before anything heavy
    torch_one_thread()
    schema = load_checked_schema(args)
    if not schema.has_physics:
        raise BodySchemaInputError("the drill runs in MuJoCo: the checkpoint's robot needs its MJCF")
    muscles = schema.robot_model.muscle_names
    faults = _faults(specs, muscles) if specs else None
    from ..schemas.loading import load_datamodule

    q_pool = np.asarray(load_datamodule(args.ckpt).splits["val"][0], float)
    load_cells = np.zeros(len(muscles), bool) if args.no_load_cells else None
    schema.body_error()
    os.makedirs(args.out, exist_ok=True)
    if args.n > 0:
        return _random_drills(schema, q_pool, args, settings, noise, load_cells)
    q_ref = _q_ref(args.q_ref, q_pool, schema)
    print(f"drill: holding q_ref {np.round(q_ref, 4).tolist()}, {args.fault} at {args.at} s, {args.seconds} s of "
          f"MuJoCo ({schema.robot_model.n_joints} joints; seconds on the paper arm, a minute on myoArm) ...",
          flush=True)
    _one_drill(schema, q_ref, faults, args, settings, noise, load_cells)


def _q_ref(text, q_pool, schema) -> np.ndarray:
    if text is None:
        return q_pool[0]
    try:
        q = np.array([float(v) for v in text.split(",")])
    except ValueError:
        raise BodySchemaInputError(f"--q-ref {text!r}: give {schema.n_joints} comma-separated angles [rad]") from None
    return schema.robot_model.check_q(q[None], within_range=True)[0]


def _one_drill(schema, q_ref, faults, args, settings, noise, load_cells):
    from ..diagnosis.drill import run_drill
    from ..diagnosis.log import SensorLog, write_sensor_log

    start = time.perf_counter()
    result = run_drill(schema, q_ref, faults, np.random.default_rng(args.seed), noise, settings, load_cells)
    summary = drill_summary(schema, q_ref, faults, result, settings)
    model = schema.robot_model
    log = SensorLog.from_rows(model.joint_names, model.muscle_names, result.q_rad, result.l_m, result.l_cmd_m,
                              result.f_cmd_n, result.f_n, t_s=result.t_s)
    write_sensor_log(os.path.join(args.out, "trace.csv"), log, {"error_rad": result.error_rad})
    from ..npz import atomic_write_bytes

    atomic_write_bytes(os.path.join(args.out, "summary.json"), (json.dumps(summary, indent=1) + "\n").encode())
    from ..plots.drill import plot_drill

    plot_drill(result, settings, model.muscle_names, summary, os.path.join(args.out, "drill.png"))
    if args.tensorboard:
        _tensorboard(args.tensorboard, result)
    print(json.dumps(summary, indent=1))
    print(f"wrote {args.out}/trace.csv, summary.json, drill.png in {time.perf_counter() - start:.1f} s")


def drill_summary(schema, q_ref, faults, result, settings) -> dict:
    from ..diagnosis.drill import faulted_names, rest_errors
    from ..diagnosis.result import fault_request

    muscles = schema.robot_model.muscle_names
    before = result.error_rad[result.t_s < settings.at_s]
    after = result.error_rad[(result.t_s >= settings.at_s)
                             & (result.t_s <= (result.detected_s if np.isfinite(result.detected_s) else np.inf))]
    identified = None if result.diagnosis is None else faulted_names(result.diagnosis.kind[0], muscles)
    truth = fault_request(faults, 0, muscles)
    rest = rest_errors(schema, q_ref, faults, None if result.diagnosis is None else result.diagnosis.union_faults(0))
    return {"q_ref": q_ref.tolist(), "fault": truth, "at_s": settings.at_s,
            "detected_s": None if np.isnan(result.detected_s) else float(result.detected_s),
            "detection_delay_s": None if np.isnan(result.detected_s) else float(result.detected_s - settings.at_s),
            "status": None if result.diagnosis is None else str(result.diagnosis.status[0]),
            "identified": identified, "identified_right": identified == _kinds(truth),
            "diagnosed_faults": None if result.diagnosis is None else fault_request(result.diagnosis.union_faults(0), 0,
                                                                                     muscles),
            "adapted_status": result.adapted_status,
            "error_before_fault_rad": float(before[-1]) if before.size else None,
            "error_after_fault_max_rad": float(after.max()) if after.size else None,
            "error_end_rad": float(result.error_rad[-1]),
            "rest_error_rad": rest}


def _kinds(request: dict) -> dict:
    out = {m: "cut" for m in request.get("cut", [])}
    for kind in ("jam", "weak", "band"):
        out.update({m: kind for m in request.get(kind, {})})
    return out


def _tensorboard(logdir, result):
    from torch.utils.tensorboard import SummaryWriter

    writer = SummaryWriter(logdir)
    for k, t in enumerate(result.t_s):
        writer.add_scalar("drill/posture_error_rad", result.error_rad[k], k)
        writer.add_scalar("drill/time_s", t, k)
    writer.close()


def _random_drills(schema, q_pool, args, settings, noise, load_cells):
    from ..diagnosis.trials import FAULT_KINDS, _draw_faults
    from ..evaluation import FaultCases, check_feasible, condition_of

    rng = np.random.default_rng(args.seed)
    rows, start = [], time.perf_counter()
    for k in range(args.n):
        q_ref = q_pool[rng.integers(len(q_pool))]
        l_cmd, f_cmd = schema.infer(q_ref[None])
        _, faults = _draw_faults(l_cmd, f_cmd, int(rng.integers(1, 3)), FAULT_KINDS, rng)
        cases = FaultCases(q_ref[None], faults.cut, faults.fix, faults.l_fixed_m,
                           condition_of(faults.cut, faults.fix, faults.weak, faults.band), faults.f_max_n,
                           faults.l_band_m)
        feasible = bool(check_feasible(schema.robot_model, cases, schema.spring)[0][0])
        from ..diagnosis.drill import run_drill

        result = run_drill(schema, q_ref, faults, rng, noise, settings, load_cells)
        summary = drill_summary(schema, q_ref, faults, result, settings)
        summary["feasible"] = feasible
        summary["identifiable"] = _identifiable(schema, q_ref, l_cmd, f_cmd, faults, noise, load_cells)
        summary["as_well_as_true"] = _as_well(summary["rest_error_rad"])
        rows.append(summary)
        print(f"drill {k + 1}/{args.n}: {summary['fault']} -> {summary['status']} {summary['identified']}, delay "
              f"{summary['detection_delay_s']}, rest error diagnosed {summary['rest_error_rad'].get('diagnosed')} vs "
              f"true {summary['rest_error_rad'].get('true_faults')}", flush=True)
    table = drill_table(rows)
    from ..npz import atomic_write_bytes

    atomic_write_bytes(os.path.join(args.out, "drills.json"),
                       (json.dumps({"table": table, "drills": rows}, indent=1) + "\n").encode())
    print(json.dumps(table, indent=1))
    print(f"wrote {args.out}/drills.json: {args.n} drills in {time.perf_counter() - start:.0f} s")


def _identifiable(schema, q_ref, l_cmd, f_cmd, faults, noise, load_cells) -> bool:
    """The physics oracle's rule (``diagnosis.trials``): the true body's diagnosis of the noise-free readings at the
    posture the faulted body comes to rest at names exactly the true faults."""
    from ..diagnosis.trials import Trial, identifiable

    trial = Trial(_truth(faults), faults, q_ref[None], l_cmd, f_cmd, np.zeros(1, int), None, np.ones(1, bool))
    from ..diagnosis.sensors import true_readings

    trial.readings = true_readings(schema.robot_model, schema.spring, q_ref[None], l_cmd, f_cmd, faults)
    return bool(identifiable(trial, schema.robot_model, schema.spring, noise, None, load_cells)[0])


def _truth(faults) -> np.ndarray:
    from ..diagnosis.result import BAND, CUT, HEALTHY, JAM, WEAK

    truth = np.full(faults.cut.shape, HEALTHY)
    for mask, kind in ((faults.cut, CUT), (faults.fix, JAM), (faults.weak, WEAK), (faults.band, BAND)):
        truth[mask] = kind
    return truth


def _as_well(rest: dict):
    """True / False, or None where either command never came to rest (no rest posture to compare)."""
    diag, true = rest.get("diagnosed"), rest.get("true_faults")
    if diag is None or true is None:
        return None
    return bool(diag <= (1 + TOLERANCE) * true or diag - true <= FLOOR_RAD)


def drill_table(rows: list) -> dict:
    feasible = [r for r in rows if r["feasible"]]
    good = [r for r in feasible if r["identified_right"] and r["as_well_as_true"]]
    shown = [r for r in feasible if r["identifiable"] and r["as_well_as_true"] is not None]
    shown_good = [r for r in shown if r["identified_right"] and r["as_well_as_true"]]
    delays = [r["detection_delay_s"] for r in feasible if r["detection_delay_s"] is not None]
    statuses = {}
    for r in feasible:
        statuses[str(r["status"])] = statuses.get(str(r["status"]), 0) + 1
    return {"drills": len(rows), "feasible": len(feasible),
            "identified_right": sum(r["identified_right"] for r in feasible),
            "identified_and_as_well_as_true": len(good),
            "rate": len(good) / len(feasible) if feasible else None, "statuses": statuses,
            "identifiable_compared": len(shown), "identifiable_identified_and_as_well": len(shown_good),
            "identifiable_not_at_rest": sum(r["identifiable"] and r["as_well_as_true"] is None for r in feasible),
            "identifiable_rate": len(shown_good) / len(shown) if shown else None,
            "as_well_as_true_any_status": sum(bool(r["as_well_as_true"]) for r in feasible),
            "detection_delay_s_median": float(np.median(delays)) if delays else None,
            "detection_delay_s_max": float(np.max(delays)) if delays else None}
