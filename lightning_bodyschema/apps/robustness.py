"""``tools/robustness.py``: how much sensor noise and model error the diffusion schema survives.

For each level, a dataset is made as a robot would record it (``tools/make_dataset.py``'s noise and mismatch),
written in the recorded-data format and read back by ``RecordedDataModule`` (no MJCF in training), the paper's
diffusion schema is trained on it, and its healthy and adapted commands are scored ON THE TRUE MODEL (the
unperturbed paper arm): E_tau, E_q (forward solver) and E_q_phys (MuJoCo settle check), over the fault cases that
have a physical solution. Beside them: the unadapted (healthy) command under the same faults and the physics
oracle of the true model (``evaluation.feasibility.oracle_commands``).

Levels: noise 0, 0.5, 1, 2 % of each channel's range (joint range, motor-length spread of the data, f_max), model
mismatch 0, 5, 10, 20 % (``sim/mismatch.py``). The clean run is shared by both sweeps.
"""
from __future__ import annotations

import json
import os
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass
import multiprocessing

import numpy as np

from .._numpy import to_numpy
from ..errors import BodySchemaInputError
from .common import argument_parser, exits_cleanly, torch_one_thread

NOISE_PCT = (0.0, 0.5, 1.0, 2.0)
MISMATCH_PCT = (0.0, 5.0, 10.0, 20.0)
METRICS = ("E_tau", "E_q", "E_q_phys")
ORACLE_FLOOR = 1e-6  # medians below this are round-off (the oracle's): stated, not drawn on a log axis
WIDE_N = 1e6  # tension limit given to the reader in the study: noisy readings below 0 N are kept, not dropped


@dataclass(frozen=True)
class Level:
    """One training set: sensor noise [% of each channel's range] and model mismatch [%]."""

    noise_pct: float
    mismatch_pct: float

    @property
    def name(self) -> str:
        return f"noise{self.noise_pct:g}-mismatch{self.mismatch_pct:g}"


def study_levels(noise_pct=NOISE_PCT, mismatch_pct=MISMATCH_PCT) -> list[Level]:
    """The noise sweep (no mismatch) then the mismatch sweep (no noise); the clean level once."""
    levels = [Level(float(p), 0.0) for p in noise_pct]
    levels += [Level(0.0, float(m)) for m in mismatch_pct if m > 0 or 0.0 not in noise_pct]
    return list(dict.fromkeys(levels))


# ---------------------------------------------------------------------------- data
def noise_std(level: Level, model, l_motor: np.ndarray, f_max_n: float) -> tuple:
    """(std q (N,) [rad], std l (M,) [m], std f (M,) [N]): ``noise_pct`` of each channel's range."""
    share = level.noise_pct / 100.0
    q_span = np.diff(model.q_range, axis=1)[:, 0]
    l_span = l_motor.max(0) - l_motor.min(0)
    return share * q_span, share * l_span, share * np.full(l_motor.shape[1], f_max_n)


def make_level_data(level: Level, path: str, n: int, seed: int, mismatch_seed: int) -> dict:
    """Write the level's dataset (recorded format) to ``path``; returns what was applied."""
    from ..data.dataset import build_dataset
    from ..data.recorded import write_recorded
    from ..sim import MusculoskeletalModel, SpringParams
    from ..sim.mismatch import mismatched_robot
    from .dataset_tool import add_sensor_noise

    model, spring = MusculoskeletalModel("paper_arm"), SpringParams()
    source = model
    if level.mismatch_pct > 0:
        source, spring = mismatched_robot(model, spring, level.mismatch_pct / 100.0, mismatch_seed)
    arrays = build_dataset(source, n, seed, spring)
    std_q, std_l, std_f = noise_std(level, model, arrays["l_motor"], float(SpringParams().f_max_n))
    arrays = add_sensor_noise(arrays, std_q, std_l, std_f, seed)
    ranges = {f"q_{j}": lim for j, lim in zip(model.joint_names, model.q_range.tolist())}
    write_recorded(path, arrays["q"], arrays["l_motor"], arrays["f"], model.joint_names, model.muscle_names, ranges,
                   {"noise_pct": level.noise_pct, "mismatch_pct": level.mismatch_pct, "mismatch_seed": mismatch_seed})
    return {"std_q_rad": std_q.tolist(), "std_l_m": std_l.tolist(), "std_f_n": std_f.tolist()}


def recorded_module(path: str, seed: int):
    """The study's reader: q limits from the file, tensions kept whatever their sign (f_max stays 150 N)."""
    from ..data.recorded import RecordedDataModule, read_recorded

    muscles = read_recorded(path).muscles
    return RecordedDataModule(path, seed=seed, f_range={m: [-WIDE_N, WIDE_N] for m in muscles}, f_max_n=150.0)


# ---------------------------------------------------------------------------- scoring on the true model
def _medians(values: dict, rows: np.ndarray) -> dict:
    out = {}
    for name in METRICS:
        v = np.asarray(values[name])[rows]
        v = v[np.isfinite(v)]
        out[name] = float(np.median(v)) if v.size else None
    # settle runs never at rest are not in E_q_phys's median: counted beside it
    return out | {"n": int(rows.sum()), "n_unsettled": int(np.asarray(values["settle_unsettled"])[rows].sum())}


def score(values: dict, cases, feasible: np.ndarray) -> dict:
    """{cond or "all": medians of METRICS over the feasible cases}."""
    out = {"all": _medians(values, feasible)}
    for cond in dict.fromkeys(cases.cond.tolist()):
        out[cond] = _medians(values, feasible & (cases.cond == cond))
    return out


def score_commands(model, spring, cases, l_motor, f) -> dict:
    """E_tau, E_q (forward solver, jammed wires pull) and E_q_phys (settle check) of commands on ``model``."""
    from ..evaluation.forward_solver import ForwardSolverParams
    from ..evaluation.metrics import evaluate_commands
    from ..evaluation.benchmark import settle_metrics
    from ..sim.settle import settle

    metrics = evaluate_commands(model, cases, l_motor, f, spring, ForwardSolverParams(jammed_tension_in_torque=True))
    # a simulation still moving at its time limit or blown up has no rest posture: not a score, left out (NaN) and
    # counted in settle_unsettled
    metrics.update(settle_metrics(settle(model, l_motor, f, cases, spring=spring)))
    return metrics


def train_and_score(level: Level, out_dir: str, epochs: int, n: int, seed: int, mismatch_seed: int) -> dict:
    """One level: data -> RecordedDataModule -> diffusion schema -> scores on the true model (a worker process)."""
    torch_one_thread()
    import lightning as L

    from ..evaluation.cases import FaultCases
    from ..evaluation.feasibility import check_feasible
    from ..schemas import DiffusionSchema
    from ..sim import MusculoskeletalModel, SpringParams

    start = time.perf_counter()
    path = os.path.join(out_dir, f"{level.name}.npz")
    applied = make_level_data(level, path, n, seed, mismatch_seed)
    datamodule = recorded_module(path, seed)
    L.seed_everything(seed, verbose=False)
    schema = DiffusionSchema(robot=datamodule.robot)
    trainer = L.Trainer(max_epochs=epochs, logger=False, enable_checkpointing=False, enable_progress_bar=False,
                        enable_model_summary=False, check_val_every_n_epoch=10 ** 9, num_sanity_val_steps=0)
    trainer.fit(schema, datamodule)
    trainer.save_checkpoint(os.path.join(out_dir, f"{level.name}.ckpt"), weights_only=False)
    train_seconds = time.perf_counter() - start
    schema.eval()
    model, spring = MusculoskeletalModel("paper_arm"), SpringParams()  # the true robot
    out = {"level": asdict(level), "applied_noise_std": applied, "n_dropped": datamodule.n_dropped,
           "train_seconds": train_seconds, "protocols": {}}
    healthy = FaultCases.load(os.path.join(out_dir, "healthy_cases.npz"))
    l_motor, f = schema.infer(healthy.q_ref)
    out["healthy"] = score(score_commands(model, spring, healthy, l_motor, f), healthy, np.ones(len(healthy), bool))
    for protocol in _protocols(out_dir):
        cases = FaultCases.load(os.path.join(out_dir, f"cases_{protocol}.npz"))
        feasible = check_feasible(model, cases, spring)[0]
        adapted = schema.adapt(cases.q_ref, cases.faults, check_physics=False)  # scored below, every command
        plain = schema.infer(cases.q_ref)
        out["protocols"][protocol] = {
            "adapted": score(score_commands(model, spring, cases, adapted.l_motor_m, adapted.f_n), cases, feasible),
            "unadapted": score(score_commands(model, spring, cases, *plain), cases, feasible)}
    out["seconds"] = time.perf_counter() - start
    return out


def _protocols(out_dir: str) -> list[str]:
    return sorted(name[len("cases_"):-4] for name in os.listdir(out_dir) if name.startswith("cases_"))


def make_cases(out_dir: str, n: int, seed: int, n_per_condition: int) -> dict:
    """The fault cases (paper and binding protocols; CUT, FIX, BOTH) and healthy postures, from the true model's
    clean test split; the physics oracle's scores on them."""
    from ..evaluation.cases import FaultCases, HealthyPool, make_binding_cases, make_fault_cases
    from ..evaluation.feasibility import oracle_commands
    from ..sim import MusculoskeletalModel, SpringParams

    clean = os.path.join(out_dir, "true_model_clean.npz")
    make_level_data(Level(0.0, 0.0), clean, n, seed, 0)
    datamodule = recorded_module(clean, seed)
    datamodule.setup("test")
    q, x = (to_numpy(t) for t in datamodule.splits["val"])
    m = x.shape[1] // 2
    model, spring = MusculoskeletalModel("paper_arm"), SpringParams()
    protocols = {"paper": make_fault_cases(q, x[:, :m], n_per_condition, seed),
                 # every case has a physical solution and its healthy command breaks every fault
                 "binding": make_binding_cases(model, HealthyPool(q, x[:, :m], x[:, m:]), n_per_condition, seed,
                                               spring, conditions=("CUT", "FIX", "BOTH"))[0]}
    oracle = {}
    for name, cases in protocols.items():
        cases.save(os.path.join(out_dir, f"cases_{name}.npz"))
        feasible, l_motor, f = oracle_commands(model, cases, spring)
        oracle[name] = score(score_commands(model, spring, cases, l_motor, f), cases, feasible)
    healthy = FaultCases(q, np.zeros((len(q), m), bool), np.zeros((len(q), m), bool), np.full((len(q), m), np.nan),
                         np.full(len(q), "NONE"))
    healthy.save(os.path.join(out_dir, "healthy_cases.npz"))
    return oracle


# ---------------------------------------------------------------------------- report
def _fmt(value) -> str:
    return "—" if value is None else f"{value:.3g}"


def _n(values: dict) -> str:
    """The case count, and the settle runs among them that never came to rest (not in E_q_phys's median)."""
    return f"{values['n']}" + (f" ({values['n_unsettled']} not at rest)" if values.get("n_unsettled") else "")


def markdown(results: list[dict], oracle: dict, meta: dict) -> str:
    lines = [f"Command: `{meta['command']}`; {meta['epochs']} epochs per schema, {meta['n']} samples, "
             f"{meta['n_per_condition']} cases per condition; {meta['minutes']:.1f} min on 2 cores "
             f"(load average {meta['load_start']:.1f} at start, {meta['load_end']:.1f} at end). Medians over the "
             "cases with a physical solution on the true model; E_tau [N m], E_q and E_q_phys [rad]; E_q_phys over the "
             "settle runs that came to rest (`n (k not at rest)`: k runs still moving or blown up, left out).", ""]
    lines += summary_table(results, oracle)
    for protocol in oracle:
        lines += ["", f"Fault cases, {protocol} protocol (adapted / unadapted):", "",
                  "| training data | cond | n | E_tau | E_q | E_q_phys |", "|---|---|---|---|---|---|"]
        for cond in _conditions(oracle[protocol]):
            o = oracle[protocol][cond]
            lines.append(f"| physics oracle | {cond} | {_n(o)} | " + " | ".join(_fmt(o[k]) for k in METRICS) + " |")
        for r in results:
            for cond in _conditions(r["protocols"][protocol]["adapted"]):
                a, u = r["protocols"][protocol]["adapted"][cond], r["protocols"][protocol]["unadapted"][cond]
                lines.append(f"| {_label(r['level'])} | {cond} | {_n(a)} | "
                             + " | ".join(f"{_fmt(a[k])} / {_fmt(u[k])}" for k in METRICS) + " |")
    return "\n".join(lines) + "\n"


def summary_table(results: list[dict], oracle: dict) -> list[str]:
    """One row per level: healthy E_tau / E_q / E_q_phys, then adapted (unadapted) E_tau / E_q_phys per protocol,
    pooled over the conditions."""
    protocols = [p for p in ("paper", "binding") if p in oracle] + sorted(p for p in oracle if p not in
                                                                           ("paper", "binding"))
    lines = ["| training data | rows dropped | healthy (no fault) E_tau / E_q / E_q_phys | "
             + " | ".join(f"{p} protocol: adapted (unadapted) E_tau / E_q_phys" for p in protocols) + " |",
             "|---|---|---|" + "---|" * len(protocols)]
    lines.append("| physics oracle of the true arm | — | — | " + " | ".join(
        f"{_fmt(oracle[p]['all']['E_tau'])} / {_fmt(oracle[p]['all']['E_q_phys'])}" for p in protocols) + " |")
    for r in results:
        h, cells = r["healthy"]["all"], []
        for p in protocols:
            a, u = r["protocols"][p]["adapted"]["all"], r["protocols"][p]["unadapted"]["all"]
            cells.append(f"{_fmt(a['E_tau'])} ({_fmt(u['E_tau'])}) / {_fmt(a['E_q_phys'])} ({_fmt(u['E_q_phys'])})")
        lines.append(f"| {_label(r['level'])} | {r['n_dropped']} | {_fmt(h['E_tau'])} / {_fmt(h['E_q'])} / "
                     f"{_fmt(h['E_q_phys'])} | " + " | ".join(cells) + " |")
    return lines


def _conditions(by_cond: dict) -> list:
    """"all" first, then the paper's order (the json file sorts its keys)."""
    order = ("all", "CUT", "FIX", "BOTH")
    return [c for c in order if c in by_cond] + sorted(c for c in by_cond if c not in order)


def _label(level: dict) -> str:
    if level["mismatch_pct"] == 0:
        return f"noise {level['noise_pct']:g} %" + (" (clean)" if level["noise_pct"] == 0 else "")
    return f"mismatch {level['mismatch_pct']:g} %"


def figure(results: list[dict], oracle: dict, path: str) -> None:
    """E_tau, E_q, E_q_phys (rows) against noise and mismatch (columns): adapted, unadapted, healthy, oracle."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(METRICS), 2, figsize=(9, 8), sharey="row")
    for col, (axis_key, other_key, xlabel) in enumerate((("noise_pct", "mismatch_pct", "sensor noise [% of range]"),
                                                         ("mismatch_pct", "noise_pct", "model mismatch [%]"))):
        rows = sorted((r for r in results if r["level"][other_key] == 0), key=lambda r: r["level"][axis_key])
        x = [r["level"][axis_key] for r in rows]
        for row, metric in enumerate(METRICS):
            ax = axes[row, col]
            for style, protocol in zip(("-", "--"), oracle):
                for kind, color in (("adapted", "C0"), ("unadapted", "C3")):
                    ax.plot(x, [_pos(r["protocols"][protocol][kind]["all"][metric]) for r in rows], style, marker="o",
                            color=color, label=f"{kind} ({protocol})")
                if _pos(oracle[protocol]["all"][metric]) > ORACLE_FLOOR:  # ~0 (round-off): said in the title
                    ax.axhline(oracle[protocol]["all"][metric], color="C2", ls=style, lw=1,
                               label=f"physics oracle ({protocol})")
            ax.plot(x, [_pos(r["healthy"]["all"][metric]) for r in rows], ":", marker="s", color="k",
                    label="healthy, no fault")
            ax.set_yscale("log")
            ax.set_ylabel(f"median {metric}")
            ax.set_xlabel(xlabel)
            ax.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=7)
    zero = ", ".join(f"{m} {_fmt(oracle[p]['all'][m])}" for p in oracle for m in METRICS
                     if _pos(oracle[p]["all"][m]) <= ORACLE_FLOOR)
    fig.suptitle("Diffusion schema trained on noisy / mismatched data, scored on the true paper arm"
                 + (f"\nphysics oracle (not drawn, ~0): {zero}" if zero else ""), fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _pos(value):
    """A median for a log axis: None -> NaN, 0 -> a floor (the oracle's exact zeros)."""
    return np.nan if value is None else max(float(value), 1e-6)


@exits_cleanly
def robustness_main(argv=None):
    parser = argument_parser("Robustness study: train the diffusion schema on noisy and mismatched data, score "
                             "healthy and adapted commands on the true paper arm; writes a table, a figure, json.")
    parser.add_argument("--out-dir", default="runs/robustness", help="folder for data, checkpoints and results")
    parser.add_argument("--epochs", type=int, default=1500,
                        help="training epochs per schema (paper: 10000; fewer shorten the study, BENCHMARKS.md "
                             "\"Figures behind code choices\")")
    parser.add_argument("--n", type=int, default=800, help="samples per dataset (paper: 800)")
    parser.add_argument("--seed", type=int, default=0, help="seed of postures, noise, split, training and cases")
    parser.add_argument("--mismatch-seed", type=int, default=0)
    parser.add_argument("--n-per-condition", type=int, default=40, help="fault cases per condition (paper: 40)")
    parser.add_argument("--noise", type=float, nargs="+", default=list(NOISE_PCT), help="noise levels [%% of range]")
    parser.add_argument("--mismatch", type=float, nargs="+", default=list(MISMATCH_PCT), help="mismatch levels [%%]")
    parser.add_argument("--jobs", type=int, default=2, help="levels trained in parallel (one process each)")
    parser.add_argument("--report-only", action="store_true",
                        help="rewrite robustness.md and .png from the robustness.json in --out-dir, train nothing")
    args = parser.parse_args(argv)
    if args.report_only:
        return write_report(args.out_dir)
    if args.epochs < 1 or args.n < 10 or args.jobs < 1 or args.n_per_condition < 1 or args.seed < 0:
        raise BodySchemaInputError("--epochs, --jobs, --n-per-condition must be >= 1, --n >= 10 and --seed >= 0")
    if any(p < 0 for p in args.noise) or any(not 0 <= m < 100 for m in args.mismatch):
        raise BodySchemaInputError(f"--noise {args.noise} must be >= 0 and --mismatch {args.mismatch} in [0, 100)")
    torch_one_thread()
    os.makedirs(args.out_dir, exist_ok=True)
    start, load_start = time.perf_counter(), os.getloadavg()[0]
    oracle = make_cases(args.out_dir, args.n, args.seed, args.n_per_condition)
    levels = study_levels(args.noise, args.mismatch)
    jobs = [(level, args.out_dir, args.epochs, args.n, args.seed, args.mismatch_seed) for level in levels]
    with ProcessPoolExecutor(args.jobs, mp_context=multiprocessing.get_context("spawn")) as pool:
        futures = [pool.submit(train_and_score, *job) for job in jobs]
        results = []
        for level, future in zip(levels, futures):
            results.append(future.result())
            print(f"{level.name}: {results[-1]['seconds']:.0f} s", flush=True)
    meta = {"command": "python tools/robustness.py " + " ".join(argv if argv is not None else _argv()),
            "epochs": args.epochs, "n": args.n, "n_per_condition": args.n_per_condition,
            "minutes": (time.perf_counter() - start) / 60, "load_start": load_start, "load_end": os.getloadavg()[0]}
    _write(os.path.join(args.out_dir, "robustness.json"),
           json.dumps({"meta": meta, "oracle": oracle, "results": results}, indent=1, sort_keys=True))
    write_report(args.out_dir)


def write_report(out_dir: str) -> None:
    """robustness.md and robustness.png from robustness.json."""
    path = os.path.join(out_dir, "robustness.json")
    if not os.path.isfile(path):
        raise BodySchemaInputError(f"{path} does not exist: run the study first (without --report-only)")
    with open(path) as fh:
        saved = json.load(fh)
    table = markdown(saved["results"], saved["oracle"], saved["meta"])
    _write(os.path.join(out_dir, "robustness.md"), table)
    figure(saved["results"], saved["oracle"], os.path.join(out_dir, "robustness.png"))
    print(table)
    print(f"wrote {out_dir}/robustness.md, .png ({saved['meta']['minutes']:.1f} min study)")


def _argv():
    import sys

    return sys.argv[1:]


def _write(path: str, text: str) -> None:
    from ..npz import atomic_write_bytes

    atomic_write_bytes(path, text.encode())
