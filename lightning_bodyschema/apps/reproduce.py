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

from .._numpy import to_numpy
from ..evaluation import oracle_commands, oracle_scores, run_fault_benchmark
from ..evaluation.cases import PROTOCOLS
from ..faults import Faults
from .case_tools import draw_cases
from .results_figures import write_figures
from .results_md import write_results_md
# re-exported: the tables, claims and figures are importable from this module too
from .results_figures import TIMING_FORMATS, timing_figure  # noqa: F401
from .results_md import (BINDING_COLUMNS, BINDING_CONDS, CONDS, FAULT_METRICS, HAND_WRITTEN,  # noqa: F401
                         PAPER_COLUMNS, TARGETS, UNITS, binding_claims, claims, results_table)

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


# relative CPU cost of one training epoch per schema family (paper configs, one thread), VAE = 1; the per-epoch
# times behind it are in BENCHMARKS.md (full reproduction)
_EPOCH_COST = {"vae": 1.0, "ae": 0.89, "diff": 0.73}


def train_all(specs: list[RunSpec], config_dir: str, cache_dir: str, jobs: int = 2, log=print,
              when_idle=None) -> dict[str, str]:
    """Train every spec without a checkpoint on ``jobs`` slots; return name -> checkpoint.

    The runs are split into one queue per slot so that the longest queue is as short as possible by the
    expected cost (``_EPOCH_COST``): on two slots the paper's 7 runs become VAE-3/10/30 and AE-3/10/30 + Diff,
    shorter than handing the next run to whichever slot frees first. Where ``os.fork`` exists each
    training is a forked child that runs the CLI in-process: it inherits the already imported torch and
    Lightning (no import per run); elsewhere a ``bodyschema fit`` subprocess.
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

        q_pool, x_pool = (to_numpy(t) for t in load_datamodule(checkpoint).splits["val"])
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
    print("fault benchmark of the trained schemas (paper and binding cases), timings, figures: about half a minute "
          "on 2 cores", flush=True)
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
