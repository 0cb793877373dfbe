"""The paper's fault benchmark for one schema: adapt every case, solve for the realized posture, score.

Takes the schema as two callables (``infer(q) -> (l_motor, f)``, ``adapt(q, faults) -> AdaptationResult``)
so this module needs no Lightning. Metrics are computed twice:

* ``paper``: the paper's definitions, where jammed muscles are excluded from the taut set, so their
  tension does not enter E_tau (and hence E_q);
* ``phys``: jammed muscles pull with the tension of their stretch, as a real wire does.

Each is summarised over all cases, over the cases that are feasible under the same reading, and over the
feasible cases whose healthy command breaks a fault constraint (``feasible_active``: adaptation has work to do).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import numpy as np

from ..sim import MusculoskeletalModel, SpringParams
from .cases import FaultCases
from .feasibility import check_feasible
from .forward_solver import ForwardSolverParams
from .metrics import METRICS, evaluate_commands
from ..sim.settle import settle

READINGS = {"paper": False, "phys": True}  # reading -> jammed_tension_in_torque
SUMMARY_METRICS = METRICS + ("E_q_phys",)  # E_q_phys: the MuJoCo settle check, when it was run
ACTIVE_CUT_N, ACTIVE_FIX_M = 0.5, 1e-4  # a healthy command breaking a fault by more than this needs adapting


@dataclass
class BenchmarkResult:
    """Per-case arrays of one benchmark run; ``summary()`` gives the medians as plain floats."""

    cases: FaultCases
    feasible: dict  # reading -> (B,) bool
    metrics: dict  # command kind ("adapted", "unadapted") -> reading -> metric -> (B,)
    adapt_status: np.ndarray
    seconds: dict = field(default_factory=dict)

    def summary(self) -> dict:
        """{kind: {reading: {cond: {subset: {metric: median}}}}} with subsets "all" and "feasible"."""
        out = {}
        for kind, by_reading in self.metrics.items():
            out[kind] = {reading: self._by_condition(values, self.feasible[reading])
                         for reading, values in by_reading.items()}
        return out

    @property
    def active(self) -> np.ndarray:
        """Cases whose healthy command breaks a fault constraint (cut tension > 0.5 N or jam excess > 0.1 mm).

        Where the healthy command already complies, adaptation has nothing to fix and can only tie.
        """
        plain = self.metrics["unadapted"]["phys"]
        return (np.nan_to_num(plain["E_cut"]) > ACTIVE_CUT_N) | (np.nan_to_num(plain["E_fix"]) > ACTIVE_FIX_M)

    def _by_condition(self, values, feasible):
        table = {}
        subsets = (("all", np.ones(len(self.cases), bool)), ("feasible", feasible),
                   ("feasible_active", feasible & self.active))
        for cond in dict.fromkeys(self.cases.cond.tolist()):
            rows = self.cases.cond == cond
            names = [m for m in SUMMARY_METRICS if m in values]
            table[cond] = {subset: {m: _median(values[m][rows & mask]) for m in names} | {"n": int((rows & mask).sum())}
                           for subset, mask in subsets}
        return table


def _median(values) -> float | None:
    values = values[np.isfinite(values)]
    return float(np.median(values)) if values.size else None


def run_fault_benchmark(model: MusculoskeletalModel, spring: SpringParams, cases: FaultCases, infer, adapt,
                        params: ForwardSolverParams = ForwardSolverParams(), settle_check: bool = False
                        ) -> BenchmarkResult:
    """Adapt and score every case; unadapted (healthy) commands are scored beside them as the baseline.

    settle_check: also drop every command into MuJoCo (``settle.settle``, a few seconds for 120 cases) and
    report ``E_q_phys``, the distance of the posture the arm really settles in from q_ref, beside E_q.
    """
    seconds = {}
    start = time.perf_counter()
    result = adapt(cases.q_ref, cases.faults)
    seconds["adapt"] = time.perf_counter() - start
    start = time.perf_counter()
    l_plain, f_plain = infer(cases.q_ref)
    seconds["infer"] = time.perf_counter() - start
    start = time.perf_counter()
    feasible, metrics = {}, {"adapted": {}, "unadapted": {}}
    for reading, jammed_pull in READINGS.items():
        feasible[reading] = check_feasible(model, cases, spring, jammed_tension_in_torque=jammed_pull)[0]
        reading_params = replace(params, jammed_tension_in_torque=jammed_pull)
        metrics["adapted"][reading] = evaluate_commands(model, cases, result.l_motor_m, result.f_n, spring,
                                                        reading_params)
        metrics["unadapted"][reading] = evaluate_commands(model, cases, l_plain, f_plain, spring, reading_params)
    seconds["evaluate"] = time.perf_counter() - start
    if settle_check:
        start = time.perf_counter()
        for kind, (l_motor, f) in (("adapted", (result.l_motor_m, result.f_n)), ("unadapted", (l_plain, f_plain))):
            e_q_phys = settle(model, l_motor, f, cases, spring=spring).E_q_phys
            for reading in READINGS:
                metrics[kind][reading]["E_q_phys"] = e_q_phys
        seconds["settle"] = time.perf_counter() - start
    return BenchmarkResult(cases, feasible, metrics, np.asarray(result.status), seconds)
