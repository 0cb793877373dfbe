"""The paper's fault benchmark (section IV-B) as a Lightning callback: TensorBoard during fit, files at test.

No maths here: the cases come from ``evaluation.make_fault_cases``, the scores from
``evaluation.run_fault_benchmark``, the figure from ``plots.fault_boxplots``; this module only
schedules, logs and writes.

Logged during fit (step = epoch), medians over each condition's cases; units: E_cut [N],
E_fix_mm [mm], E_tau [N m], E_q [rad] and E_q_phys [rad] (the MuJoCo settle check beside the Gauss-Newton
E_q; ``settle_check``, on by default); ``{reading}`` is ``paper`` or ``phys`` (see
``evaluation.benchmark``), ``{subset}`` is ``all`` or ``feasible``:

    fault/{reading}/{cond}/{metric}_{subset}              adapted commands, e.g. fault/phys/CUT/E_cut_feasible
    fault_unadapted/{reading}/{cond}/{metric}_{subset}    the healthy command at the same cases (baseline)
    fault_oracle/{reading}/{cond}/{metric}_{subset}       the physics oracle (test only: a constant of the cases)
    fault/{reading}/{cond}/n_feasible                     cases with a physical solution
    {prefix}/{reading}/{cond}/n_unsettled_{subset}        settle runs never at rest (still moving at max_time_s or
                                                          blown up): left out of E_q_phys, counted here
    fault/adapt_ok_fraction, fault/adapt_seconds, fault/infer_seconds, fault/evaluate_seconds
    fault/boxplots                                        figure: phys reading, all cases, unadapted vs adapted

A median over an empty set (E_fix under CUT, E_cut under FIX, no feasible case) is not logged.

At test (``bodyschema test --config X --ckpt_path Y``) it benchmarks every protocol of ``protocols``
(default the paper's cases and the binding ones, ``evaluation.make_binding_cases``) and writes, per protocol,
``fault_benchmark{suffix}.json`` (summary, per-case arrays, cases, feasibility; deterministic: identical bytes
on rerun) and ``fault_benchmark{suffix}.md`` (the median table with one row per command: adapted, unadapted and
the physics oracle, and the wall times, which are not in the JSON because they differ from run to run) to
``out_dir`` or the trainer's log folder; suffix "" for paper, "_binding" for binding. It prints the phys-reading
table of each protocol.
"""
from __future__ import annotations

import hashlib
import json
import math
import os
from typing import Optional

import numpy as np
import torch
from lightning.pytorch.callbacks import Callback
from lightning.pytorch.trainer.states import TrainerFn
from lightning.pytorch.utilities import rank_zero_info, rank_zero_only, rank_zero_warn

from ..errors import BodySchemaInputError
from ..evaluation import BenchmarkResult, make_fault_cases, run_fault_benchmark
from ..evaluation.benchmark import COMMANDS, SUMMARY_METRICS
from ..evaluation.cases import PROTOCOLS, HealthyPool, make_binding_cases
from ..npz import atomic_write_bytes
from ..training.fit_loop import fit_ends_with_this_epoch
from ..variants import check_variant
from .steps import averaged_weights_now, stopped_after_last_validation, validation_log_step

CONDITION_ORDER = ("CUT", "FIX", "BOTH", "WEAK", "BAND")
METRIC_KEYS = {"E_cut": ("E_cut", 1.0), "E_fix": ("E_fix_mm", 1e3), "E_tau": ("E_tau", 1.0), "E_q": ("E_q", 1.0),
               "E_weak": ("E_weak", 1.0), "E_band": ("E_band_mm", 1e3), "E_q_phys": ("E_q_phys", 1.0)}
METRIC_HEADERS = {"E_cut": "E_cut [N]", "E_fix": "E_fix [mm]", "E_tau": "E_tau [N m]", "E_q": "E_q [rad]",
                  "E_weak": "E_weak [N]", "E_band": "E_band [mm]", "E_q_phys": "E_q_phys (MuJoCo settle) [rad]"}
JSON_NAME, MD_NAME = "fault_benchmark.json", "fault_benchmark.md"
PREFIXES = {"adapted": "fault", "unadapted": "fault_unadapted", "oracle": "fault_oracle"}
SIGNIFICANT_DIGITS = 9


def _schema_classes(root: type) -> list[type]:
    """``root`` and every subclass of it defined so far (the schema classes a CLI run may instantiate)."""
    return [root] + [sub for cls in root.__subclasses__() for sub in _schema_classes(cls)]


class FaultBenchmark(Callback):
    """Adapt the schema to seeded fault cases, score the commands, log medians and box plots; write files at test.

    Args:
        every_n_epochs: during fit, benchmark at the first validation at or after every multiple of this many
            epochs, and at the last validated epoch (0: never during fit, nor without a logger; test always
            runs it). Default 5000: twice in the paper's 10000 epochs (its cost per run: BENCHMARKS.md "Figures
            behind code choices").
        n_per_condition: cases per condition (paper: 40), drawn from the validation (= test) split.
        protocols: the case protocols ``test`` benchmarks (``evaluation.cases.PROTOCOLS``); fit uses the paper's.
        binding_n_per_condition: binding cases per condition at test (5 conditions; 40 keeps ``bodyschema test``
            under a minute on one core).
        seed: seed of the case draw (the same cases at every run, so curves are comparable).
        variant: adaptation variant passed to ``BodySchema.adapt``: one of the schema's ``VARIANTS``.
        out_dir: where ``test`` writes ``fault_benchmark.json``/``.md`` (None: the trainer's log folder).
        settle_check: also run the MuJoCo settle check (``E_q_phys``) in the benchmarks during fit
            (it costs seconds per benchmark); ``test`` always runs it.
    """

    def __init__(self, every_n_epochs: int = 5000, n_per_condition: int = 40, seed: int = 0,
                 variant: str = "default", out_dir: Optional[str] = None, settle_check: bool = True,
                 protocols: tuple[str, ...] = PROTOCOLS, binding_n_per_condition: int = 40):
        from ..schemas.base import BodySchema  # late: keeps `import callbacks` light for the CLI's parser

        if int(every_n_epochs) != every_n_epochs or every_n_epochs < 0:
            raise BodySchemaInputError(f"faults.every_n_epochs={every_n_epochs!r} must be an integer >= 0")
        if int(n_per_condition) != n_per_condition or n_per_condition < 1:
            raise BodySchemaInputError(f"faults.n_per_condition={n_per_condition!r} must be an integer >= 1")
        if int(binding_n_per_condition) != binding_n_per_condition or binding_n_per_condition < 1:
            raise BodySchemaInputError(f"faults.binding_n_per_condition={binding_n_per_condition!r} must be an "
                                       f"integer >= 1")
        unknown = [p for p in protocols if p not in PROTOCOLS]
        if unknown or not protocols:
            raise BodySchemaInputError(f"faults.protocols={list(protocols)!r}; allowed: one or more of {list(PROTOCOLS)}")
        check_variant(_schema_classes(BodySchema), variant, "faults.variant")  # any schema's; setup: this one's
        self.every_n_epochs, self.n_per_condition, self.seed = int(every_n_epochs), int(n_per_condition), seed
        self.variant, self.out_dir, self.settle_check = variant, out_dir, bool(settle_check)
        self.protocols, self.binding_n_per_condition = tuple(dict.fromkeys(protocols)), int(binding_n_per_condition)
        self._cases, self._warned = {}, False  # protocol -> (key of the split, cases)
        self._last_period = 0  # index of the last every_n_epochs period benchmarked during fit
        self._validated_at = self._benchmarked_at = None  # log steps of the last validation and benchmark of a fit

    # ------------------------------------------------------------------ Lightning hooks
    def setup(self, trainer, pl_module, stage):
        check_variant(pl_module, self.variant, "faults.variant")

    def on_fit_start(self, trainer, pl_module):
        # a resumed run continues the cadence from its epoch instead of benchmarking at once
        self._last_period = trainer.current_epoch // self.every_n_epochs if self.every_n_epochs else 0

    @rank_zero_only
    def on_validation_epoch_end(self, trainer, pl_module):
        if not trainer.sanity_checking:
            self._validated_at = validation_log_step(trainer)
        if self._due_in_fit(trainer):
            self._benchmark_in_fit(trainer, pl_module)

    @rank_zero_only
    def on_train_end(self, trainer, pl_module):
        # EarlyStopping requests its stop after this callback's on_validation_epoch_end: benchmark the weights the
        # fit stopped with, at the step of that validation, unless that validation already did
        if stopped_after_last_validation(trainer, self._validated_at, self._benchmarked_at) and self.every_n_epochs \
                and trainer.loggers:
            averaged_weights_now(trainer, pl_module)  # the weights the fit saves, under weight averaging too
            self._benchmark_in_fit(trainer, pl_module)

    def _benchmark_in_fit(self, trainer, pl_module):
        result = self.run(trainer, pl_module, settle_check=self.settle_check)
        if result is None:
            return
        self._last_period = (trainer.current_epoch + 1) // self.every_n_epochs
        step = self._benchmarked_at = validation_log_step(trainer)
        self._log_scalars(trainer, result, step)
        self._log_figure(trainer, pl_module, result, step)

    @rank_zero_only
    def on_test_epoch_end(self, trainer, pl_module):
        folder = self.out_dir or trainer.log_dir or trainer.default_root_dir
        for protocol in self.protocols:
            # test time: also the MuJoCo settle check and the physics oracle
            result = self.run(trainer, pl_module, settle_check=True, protocol=protocol, oracle=True)
            if result is None:
                return
            if protocol == "paper":
                self._log_scalars(trainer, result, trainer.global_step)
            json_path, md_path = self.write(result, folder, pl_module, protocol)
            print(f"\nfault benchmark, {protocol} protocol ({len(result.cases)} cases, "
                  f"{sum(result.seconds.values()):.2f} s): {json_path}\n"
                  + benchmark_markdown(result, self._meta(pl_module, protocol), readings=("phys",),
                                       subsets=("feasible",), title=False)
                  + f"full table: {md_path}")

    def _due_in_fit(self, trainer) -> bool:
        if trainer.sanity_checking or trainer.state.fn != TrainerFn.FITTING or self.every_n_epochs == 0:
            return False
        if not trainer.loggers:  # nothing to log to (--trainer.logger=false): don't spend the time
            return False
        epoch = trainer.current_epoch + 1  # epochs completed
        # "at or after each multiple": works whatever check_val_every_n_epoch is
        return fit_ends_with_this_epoch(trainer) or epoch // self.every_n_epochs > self._last_period

    # ------------------------------------------------------------------ the benchmark
    def cases_for(self, trainer, pl_module, protocol: str = "paper"):
        """The seeded case set of ``protocol`` from the data module's validation split, drawn once per split."""
        datamodule = getattr(trainer, "datamodule", None)
        splits = getattr(datamodule, "splits", None)
        if splits is None or "val" not in splits:
            rank_zero_warn("FaultBenchmark: the data module has no `splits['val']`; fault benchmark skipped")
            return None
        q, x = (t.detach().cpu().numpy() if torch.is_tensor(t) else np.asarray(t) for t in splits["val"])
        n_muscles = pl_module.n_muscles
        key = hashlib.sha256(q.tobytes() + x.tobytes()).hexdigest()
        if self._cases.get(protocol, (None,))[0] != key:
            try:
                if protocol == "binding":
                    pool = HealthyPool(q, x[:, :n_muscles], x[:, n_muscles:2 * n_muscles])
                    cases = make_binding_cases(pl_module.robot_model, pool, self.binding_n_per_condition,
                                               self.seed, pl_module.spring)[0]
                else:
                    cases = make_fault_cases(q, x[:, :n_muscles], self.n_per_condition, self.seed)
            except BodySchemaInputError as err:  # e.g. a 2-muscle robot: the fit and its checkpoint must not die here
                rank_zero_warn(f"FaultBenchmark: the {protocol} protocol is skipped for this robot: {err}")
                cases = None
            self._cases[protocol] = (key, cases)
        return self._cases[protocol][1]

    def run(self, trainer, pl_module, settle_check: bool = False, protocol: str = "paper",
            oracle: bool = False) -> Optional[BenchmarkResult]:
        """Run ``run_fault_benchmark`` on the schema, with gradients available and the RNG left untouched."""
        if not getattr(pl_module, "supports_adaptation", False):
            if not self._warned:
                rank_zero_info(f"FaultBenchmark: {type(pl_module).__name__} implements no adaptation; skipped")
                self._warned = True
            return None
        if not pl_module.has_physics:  # recorded data: no model to score commands on (tools/robustness.py takes one)
            if not self._warned:
                rank_zero_info(f"FaultBenchmark: {pl_module.robot_model} has no model to evaluate on; skipped")
                self._warned = True
            return None
        cases = self.cases_for(trainer, pl_module, protocol)
        if cases is None:
            return None

        def adapt(q, faults):
            return pl_module.adapt(q, faults, variant=self.variant, check_physics=False)  # score every command

        was_training = pl_module.training
        pl_module.eval()
        # Lightning validates and tests under torch.inference_mode(); adaptation differentiates through the
        # network (BodySchema.adapt leaves inference mode itself; this keeps infer's tensors normal too).
        # fork_rng: the benchmark must not shift the training RNG streams (same run with or without it); manual_seed
        # seeds every CUDA device too, so their states are forked as well when CUDA is in use
        cuda = list(range(torch.cuda.device_count())) if torch.cuda.is_available() and torch.cuda.is_initialized() else []
        try:
            with torch.inference_mode(False), torch.random.fork_rng(devices=cuda):
                torch.manual_seed(self.seed)
                return run_fault_benchmark(pl_module.robot_model, pl_module.spring, cases, pl_module.infer, adapt,
                                           settle_check=settle_check, oracle=oracle)
        finally:
            pl_module.train(was_training)

    # ------------------------------------------------------------------ logging
    def _log_scalars(self, trainer, result: BenchmarkResult, step: int):
        metrics = scalar_metrics(result)
        for logger in trainer.loggers:
            logger.log_metrics(metrics, step=step)

    def _log_figure(self, trainer, pl_module, result: BenchmarkResult, step: int):
        experiments = [getattr(lg, "experiment", None) for lg in trainer.loggers]
        experiments = [e for e in experiments if hasattr(e, "add_figure")]
        if not experiments:
            return
        from ..plots.boxplots import fault_boxplots

        name = type(pl_module).__name__
        fig = fault_boxplots({name: result}, reading="phys", subset="all", kind=("unadapted", "adapted"),
                             title=f"{name}, step {step}: fault benchmark (phys reading, all cases)")
        for experiment in experiments:
            experiment.add_figure("fault/boxplots", fig, global_step=step, close=False)

    # ------------------------------------------------------------------ files
    def _meta(self, pl_module, protocol: str) -> dict:
        n = self.binding_n_per_condition if protocol == "binding" else self.n_per_condition
        return {"model": type(pl_module).__name__ if pl_module is not None else None, "variant": self.variant,
                "protocol": protocol, "n_per_condition": n, "seed": self.seed}

    def write(self, result: BenchmarkResult, folder: str, pl_module=None, protocol: str = "paper") -> tuple[str, str]:
        """Write ``fault_benchmark{suffix}.json`` and ``.md`` into ``folder`` atomically; return both paths."""
        meta = self._meta(pl_module, protocol)
        suffix = "" if protocol == "paper" else f"_{protocol}"
        json_path = os.path.join(folder, JSON_NAME.replace(".json", f"{suffix}.json"))
        md_path = os.path.join(folder, MD_NAME.replace(".md", f"{suffix}.md"))
        for path, text in ((json_path, benchmark_json(result, meta)), (md_path, benchmark_markdown(result, meta))):
            atomic_write_bytes(path, text.encode())
        return json_path, md_path


# ---------------------------------------------------------------------------- formatting (pure functions)
def scalar_metrics(result: BenchmarkResult) -> dict[str, float]:
    """The flat {tag: value} dict logged during fit (see the module docstring for the keys)."""
    out = {}
    summary = result.summary()
    for kind in summary:
        prefix = PREFIXES[kind]
        for reading, by_cond in summary[kind].items():
            for cond, by_subset in by_cond.items():
                for subset, values in by_subset.items():
                    for metric in (m for m in SUMMARY_METRICS if m in values):
                        key, factor = METRIC_KEYS[metric]
                        if values[metric] is not None:
                            out[f"{prefix}/{reading}/{cond}/{key}_{subset}"] = factor * values[metric]
                    if "n_unsettled" in values:  # settle runs never at rest: no E_q_phys, counted here
                        out[f"{prefix}/{reading}/{cond}/n_unsettled_{subset}"] = float(values["n_unsettled"])
                if kind == "adapted":
                    out[f"fault/{reading}/{cond}/n_feasible"] = float(by_subset["feasible"]["n"])
    out["fault/adapt_ok_fraction"] = float(np.mean(result.adapt_status == "ok"))
    for name, seconds in result.seconds.items():
        out[f"fault/{name}_seconds"] = float(seconds)
    return out


def _round(value: float):
    if not math.isfinite(value):
        return None
    return float(f"{value:.{SIGNIFICANT_DIGITS}g}")


def _jsonable(obj):
    """Plain JSON types: arrays -> lists, floats rounded to 9 significant digits, NaN/inf -> None."""
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist())
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        return _round(float(obj))
    if isinstance(obj, np.str_):
        return str(obj)
    return obj


def benchmark_json(result: BenchmarkResult, meta: Optional[dict] = None) -> str:
    """Deterministic JSON text of a benchmark: same result -> same bytes (wall times left out on purpose)."""
    cases = result.cases
    payload = {
        "meta": dict(meta or {}) | {"units": {"E_cut": "N", "E_fix": "m", "E_tau": "N m", "E_q": "rad",
                                              "E_weak": "N", "E_band": "m", "E_q_phys": "rad",
                                              "q_ref": "rad", "l_fixed": "m", "f_max": "N", "l_band": "m"}},
        "summary": result.summary(),
        "per_case": result.metrics,  # kind -> reading -> E_*, q_hat, status, converged, n_iter, objective
        "feasible": result.feasible,
        "adapt_status": result.adapt_status,
        "cases": cases.arrays(),  # q_ref, cut, fix, l_fixed, cond (+ f_max, l_band when the cases have them)
    }
    return json.dumps(_jsonable(payload), sort_keys=True, indent=1, allow_nan=False) + "\n"


def _cell(value, factor=1.0) -> str:
    return "n/a" if value is None else f"{factor * value:.4g}"


def benchmark_markdown(result: BenchmarkResult, meta: Optional[dict] = None, readings=None,
                       subsets=("all", "feasible"), title: bool = True) -> str:
    """Markdown table of medians: rows condition x reading x subset x command (adapted, unadapted, oracle)."""
    meta = meta or {}
    summary = result.summary()
    readings = readings or tuple(summary["adapted"])
    # every metric some command has (adapted commands that all failed have none)
    names = [m for m in SUMMARY_METRICS if any(m in by_subset["all"] for kind in summary
                                                for by_subset in summary[kind]["phys"].values())]
    settled = "E_q_phys" in names  # the settle check ran: its runs that never came to rest are counted apart
    header = (["condition", "reading", "subset", "command", "n"] + [METRIC_HEADERS[m] for m in names]
              + (["settle runs not at rest"] if settled else []))
    lines = [f"# Fault benchmark: {meta.get('model', 'schema')}, {meta.get('protocol', 'paper')} protocol", ""] if title \
        else []
    lines += [f"{len(result.cases)} cases ({meta.get('n_per_condition', '?')} per condition, seed "
              f"{meta.get('seed', '?')}), adaptation variant `{meta.get('variant', '?')}`; medians over the cases "
              f"(NaN left out); adaptation ok: {int(np.sum(result.adapt_status == 'ok'))}/{len(result.cases)}."
              + (" E_q_phys: medians over the settle runs that came to rest; `settle runs not at rest`: still moving "
                 "at the time limit or blown up, left out of them." if settled else ""),
              "Readings: `paper` = the paper's metric definitions (jammed muscles excluded from the torque); "
              "`phys` = jammed muscles pull with their stretch. `feasible`: cases with a physical solution. "
              "`oracle`: the command the true physics gives (the physical limit of every metric).", "",
              "| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    conds = [c for c in CONDITION_ORDER if c in summary["adapted"]["phys"]]
    conds += [c for c in summary["adapted"]["phys"] if c not in conds]
    for cond in conds:
        for reading in readings:
            for subset in subsets:
                for kind in (k for k in COMMANDS if k in summary):
                    values = summary[kind][reading][cond][subset]
                    row = [cond, reading, subset, kind, str(values["n"])]
                    row += [_cell(values.get(metric), METRIC_KEYS[metric][1]) for metric in names]
                    row += [str(values.get("n_unsettled", "n/a"))] if settled else []
                    lines.append("| " + " | ".join(row) + " |")
    timing = ", ".join(f"{k} {v:.3f} s" for k, v in result.seconds.items())
    if "oracle" in result.seconds:
        timing += f"; oracle {1e3 * result.seconds['oracle'] / len(result.cases):.3f} ms per case"
    lines += ["", f"Wall time (this run; not in the JSON, which is byte-identical across reruns): {timing}.", ""]
    return "\n".join(lines)
