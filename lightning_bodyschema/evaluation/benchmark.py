"""The paper's fault benchmark for one schema: adapt every case, solve for the realized posture, score.

Takes the schema as two callables (``infer(q) -> (l_motor, f)``, ``adapt(q, faults) -> AdaptationResult``)
so this module needs no Lightning. Metrics are computed twice:

* ``paper``: the paper's definitions, where jammed muscles are excluded from the taut set, so their
  tension does not enter E_tau (and hence E_q);
* ``phys``: jammed muscles pull with the tension of their stretch, as a real wire does.

Each is summarised over all cases, over the cases that are feasible under the same reading, and over the
feasible cases whose healthy command breaks a fault constraint (``feasible_active``: adaptation has work to do).

Three commands are scored per case: ``adapted`` (the schema's), ``unadapted`` (its healthy command, the
baseline) and ``oracle`` (``feasibility.oracle_commands``: what the true physics gives for the faults, the
tensions nearest the healthy ones that hold q_ref, lengths from the spring; NaN where no command exists). The
oracle is the physical limit of every metric (0 where feasible) and what a user with an exact model of the
robot would run instead of a learned schema; its wall time is ``seconds["oracle"]``.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import numpy as np

from ..sim import MusculoskeletalModel, SpringParams
from ..status import Status, status_names
from .cases import FaultCases
from .feasibility import oracle_commands
from .forward_solver import ForwardSolverParams
from .metrics import EXTRA_METRICS, METRICS, evaluate_commands
from ..sim.settle import settle

READINGS = {"paper": False, "phys": True}  # reading -> jammed_tension_in_torque
SUMMARY_METRICS = METRICS + EXTRA_METRICS + ("E_q_phys",)  # E_q_phys: the MuJoCo settle check, when it was run
COMMANDS = ("adapted", "unadapted", "oracle")  # the command kinds a benchmark scores
ACTIVE_CUT_N, ACTIVE_FIX_M = 0.5, 1e-4  # a healthy command breaking a fault by more than this needs adapting


@dataclass
class BenchmarkResult:
    """Per-case arrays of one benchmark run; ``summary()`` gives the medians as plain floats."""

    cases: FaultCases
    feasible: dict  # reading -> (B,) bool
    metrics: dict  # command kind (``COMMANDS``) -> reading -> metric -> (B,)
    adapt_status: np.ndarray
    seconds: dict = field(default_factory=dict)

    def summary(self) -> dict:
        """{kind: {reading: {cond: {subset: {metric: median}}}}} with subsets "all" and "feasible"."""
        # the same metric keys for every command kind (None where a kind has no finite value, e.g. every adapted
        # command failed), so the summary's shape depends on the cases, not on how a schema did
        names = [m for m in SUMMARY_METRICS if any(m in values and _defined(values[m])
                                                   for by_reading in self.metrics.values()
                                                   for values in by_reading.values())]
        out = {}
        for kind, by_reading in self.metrics.items():
            out[kind] = {reading: self._by_condition(values, self.feasible[reading], names)
                         for reading, values in by_reading.items()}
        return out

    @property
    def active(self) -> np.ndarray:
        """Cases whose healthy command breaks a fault constraint (cut tension > 0.5 N or jam excess > 0.1 mm).

        Where the healthy command already complies, adaptation has nothing to fix and can only tie.
        """
        plain = self.metrics["unadapted"]["phys"]
        return (np.nan_to_num(plain["E_cut"]) > ACTIVE_CUT_N) | (np.nan_to_num(plain["E_fix"]) > ACTIVE_FIX_M)

    def _by_condition(self, values, feasible, names):
        table = {}
        subsets = (("all", np.ones(len(self.cases), bool)), ("feasible", feasible),
                   ("feasible_active", feasible & self.active))
        for cond in dict.fromkeys(self.cases.cond.tolist()):
            rows = self.cases.cond == cond
            table[cond] = {subset: {m: _median(values[m][rows & mask]) if m in values else None for m in names}
                           | {"n": int((rows & mask).sum())} | _unsettled_count(values, rows & mask)
                           for subset, mask in subsets}
        return table


def _defined(values) -> bool:
    """A metric a case set has at all: E_weak / E_band only where some muscle is weakened / banded."""
    return not np.issubdtype(np.asarray(values).dtype, np.floating) or bool(np.isfinite(values).any())


def _unsettled_count(values, mask) -> dict:
    """{"n_unsettled": settle runs that never came to rest} where the settle check ran (their E_q_phys is NaN)."""
    return {"n_unsettled": int(values["settle_unsettled"][mask].sum())} if "settle_unsettled" in values else {}


def _median(values) -> float | None:
    values = values[np.isfinite(values)]
    return float(np.median(values)) if values.size else None


@dataclass
class OracleScores:
    """The physics oracle of one case set, scored once and reusable for every schema benchmarked on it.

    feasible: reading -> (B,) bool; commands: reading -> (l_motor, f) (B, M); metrics: reading -> metric -> (B,)
    (None until scored); seconds: wall time of the physical reading's ``oracle_commands``.
    """

    feasible: dict
    commands: dict
    seconds: float
    metrics: dict | None = None


def oracle_scores(model: MusculoskeletalModel, spring: SpringParams, cases: FaultCases,
                  params: ForwardSolverParams = ForwardSolverParams(), settle_check: bool = False,
                  score: bool = True) -> OracleScores:
    """Each reading's oracle command (a command exact under one torque convention is not under the other, see
    ``feasibility``), its feasibility verdict, and with ``score`` its metrics (and E_q_phys with ``settle_check``)."""
    feasible, commands, seconds = {}, {}, 0.0
    for reading, jammed_pull in READINGS.items():
        start = time.perf_counter()
        feasible[reading], *commands[reading] = oracle_commands(model, cases, spring,
                                                                jammed_tension_in_torque=jammed_pull)
        seconds = time.perf_counter() - start if jammed_pull else seconds
    out = OracleScores(feasible, commands, seconds)
    if score:
        out.metrics = {reading: _score(model, spring, cases, *commands[reading], params, reading)
                       for reading in READINGS}
        if settle_check:
            for reading in READINGS:
                out.metrics[reading].update(settle_metrics(settle(model, *commands[reading], cases, spring=spring)))
    return out


def settle_metrics(result) -> dict:
    """The settle check's per-case entries of a benchmark: ``E_q_phys`` of the cases that came to rest (NaN for a
    run still moving or blown up: no rest posture to score) and ``settle_unsettled`` (those runs, counted apart as
    ``n_unsettled`` in the summary)."""
    return {"E_q_phys": result.E_q_rest, "settle_unsettled": result.unsettled}


def _score(model, spring, cases, l_motor, f, params, reading):
    return evaluate_commands(model, cases, l_motor, f, spring,
                             replace(params, jammed_tension_in_torque=READINGS[reading]))


def run_fault_benchmark(model: MusculoskeletalModel, spring: SpringParams, cases: FaultCases, infer, adapt,
                        params: ForwardSolverParams = ForwardSolverParams(), settle_check: bool = False,
                        oracle: bool | OracleScores = True) -> BenchmarkResult:
    """Adapt and score every case; unadapted (healthy) and, with ``oracle``, physics-oracle commands are scored
    beside them (the baseline and the physical limit).

    settle_check: also drop every command into MuJoCo (``settle.settle``: one simulation per command) and report
    ``E_q_phys`` (B,) [rad], the distance of the posture the arm really settles in from q_ref, beside E_q (NaN where
    the run never came to rest, flagged in ``settle_unsettled`` and counted as ``n_unsettled`` in the summary).
    oracle: True (score it here), False (feasibility only), or the ``oracle_scores`` of these cases (scored once
    for several schemas); ``seconds["oracle"]`` is the physical reading's oracle time.
    """
    seconds = {}
    start = time.perf_counter()
    result = adapt(cases.q_ref, cases.faults)
    seconds["adapt"] = time.perf_counter() - start
    start = time.perf_counter()
    l_plain, f_plain = infer(cases.q_ref)
    seconds["infer"] = time.perf_counter() - start
    if not isinstance(oracle, OracleScores):
        oracle = oracle_scores(model, spring, cases, params, settle_check, score=bool(oracle))
    seconds["oracle"] = oracle.seconds
    start = time.perf_counter()
    commands = {"adapted": scored_command(result), "unadapted": (l_plain, f_plain)}
    metrics = {kind: {reading: _score(model, spring, cases, *command, params, reading) for reading in READINGS}
               for kind, command in commands.items()}
    seconds["evaluate"] = time.perf_counter() - start
    if settle_check:
        start = time.perf_counter()
        for kind, command in commands.items():  # the physics has one reading: one settle per command
            physical = settle_metrics(settle(model, *command, cases, spring=spring))
            for reading in READINGS:
                metrics[kind][reading].update(physical)
        seconds["settle"] = time.perf_counter() - start
    if oracle.metrics is not None:
        metrics["oracle"] = oracle.metrics
    return BenchmarkResult(cases, oracle.feasible, metrics, status_names(result.status), seconds)


def scored_command(result) -> tuple[np.ndarray, np.ndarray]:
    """(l_motor, f) (B, M) the benchmark scores: the adapted commands, and for a ``fault_not_met`` row the clipped
    command it would have sent (the E_cut/E_fix/E_band residuals measure exactly how far it breaks its faults)."""
    clipped = result.diagnostics.get("clipped_l_motor_m"), result.diagnostics.get("clipped_f_n")
    not_met = (np.asarray(result.status) == Status.FAULT_NOT_MET)[:, None]
    if clipped[0] is None or not not_met.any():
        return result.l_motor_m, result.f_n
    return np.where(not_met, clipped[0], result.l_motor_m), np.where(not_met, clipped[1], result.f_n)
