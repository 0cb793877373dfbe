"""Fault commands on a learned body by quadratic programming: every fault an exact constraint on the tensions.

A body is given per case by its muscle lengths ``l_geo (B, M)`` [m], moment arms ``G (B, M, N) = d l_geo/dq`` [m/rad]
and the joint torque the muscles must balance ``tau (B, N)`` [N m] (static equilibrium ``-G^T f = tau``). Every fault
becomes a box on the tensions f through the spring ``l_motor = l_geo - delta(f)`` (sim/spring.py):

* cut: ``f = 0``; weakened: ``f <= f_max'``; healthy: ``0 <= f <= f_max``;
* a motor length bound ``l_motor <= l_hi`` (a jam's ``l_fixed``, a band's hi):
  ``f >= k (exp(alpha (l_geo - l_hi)) - 1)``
  (the tension the spring gives when the motor stays at ``l_hi``; reeling in, a higher tension, is allowed);
* ``l_motor >= l_lo`` (a band's lo): ``f <= k (exp(alpha (l_geo - l_lo)) - 1)``; below ``l_geo`` the wire is slack
  (f = 0, the motor may stand anywhere above ``l_geo``).

``fault_command`` solves ``min ||f - f_ref||^2  s.t.  -G^T f = tau,  f_lo <= f <= f_hi`` for every case at once
with ``solvers.solve_box_qp`` (the batched dual Newton, the torque-reach screen, proxsuite on what they leave); a case
without a solution (bounds that cross, or a torque the box cannot balance) gets the least-squares tensions
``min ||G^T f + tau||^2 + reg s ||f - f_ref||^2`` within the box and the status ``"infeasible_learned"``. Arrays in
and out.
"""
from __future__ import annotations

import numpy as np

from ..sim.spring import SpringParams, elongation_from_tension, tension_from_elongation
from ..solvers import EQUILIBRIUM_TOL_NM, LS_REG, BoxQP, least_squares_weight, solve_box_qp
from ..status import Status
from .constraints import LENGTH

OK, INFEASIBLE_LEARNED = "ok", "infeasible_learned"
# proxsuite iterations per command QP the dual Newton leaves: a feasible one converges well within it
# (BENCHMARKS.md, "Structured schema's command QPs"); one without a solution runs to it
QP_MAX_ITER = 50
STATUS_DTYPE = "<U18"
# the solvers' status codes as this module names them (INFEASIBLE: the learned body cannot hold the posture)
_STATUS_NAMES = np.array([INFEASIBLE_LEARNED if s is Status.INFEASIBLE else s.value for s in Status], dtype=STATUS_DTYPE)


def intersect_bounds(constraints, shape) -> tuple[np.ndarray, ...]:
    """(f_lo, f_hi, l_lo, l_hi), each (B, M) in N or m (+-inf where unbounded): the intersection of the intervals of
    ``constraints`` (``faults.constraints``: ``Faults.constraints(f_max)`` gives them, tension limits included)."""
    bounds = {col: [np.full(shape, -np.inf), np.full(shape, np.inf)] for col in ("f", LENGTH)}
    for c in constraints:
        lower, upper = (np.broadcast_to(np.asarray(b, float), shape) for b in c.bounds())
        lo, hi = bounds[c.column]
        mask = np.asarray(c.mask, bool)
        np.copyto(lo, np.maximum(lo, lower), where=mask)
        np.copyto(hi, np.minimum(hi, upper), where=mask)
    return bounds["f"][0], bounds["f"][1], bounds[LENGTH][0], bounds[LENGTH][1]


def tension_box(l_geo_m, f_lo, f_hi, l_lo, l_hi, spring: SpringParams) -> tuple[np.ndarray, np.ndarray]:
    """The tension box (B, M) [N] that the tension and motor-length bounds give at lengths ``l_geo_m`` (module
    docstring); where the two cross, lo > hi and no tension meets them."""
    with np.errstate(over="ignore", invalid="ignore"):
        by_hi = np.where(np.isfinite(l_hi), tension_from_elongation(l_geo_m - np.where(np.isfinite(l_hi), l_hi, 0.0),
                                                                    spring), -np.inf)
        by_lo = np.where(np.isfinite(l_lo), tension_from_elongation(l_geo_m - np.where(np.isfinite(l_lo), l_lo, 0.0),
                                                                    spring), np.inf)
    return np.maximum(np.maximum(f_lo, by_hi), 0.0), np.minimum(f_hi, by_lo)


def least_squares_tensions(G, tau, f_ref, f_lo, f_hi, reg: float = LS_REG, num_threads: int = 1) -> np.ndarray:
    """``argmin ||G^T f + tau||^2 + reg s ||f - f_ref||^2`` over ``f_lo <= f <= f_hi`` per case (B, M) [N], with
    ``s`` the mean squared moment arm of the case (``solvers.least_squares_weight``): ``solvers.solve_box_qp`` of
    that least-squares problem (the dual Newton, proxsuite on the cases it leaves)."""
    problem = BoxQP.build(G, tau, f_ref, f_lo, f_hi)
    problem = problem.with_weight(least_squares_weight(problem.G, reg))
    return solve_box_qp(problem, num_threads=num_threads).f_n.cpu().numpy()


def fault_command(l_geo_m, G, tau_nm, f_ref, f_lo, f_hi, l_lo, l_hi, spring: SpringParams, reg: float = LS_REG,
                  max_iter: int = QP_MAX_ITER, num_threads: int = 1):
    """Command ``(l_motor (B, M) [m], f (B, M) [N], status (B,))`` on the body ``(l_geo_m, G, tau_nm)`` closest to
    ``f_ref`` (module docstring). Every row is finite and meets every bound (the box and the motor-length bounds);
    rows whose status is ``"infeasible_learned"`` miss the torque balance (least squares) and are not commands
    (``"not_converged"``: no solver settled the row; ``"bad_input"``: a non-finite body, NaN rows).
    ``max_iter``: proxsuite's iteration limit of an equilibrium QP the dual Newton leaves; ``num_threads``:
    proxsuite's threads (more than 1: its batch API)."""
    box_lo, box_hi = tension_box(l_geo_m, f_lo, f_hi, l_lo, l_hi, spring)
    solution = solve_box_qp(BoxQP.build(G, tau_nm, f_ref, box_lo, box_hi), fallback_max_iter=max_iter, ls_reg=reg,
                            num_threads=num_threads)
    f, codes = solution.f_n.cpu().numpy(), solution.status.cpu().numpy()
    l_motor = l_geo_m - elongation_from_tension(f, spring)
    slack = (f <= 0.0) & np.isfinite(l_lo)  # a slack wire: the motor may stand anywhere above l_geo
    l_motor = np.where(slack, np.maximum(l_motor, l_lo), l_motor)
    l_motor = np.minimum(l_motor, l_hi)  # rounding of exp/log1p only: the box already keeps l_motor <= l_hi
    return l_motor, f, _STATUS_NAMES[codes]


def balance_residual_nm(G, tau_nm, f) -> np.ndarray:
    """``|-G^T f - tau|`` per case (B,) [N m], the largest joint."""
    return np.abs(-np.einsum("bmn,bm->bn", G, f) - tau_nm).max(1)


__all__ = ["fault_command", "intersect_bounds", "tension_box", "least_squares_tensions", "balance_residual_nm",
           "OK", "INFEASIBLE_LEARNED", "EQUILIBRIUM_TOL_NM"]
