"""Reproduce the paper's experiment: train the 7 schemas, benchmark them under faults, write figures and RESULTS.md.

    python tools/reproduce_paper.py                 # full: 10000 epochs each, 2 parallel trainings
    python tools/reproduce_paper.py --epochs 1000   # shorter

Training runs ``bodyschema fit`` in parallel processes with one torch thread each (two single-thread
processes beat one two-thread process on this machine), split into balanced queues; a core that has no
training left benchmarks the schemas already trained. Existing checkpoints of the same settings are reused.
"""
from __future__ import annotations

import glob
import itertools
import json
import os
import statistics
import subprocess
import sys
import time
from dataclasses import dataclass

import numpy as np
import torch

from ..evaluation import oracle_commands, oracle_scores, run_fault_benchmark
from ..evaluation.benchmark import ACTIVE_CUT_N, ACTIVE_FIX_M
from ..evaluation.cases import PROTOCOLS
from ..faults import Faults
from .case_tools import draw_cases

MODELS = {"AE-3": "ae-3", "AE-10": "ae-10", "AE-30": "ae-30", "VAE-3": "vae-3", "VAE-10": "vae-10",
          "VAE-30": "vae-30", "Diff": "diff"}
TIMED = ("AE-10", "VAE-10", "Diff")  # the paper's inference-time figure
PAPER_SECONDS = {"unadapted": {"AE-10": 0.001, "VAE-10": 0.001, "Diff": 0.1}, "adapted": 0.7}


@dataclass
class RunSpec:
    name: str
    config: str
    run_dir: str
    epochs: int

    def checkpoint(self) -> str | None:
        found = sorted(glob.glob(os.path.join(self.run_dir, "lightning_logs", "version_*", "checkpoints",
                                              f"epoch={self.epochs - 1}-*.ckpt")))
        return found[-1] if found else None

    def command(self, config_dir: str, cache_dir: str) -> list[str]:
        return [sys.executable, "-m", "lightning_bodyschema.cli", "fit",
                "--config", os.path.join(config_dir, f"{self.config}.yaml"),
                f"--trainer.max_epochs={self.epochs}", f"--trainer.default_root_dir={self.run_dir}",
                f"--trainer.check_val_every_n_epoch={max(1, min(500, self.epochs))}",
                "--faults.every_n_epochs=0", "--progress.enabled=false",
                f"--data.cache_dir={cache_dir}"]


# relative seconds per epoch on one thread (1000-epoch fits, paper configs): VAE 16.8 ms, AE 15.0, Diff 12.2
_EPOCH_COST = {"vae": 1.0, "ae": 0.89, "diff": 0.73}


def train_all(specs: list[RunSpec], config_dir: str, cache_dir: str, jobs: int = 2, log=print,
              when_idle=None) -> dict[str, str]:
    """Train every spec without a checkpoint on ``jobs`` slots; return name -> checkpoint.

    The runs are split into one queue per slot so that the longest queue is as short as possible by the
    expected cost (``_EPOCH_COST``): on two slots the paper's 7 runs become VAE-3/10/30 and AE-3/10/30 + Diff,
    ~35 s shorter than handing the next run to whichever slot frees first. Where ``os.fork`` exists each
    training is a forked child that runs the CLI in-process: it inherits the already imported torch and
    Lightning (~5 s of imports per run saved); elsewhere a ``bodyschema fit`` subprocess.
    ``when_idle(name, checkpoint)``: called for each finished run while a slot has nothing left to train
    (the tail of the schedule, when a core would idle), so its benchmark overlaps the last trainings.
    """
    queues = _balanced_queues([s for s in specs if s.checkpoint() is None], jobs)
    finished = [s for s in specs if s.checkpoint() is not None]
    running: dict[int, tuple[RunSpec, object, float]] = {}
    while any(queues) or running:
        for slot, queue in enumerate(queues):
            if slot not in running and queue:
                spec = queue.pop(0)
                os.makedirs(spec.run_dir, exist_ok=True)
                running[slot] = (spec, _start_training(spec, config_dir, cache_dir), time.perf_counter())
                log(f"training {spec.name} ({spec.epochs} epochs) -> {spec.run_dir}")
        if when_idle is not None and finished and len(running) < jobs:
            spec = finished.pop(0)
            when_idle(spec.name, spec.checkpoint())
            continue
        time.sleep(0.5)
        for slot, (spec, proc, start) in list(running.items()):
            code = _poll(proc)
            if code is not None:
                del running[slot]
                if code != 0:
                    raise RuntimeError(f"training {spec.name} failed; see {spec.run_dir}/fit.log")
                log(f"trained {spec.name} in {time.perf_counter() - start:.0f} s")
                finished.append(spec)
    return {s.name: s.checkpoint() for s in specs}


def _expected_cost(spec: RunSpec) -> float:
    return spec.epochs * _EPOCH_COST.get(spec.config.split("-")[0], 1.0)


def _balanced_queues(specs: list[RunSpec], jobs: int) -> list[list[RunSpec]]:
    """``jobs`` queues minimising the largest total expected cost: exhaustively for small cases (2 slots, 7
    runs: 128 splits), else longest-first onto the emptiest queue. Each queue runs longest first."""
    jobs = max(1, min(jobs, len(specs) or 1))
    costs = [_expected_cost(s) for s in specs]
    if jobs ** len(specs) <= 50_000:
        best = min(itertools.product(range(jobs), repeat=len(specs)),
                   key=lambda a: max(sum(c for c, k in zip(costs, a) if k == q) for q in range(jobs)))
    else:
        totals, best = [0.0] * jobs, [0] * len(specs)
        for i in sorted(range(len(specs)), key=lambda i: -costs[i]):
            best[i] = totals.index(min(totals))
            totals[best[i]] += costs[i]
    queues = [[s for s, k in zip(specs, best) if k == q] for q in range(jobs)]
    return [sorted(q, key=lambda s: -_expected_cost(s)) for q in queues]


def _start_training(spec: RunSpec, config_dir: str, cache_dir: str):
    """A forked child running ``bodyschema fit`` in-process (its pid), or a subprocess without fork."""
    argv = spec.command(config_dir, cache_dir)
    with open(os.path.join(spec.run_dir, "fit.log"), "w") as logfile:
        if not hasattr(os, "fork"):
            env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
            return subprocess.Popen(argv, stdout=logfile, stderr=subprocess.STDOUT, env=env)
        from .. import cli  # imported once here, before forking: the children inherit it

        sys.stdout.flush()
        sys.stderr.flush()
        pid = os.fork()
        if pid:
            return pid
        code = 1
        try:  # the child: never returns into the parent's code
            os.dup2(logfile.fileno(), 1)
            os.dup2(logfile.fileno(), 2)
            cli.main(argv[argv.index("fit"):])
            code = 0
        except SystemExit as stop:
            code = stop.code if isinstance(stop.code, int) else 1
        except BaseException:
            import traceback

            traceback.print_exc()
        finally:
            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(code)


def _poll(proc) -> int | None:
    """Exit code of a finished training (fork pid or Popen), else None."""
    if isinstance(proc, int):
        pid, status = os.waitpid(proc, os.WNOHANG)
        return None if pid == 0 else os.waitstatus_to_exitcode(status)
    return proc.poll()


class Benchmarker:
    """The same seeded case sets for every schema (they share one dataset): the paper's protocol and the binding
    one (``evaluation.make_binding_cases``), each with its physics oracle scored once; ``run(name, checkpoint)``
    loads and benchmarks one schema on both, ``results[protocol]``/``schemas`` collect them."""

    def __init__(self, n_per_condition: int = 40, seed: int = 0, variant: str = "default",
                 binding_n_per_condition: int = 40):
        self.n_per_condition, self.seed, self.variant = n_per_condition, seed, variant
        self.binding_n_per_condition = binding_n_per_condition
        self.cases, self.oracles, self.rejected = {}, {}, None
        self.results, self.schemas = {p: {} for p in PROTOCOLS}, {}

    def _draw(self, checkpoint: str, schema):
        from ..schemas import load_datamodule

        q_pool, x_pool = (t.numpy() for t in load_datamodule(checkpoint).splits["val"])
        for protocol in PROTOCOLS:
            n = self.binding_n_per_condition if protocol == "binding" else self.n_per_condition
            self.cases[protocol], rejected = draw_cases(protocol, schema.robot_model, schema.spring, q_pool, x_pool,
                                                        n, self.seed)
            self.rejected = rejected or self.rejected
            self.oracles[protocol] = oracle_scores(schema.robot_model, schema.spring, self.cases[protocol],
                                                   settle_check=True)

    def run(self, name: str, checkpoint: str):
        from ..schemas import load_schema

        schema = load_schema(checkpoint)
        if not self.cases:
            self._draw(checkpoint, schema)
        self.schemas[name] = schema
        for protocol, cases in self.cases.items():
            self.results[protocol][name] = run_fault_benchmark(
                schema.robot_model, schema.spring, cases, schema.infer,
                lambda q, f: schema.adapt(q, f, variant=self.variant, check_physics=False), settle_check=True,
                oracle=self.oracles[protocol])


def benchmark_all(checkpoints: dict[str, str], n_per_condition: int = 40, seed: int = 0, variant: str = "default",
                  bench: Benchmarker | None = None):
    """Benchmark every checkpoint not yet in ``bench``; returns ({protocol: {name: BenchmarkResult}},
    {protocol: cases}, {name: schema}), names in the order of ``checkpoints``."""
    bench = bench or Benchmarker(n_per_condition, seed, variant)
    for name, path in checkpoints.items():
        if name not in bench.schemas:
            bench.run(name, path)
    names = list(checkpoints)
    results = {protocol: {n: by_name[n] for n in names} for protocol, by_name in bench.results.items()}
    return results, bench.cases, {n: bench.schemas[n] for n in names}


def _one_both_case(cases):
    both = np.flatnonzero(cases.cond == "BOTH")[:1]
    return cases.q_ref[both], Faults(cases.cut[both], cases.fix[both], cases.l_fixed[both]), cases.take(both)


def time_inference(schemas: dict, cases, repeats: int = 7) -> dict:
    """Median seconds per call for one BOTH case, with and without adaptation (paper Fig. exp-time)."""
    q, faults, _ = _one_both_case(cases)
    out = {}
    for name in TIMED:
        schema = schemas[name]
        out[name] = {"unadapted": _median_seconds(lambda: schema.infer(q), repeats),
                     "adapted": _median_seconds(lambda: schema.adapt(q, faults, check_physics=False), repeats)}
    return out


def time_oracle(schema, cases, repeats: int = 7) -> float:
    """Median seconds of the physics oracle (``oracle_commands``: feasibility QP + spring) for the same BOTH case."""
    _, _, one = _one_both_case(cases)
    return _median_seconds(lambda: oracle_commands(schema.robot_model, one, schema.spring), repeats)


def _median_seconds(fn, repeats):
    fn()  # warm-up
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


TIMING_FORMATS = {"unadapted": "%.3f", "adapted": "%.1f", "oracle": "%.3f"}  # the RESULTS.md table's precision


def timing_figure(timings: dict, oracle_s: float | None = None):
    """Bars of milliseconds per case with and without adaptation per schema, and the physics oracle's, labelled
    with the precision of the RESULTS.md table."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.6, 3.6))
    names = list(timings)
    width = 0.38
    for k, (kind, color) in enumerate((("unadapted", "tab:gray"), ("adapted", "tab:blue"))):
        values = [1e3 * timings[n][kind] for n in names]
        bars = ax.bar(np.arange(len(names)) + (k - 0.5) * width, values, width, label=f"{kind} (ours)", color=color)
        ax.bar_label(bars, fmt=TIMING_FORMATS[kind], fontsize=7)
    ticks = list(names)
    if oracle_s is not None:
        bars = ax.bar([len(names)], [1e3 * oracle_s], width, color="k", label="physics oracle (exact model)")
        ax.bar_label(bars, fmt=TIMING_FORMATS["oracle"], fontsize=7)
        ticks.append("oracle")
    ax.axhline(700, color="tab:red", ls="--", lw=1, label="paper, adapted (0.7 s)")
    ax.set_xticks(np.arange(len(ticks)), ticks)
    ax.set_yscale("log")
    ax.set_xlabel("schema (one BOTH case, CPU, one thread)")
    ax.set_ylabel("ms per case (median)")
    ax.set_title("Inference time with and without adaptation")
    ax.legend(fontsize=7)
    fig.tight_layout()
    return fig


# ---------------------------------------------------------------------------------------------- RESULTS.md
TARGETS = {"E_cut": 1.0, "E_fix": 1e-3, "E_tau": 0.5, "E_q": 0.01}  # issue acceptance, SI units
UNITS = {"E_cut": ("N", 1.0), "E_fix": ("mm", 1e3), "E_weak": ("N", 1.0), "E_band": ("mm", 1e3),
         "E_tau": ("N m", 1.0), "E_q": ("rad", 1.0), "E_q_phys": ("rad", 1.0)}
CONDS = ("CUT", "FIX", "BOTH")
BINDING_CONDS = ("CUT", "FIX", "BOTH", "WEAK", "BAND")
PAPER_COLUMNS = ("E_cut", "E_fix", "E_tau", "E_q", "E_q_phys")
BINDING_COLUMNS = ("E_cut", "E_fix", "E_weak", "E_band", "E_tau", "E_q", "E_q_phys")
# what each binding condition's fault is scored by (beside E_tau, E_q and E_q_phys, which every condition has)
FAULT_METRICS = {"CUT": ("E_cut",), "FIX": ("E_fix",), "BOTH": ("E_cut", "E_fix"), "WEAK": ("E_weak",),
                 "BAND": ("E_band",)}
HAND_WRITTEN = "<!-- Hand-written sections below: tools/reproduce_paper.py keeps everything after this line. -->"


def _med(result, metric, cond, reading="phys", subset="feasible", kind="adapted"):
    value = result.summary()[kind][reading][cond][subset].get(metric)
    return np.nan if value is None else value


def _fmt(value, metric):
    unit, scale = UNITS[metric]
    return "—" if not np.isfinite(value) else f"{value * scale:.3g}"


def results_table(results: dict, reading: str, subset: str, conds=CONDS, columns=PAPER_COLUMNS) -> str:
    """Medians per condition: the unadapted command (of Diff) and the physics oracle as reference rows, then
    every schema's adapted command."""
    header = " | ".join(f"{m} [{UNITS[m][0]}]" for m in columns)
    rows = [f"| model | cond | n | {header} |", "|---|---|---|" + "---|" * len(columns)]
    reference = results.get("Diff", next(iter(results.values())))
    named = [("unadapted (Diff)", reference, "unadapted"), ("oracle", reference, "oracle")]
    named = [row for row in named if row[2] in reference.metrics] + [(n, r, "adapted") for n, r in results.items()]
    for name, result, kind in named:
        for cond in conds:
            n = result.summary()[kind][reading][cond][subset]["n"]
            cells = [_fmt(_med(result, m, cond, reading, subset, kind), m) for m in columns]
            rows.append(f"| {name} | {cond} | {n} | " + " | ".join(cells) + " |")
    return "\n".join(rows)


def claims(results: dict, timings: dict) -> list[tuple[str, str, str]]:
    """(claim, verdict, evidence) for each of the paper's conclusions, from our numbers."""
    out = []
    diff_ok = {(m, c): _med(results["Diff"], m, c) for m in TARGETS for c in CONDS}  # feasible cases
    met = all(not np.isfinite(v) or v <= TARGETS[m] for (m, c), v in diff_ok.items())
    out.append(("Diff adapts stably across all metrics and conditions (feasible cases; targets E_cut <= 1 N, "
                "E_fix <= 1 mm, E_tau <= 0.5 N m, E_q <= 0.01 rad)", "confirmed" if met else "refuted",
                ", ".join(f"{m} {c} {_fmt(v, m)}" for (m, c), v in diff_ok.items() if np.isfinite(v))))
    out.append(_beats_unadapted(results["Diff"]))
    out.append(_worse_claim(results, "AE-10 and AE-30 are weak on E_fix", ("AE-10", "AE-30"), "E_fix", ("FIX", "BOTH"),
                            ("VAE-3", "VAE-10", "VAE-30", "Diff")))
    out.append(_worse_claim(results, "VAE schemas are weak on E_cut", ("VAE-3", "VAE-10", "VAE-30"), "E_cut",
                            ("CUT", "BOTH"), ("AE-10", "AE-30", "Diff")))
    wins = [(m, c) for m in ("E_tau", "E_q") for c in CONDS
            if _med(results["VAE-10"], m, c) < min(_med(results["VAE-3"], m, c), _med(results["VAE-30"], m, c))]
    out.append(("VAE-10 is the best VAE latent size (E_tau, E_q)", "confirmed" if len(wins) >= 4 else "refuted",
                f"VAE-10 best in {len(wins)} of 6 (metric, condition) pairs: {wins}"))
    out.extend(_timing_claims(timings))
    return out


def _beats_unadapted(result):
    """Adapted vs healthy command on feasible cases where the healthy command breaks the fault the metric
    measures (E_cut: a cut muscle pulls; E_fix: a jammed motor is too long; E_tau, E_q: either)."""
    plain, adapted = result.metrics["unadapted"]["phys"], result.metrics["adapted"]["phys"]
    breaks = {"E_cut": np.nan_to_num(plain["E_cut"]) > 0.5, "E_fix": np.nan_to_num(plain["E_fix"]) > 1e-4}
    breaks["E_tau"] = breaks["E_q"] = breaks["E_cut"] | breaks["E_fix"]
    pairs = []
    for m in TARGETS:
        for c in CONDS:
            rows = (result.cases.cond == c) & result.feasible["phys"] & breaks[m]
            if rows.any():
                pairs.append((m, c, int(rows.sum()), np.nanmedian(adapted[m][rows]), np.nanmedian(plain[m][rows])))
    better = [p for p in pairs if p[3] < p[4]]
    return ("Diff adaptation beats the unadapted command on every metric (feasible cases whose healthy command "
            "breaks the fault)", "confirmed" if len(better) == len(pairs) else f"{len(better)} of {len(pairs)}",
            ", ".join(f"{m} {c} (n={n}) {_fmt(a, m)} vs {_fmt(u, m)}" for m, c, n, a, u in pairs))


def binding_claims(results: dict) -> list[tuple[str, str, str]]:
    """The paper's "adapted beats unadapted" judged on the binding set, where every case has a physical solution
    and the healthy command breaks every fault: per schema, the (condition, metric) pairs where the adapted
    median is below the unadapted one; metrics: the condition's fault metric, E_tau, E_q and E_q_phys. A pair
    whose unadapted median is already the oracle's (the physical limit) cannot be beaten and is left out."""
    out = []
    for name, result in results.items():
        pairs, at_limit = [], []
        for c in BINDING_CONDS:
            for m in FAULT_METRICS[c] + ("E_tau", "E_q", "E_q_phys"):
                adapted, plain = _med(result, m, c, subset="all"), _med(result, m, c, subset="all", kind="unadapted")
                limit = _med(result, m, c, subset="all", kind="oracle") if "oracle" in result.metrics else np.nan
                if np.isfinite(adapted) and np.isfinite(plain):
                    (at_limit if plain <= limit + 1e-9 else pairs).append((c, m, adapted, plain))
        lost = [p for p in pairs if not p[2] < p[3]]
        verdict = "confirmed" if not lost else f"{len(pairs) - len(lost)} of {len(pairs)}"
        evidence = ("not better in: " + ", ".join(f"{m} {c} {_fmt(a, m)} vs {_fmt(u, m)}" for c, m, a, u in lost)
                    if lost else "better in every pair")
        if at_limit:
            evidence += "; unadapted already at the oracle's limit in " + ", ".join(f"{m} {c}" for c, m, *_ in at_limit)
        out.append((f"{name} adaptation beats the unadapted command (binding set, all metrics)", verdict, evidence))
    return out


def _worse_claim(results, claim, weak, metric, conds, others):
    """Weak = every 'weak' model's median (all cases) is above every other model's, in every condition."""
    pairs = [(c, max(_med(results[w], metric, c, subset="all") for w in weak),
              min(_med(results[o], metric, c, subset="all") for o in others)) for c in conds]
    holds = all(worst_weak > best_other for c, worst_weak, best_other in pairs if np.isfinite(worst_weak))
    evidence = "; ".join(f"{c}: weak models' best {_fmt(min(_med(results[w], metric, c, subset='all') for w in weak), metric)}"
                         f" vs others' {_fmt(b, metric)}" for c, _, b in pairs)
    return claim, "confirmed" if holds else "refuted", evidence


def _timing_claims(timings):
    ae_vae = max(timings[n]["unadapted"] for n in ("AE-10", "VAE-10"))
    adapted = {n: t["adapted"] for n, t in timings.items()}
    return [("AE/VAE inference without adaptation < 1 ms", "confirmed" if ae_vae < 1e-3 else "refuted",
             f"slowest {1e3 * ae_vae:.3f} ms"),
            ("Diff inference without adaptation ~0.1 s", "ours faster", f"{1e3 * timings['Diff']['unadapted']:.1f} ms"),
            ("Adaptation ~0.7 s for all three", "ours faster",
             ", ".join(f"{n} {1e3 * v:.1f} ms" for n, v in adapted.items()))]


def _hand_written_tail(path) -> list[str]:
    """The hand-written sections of an existing RESULTS.md (after ``HAND_WRITTEN``), kept across regenerations."""
    if not os.path.isfile(path):
        return []
    text = open(path, encoding="utf-8").read()
    return ["", HAND_WRITTEN, ""] + text.split(HAND_WRITTEN, 1)[1].strip("\n").split("\n") if HAND_WRITTEN in text else []


def write_results_md(path, results, timings, command, epochs, n_cases, literal_ok=None, binding=None,
                     oracle_s=None, rejected=None):
    """RESULTS.md from the paper-protocol ``results`` and the ``binding`` ones ({name: BenchmarkResult})."""
    lines = ["# Results: reproduction of Kawaharazuka & Ikemoto on the paper arm", "",
             f"Produced by `{command}` ({epochs} epochs per schema, {n_cases} fault cases of the paper's protocol"
             + (f" and {len(next(iter(binding.values())).cases)} of the binding protocol" if binding else "")
             + f", {time.strftime('%Y-%m-%d')}). Medians; E_fix and E_band in mm.", "",
             "Two readings of E_tau/E_q: **phys** (a jammed muscle still pulls with the tension of its stretch) and "
             "**paper** (the paper's taut set excludes jammed muscles, so their pull is left out of the torque "
             "balance; a physically exact command then scores several N m under FIX). Subsets: **all** cases; "
             "**feasible**, the cases that have a physical solution under the same reading (the feasibility QP); "
             f"**feasible_active**, the feasible cases whose unadapted (healthy) command breaks a fault, i.e. a cut "
             f"muscle pulls with more than {ACTIVE_CUT_N:g} N or a jammed motor is more than {1e3 * ACTIVE_FIX_M:g} mm "
             "too long (elsewhere adaptation has nothing to fix and can only tie).", "",
             "Two case protocols. **paper**: 40 CUT (2 cut), FIX (2 jammed) and BOTH (1 + 1) cases, l_fixed the "
             "motor length of a random other posture, as in the paper; most FIX cases are infeasible or already met "
             "by the healthy command. **binding** (`tools/make_cases.py --protocol binding`): CUT, FIX, BOTH, WEAK (1 "
             "weakened) and BAND (1 length-banded) cases that all have a physical solution and in which the healthy "
             "command breaks every fault (a cut muscle pulls, a jammed motor must pay out >= 0.5 mm, a weakened "
             "muscle is over its new limit, a banded motor is >= 0.5 mm outside its band): there adaptation always "
             "has work to do.", "",
             "Reference rows: **unadapted** is the Diff schema's healthy command; **oracle** is the command the true "
             "physics gives for the faults (the feasibility QP's tensions nearest the healthy ones, lengths from the "
             "spring), scored by the same evaluator. It is the physical limit of every metric (0 up to round-off on "
             "feasible cases) and what a user with an exact model of the robot would run instead of a schema.", "",
             "| paper protocol (phys reading, feasible cases) | binding protocol (phys reading, all cases) |",
             "|---|---|",
             "| ![paper protocol](docs/paper_boxplots.png) | ![binding protocol](docs/binding_boxplots.png) |", "",
             "The paper's own metric definitions (paper reading, all cases, the paper's protocol): "
             "[docs/paper_boxplots_paper_reading.png](docs/paper_boxplots_paper_reading.png).", "",
             "![inference time](docs/paper_timing.png)", "",
             "## Claims", "", "| paper's claim | our verdict | evidence |", "|---|---|---|"]
    lines += [f"| {c} | {v} | {e} |" for c, v, e in claims(results, timings)]
    if binding:
        lines += ["", "### Adapted vs unadapted where the faults bind (binding protocol)", "",
                  "Per schema, the (condition, metric) pairs whose adapted median is below the unadapted one; metrics: "
                  "the condition's own fault metric (E_cut, E_fix, E_weak, E_band), E_tau, E_q and E_q_phys; medians "
                  "over all binding cases (every one feasible and binding).", "",
                  "| claim | verdict | evidence |", "|---|---|---|"]
        lines += [f"| {c} | {v} | {e} |" for c, v, e in binding_claims(binding)]
    if literal_ok is not None:
        lines += ["", f"The literal recipe (SI-unit loss, lr 0.01, no step scaling) returned a finite command for "
                      f"{literal_ok:.0%} of the Diff cases; the rest diverged to NaN and were reported `non_finite`."]
    if binding:
        lines += ["", "## Binding protocol: medians, reading `phys`, all cases (every case feasible)", "",
                  results_table(binding, "phys", "all", BINDING_CONDS, BINDING_COLUMNS)]
        if rejected:
            lines += ["", "Draws the binding protocol rejected (why): " + "; ".join(
                f"{c} " + ", ".join(f"{r} {k}" for r, k in reasons.items()) for c, reasons in rejected.items()) + "."]
    for reading, subset in (("phys", "feasible"), ("phys", "feasible_active"), ("phys", "all"),
                            ("paper", "feasible"), ("paper", "all")):
        lines += ["", f"## Paper protocol: medians, reading `{reading}`, {subset} cases", "",
                  results_table(results, reading, subset)]
    lines += ["", "## Inference time (one BOTH case, CPU, one thread; median)", "",
              "| model | without adaptation [ms] | with adaptation [ms] | paper with adaptation |", "|---|---|---|---|"]
    lines += [f"| {n} | {1e3 * t['unadapted']:.3f} | {1e3 * t['adapted']:.1f} | ~700 ms |" for n, t in timings.items()]
    if oracle_s is not None:
        lines += [f"| oracle (feasibility QP + spring, exact model) | — | {1e3 * oracle_s:.3f} | — |"]
    lines += _hand_written_tail(path)
    from ..npz import atomic_write_bytes

    atomic_write_bytes(path, ("\n".join(lines) + "\n").encode())


def main(argv=None):
    import argparse

    # the repository (configs/): lightning_bodyschema/apps/reproduce.py is two packages down
    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    parser = argparse.ArgumentParser(description="Train the paper's 7 schemas, benchmark them, write figures and RESULTS.md.")
    parser.add_argument("--epochs", type=int, default=None, help="epochs per schema (paper: 10000; --quick: 1000)")
    parser.add_argument("--quick", action="store_true",
                        help="a few-minute run: 1000 epochs; everything (checkpoints, dataset cache, RESULTS.md, "
                             "figures) under runs/quick, the repository's RESULTS.md untouched")
    parser.add_argument("--jobs", type=int, default=2, help="parallel training processes (one thread each)")
    parser.add_argument("--runs-dir", default=None,
                        help="where checkpoints go, reused when present (default runs/paper; --quick: the --out folder)")
    parser.add_argument("--n-per-condition", type=int, default=40, help="paper-protocol cases per condition")
    parser.add_argument("--binding-n-per-condition", type=int, default=40,
                        help="binding-protocol cases per condition (5 conditions; default 40)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default=".", help="folder for RESULTS.md, results.json and docs/*.png")
    parser.add_argument("--models", nargs="*", default=list(MODELS), choices=list(MODELS))
    args = parser.parse_args(argv)
    if args.quick:  # one run, one folder: its checkpoints beside its RESULTS.md and figures
        args.out = args.out if args.out != "." else "runs/quick"
        args.runs_dir = args.runs_dir or args.out
    default_epochs = 1000 if args.quick else 10000
    args.epochs = default_epochs if args.epochs is None else args.epochs
    args.runs_dir = args.runs_dir or "runs/paper"
    torch.set_num_threads(1)
    torch.set_flush_denormal(True)
    start = time.perf_counter()
    specs = [RunSpec(n, MODELS[n], os.path.join(args.runs_dir, f"{MODELS[n]}-{args.epochs}"), args.epochs)
             for n in args.models]
    bench = Benchmarker(args.n_per_condition, args.seed, binding_n_per_condition=args.binding_n_per_condition)
    checkpoints = train_all(specs, os.path.join(root, "configs"), os.path.join(args.runs_dir, "cache"), args.jobs,
                            when_idle=bench.run)
    trained = time.perf_counter()
    by_protocol, case_sets, schemas = benchmark_all(checkpoints, bench=bench)
    results, binding, cases = by_protocol["paper"], by_protocol["binding"], case_sets["paper"]
    timings = time_inference(schemas, cases) if set(TIMED) <= set(schemas) else {}
    oracle_s = time_oracle(next(iter(schemas.values())), cases)
    literal = (schemas["Diff"].adapt(cases.q_ref, cases.faults, variant="literal", check_physics=False)
               if "Diff" in schemas else None)
    write_figures(args.out, results, binding, timings, oracle_s)
    command = ("python tools/reproduce_paper.py" + (" --quick" if args.quick else "")
               + (f" --epochs {args.epochs}" if args.epochs != default_epochs else ""))
    if set(MODELS) <= set(results):
        write_results_md(os.path.join(args.out, "RESULTS.md"), results, timings, command, args.epochs, len(cases),
                         None if literal is None else float(np.mean(literal.status == "ok")), binding, oracle_s,
                         bench.rejected)
    summary = {"epochs": args.epochs, "n_cases": len(cases), "n_binding_cases": len(case_sets["binding"]),
               "timings_s": timings, "oracle_s": oracle_s,
               "summary": {name: r.summary() for name, r in results.items()},
               "binding_summary": {name: r.summary() for name, r in binding.items()},
               "seconds": {"train": trained - start, "total": time.perf_counter() - start}}
    from ..npz import atomic_write_bytes

    atomic_write_bytes(os.path.join(args.out, "results.json"), json.dumps(summary, indent=1, sort_keys=True).encode())
    print(f"done in {time.perf_counter() - start:.0f} s (training {trained - start:.0f} s); "
          f"wrote {os.path.join(args.out, 'RESULTS.md')}")


def write_figures(out: str, results: dict, binding: dict, timings: dict, oracle_s: float):
    """docs/paper_boxplots.png (phys reading, feasible cases: what the claims use), paper_boxplots_paper_reading.png
    (the paper's definitions, all cases), binding_boxplots.png (binding protocol) and paper_timing.png; each box
    plot has the unadapted command and the physics oracle as reference boxes."""
    from ..plots.arm import save_figure_atomic
    from ..plots.boxplots import fault_boxplots

    os.makedirs(os.path.join(out, "docs"), exist_ok=True)
    for name, by_name, reading, subset, what in (
            ("paper_boxplots", results, "phys", "feasible", "paper protocol"),
            ("paper_boxplots_paper_reading", results, "paper", "all", "paper protocol, the paper's metric definitions"),
            ("binding_boxplots", binding, "phys", "all", "binding protocol (every case feasible, every fault binding)")):
        reference = by_name.get("Diff", next(iter(by_name.values())))
        fig = fault_boxplots(by_name, reading=reading, subset=subset,
                             references={"unadapted (Diff)": (reference, "unadapted"), "oracle": (reference, "oracle")},
                             title=f"Fault benchmark, {what}: adapted commands, {reading} reading, {subset} cases")
        save_figure_atomic(fig, os.path.join(out, "docs", f"{name}.png"))
    if timings:
        save_figure_atomic(timing_figure(timings, oracle_s), os.path.join(out, "docs", "paper_timing.png"))
