"""Evaluation (paper section IV-B): fault cases, feasibility, the forward posture solver and metrics.

Never imports Lightning; numpy in, numpy out, SI units (m, N, rad, N m).
"""
from .cases import CONDITIONS, FaultCases, condition_of, make_fault_cases, validate_cases
from .feasibility import check_feasible, feasible_tensions, oracle_commands, tension_bounds
from .forward_solver import ForwardSolverParams, PostureResult, SolverStatus, solve_posture
from .metrics import (EXTRA_METRICS, METRICS, band_error, cut_error, evaluate_commands, fix_error, summarize_metrics,
                      weak_error)
from .benchmark import BenchmarkResult, OracleScores, oracle_scores, run_fault_benchmark

__all__ = [
    "CONDITIONS", "FaultCases", "condition_of", "make_fault_cases", "validate_cases",
    "check_feasible", "feasible_tensions", "oracle_commands", "tension_bounds",
    "ForwardSolverParams", "PostureResult", "SolverStatus", "solve_posture",
    "METRICS", "EXTRA_METRICS", "cut_error", "fix_error", "weak_error", "band_error", "evaluate_commands",
    "summarize_metrics",
    "BenchmarkResult", "OracleScores", "oracle_scores", "run_fault_benchmark",
]
