"""The physics check of a command: can any command hold q_ref under the faults? (the feasibility QP on the true model)"""
from __future__ import annotations

import numpy as np

from ..sim.feasibility import feasible_cases
from ..status import Status
from .command import AdaptationResult

# what the physics check may overrule: the physical reason wins over the schema's own failure
OVERRULED = (Status.OK, Status.NON_FINITE, Status.OUT_OF_RANGE, Status.FAULT_NOT_MET)


def flag_infeasible(result: AdaptationResult, robot_model, q: np.ndarray, faults, spring) -> AdaptationResult:
    """Status ``infeasible`` and NaN rows where no command can hold ``q (B, N)`` under ``faults`` (jammed wires pull:
    ``sim.feasibility``). The schema's best effort (its clipped command where ``safe_command`` kept one) stays in
    ``diagnostics``."""
    feasible = feasible_cases(robot_model, q, faults, spring)
    # the physical reason wins: a case no command can hold is infeasible even where the sampler also diverged
    bad = ~feasible & np.isin(result.status, OVERRULED)
    kept = result.diagnostics
    result.diagnostics.update(feasible=feasible,
                              best_effort_l_motor_m=kept.get("clipped_l_motor_m", result.l_motor_m).copy(),
                              best_effort_f_n=kept.get("clipped_f_n", result.f_n).copy())
    result.status[bad] = Status.INFEASIBLE
    result.l_motor_m[bad], result.f_n[bad] = np.nan, np.nan
    return result


def mark_unchecked(result: AdaptationResult) -> AdaptationResult:
    """Status ``unchecked`` where the physics check was asked for but the robot has no model to run it on (recorded
    data): the command stays, so a controller can choose to send it, but it never reads ``ok``."""
    result.status[result.status == Status.OK] = Status.UNCHECKED
    result.diagnostics["physics_checked"] = np.zeros(len(result.status), bool)
    return result
