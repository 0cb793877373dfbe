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

``fault_command`` solves ``min ||f - f_ref||^2  s.t.  -G^T f = tau,  f_lo <= f <= f_hi`` for every case at once by
the batched dual Newton of ``sim.dual_newton``, and the cases it leaves unsettled by proxsuite (the dataset's QP
in ``sim.equilibrium``; on more than one thread batched through proxsuite's ``BatchQP`` and ``solve_in_parallel``);
a case without a solution (bounds that cross, or a torque the box cannot balance) gets the least-squares tensions
``min ||G^T f + tau||^2 + reg ||f - f_ref||^2`` within the box and the status ``"infeasible_learned"``. numpy and
proxsuite only.
"""
from __future__ import annotations

import numpy as np

from ..sim.equilibrium import EQUILIBRIUM_TOL_NM, solve_equilibrium_qp, solve_qps_batched
from ..sim.spring import SpringParams, elongation_from_tension, tension_from_elongation
from ..status import Status
from .bounds import FaultBounds
from ..sim.dual_newton import NEWTON_TOL_NM, box_least_squares, dual_newton, least_squares_weight

OK, INFEASIBLE_LEARNED = Status.OK, Status.INFEASIBLE_LEARNED
# proxsuite iterations per command QP: a feasible one converges well within it (BENCHMARKS.md, "Structured schema's
# command QPs"); one without a solution runs to it before the least-squares answer takes over, so it is kept short
QP_MAX_ITER = 50
# the least-squares QP: stationarity to 1 mN of its scaled objective (the rows are best efforts, never commands)
LS_EPS_N, LS_MAX_ITER = 1e-3, 1000


def tension_box(l_geo_m, f_lo, f_hi, l_lo, l_hi, spring: SpringParams) -> tuple[np.ndarray, np.ndarray]:
    """The tension box (B, M) [N] that the tension bounds ``[f_lo, f_hi]`` and the motor-length bounds
    ``[l_lo, l_hi]`` (+-inf where free) give at lengths ``l_geo_m`` (``FaultBounds.tension_box``, module docstring);
    where the two cross, lo > hi and no tension meets them."""
    return _bounds_of(f_lo, f_hi, l_lo, l_hi, spring).tension_box(np.asarray(l_geo_m, float))


def _bounds_of(f_lo, f_hi, l_lo, l_hi, spring: SpringParams) -> FaultBounds:
    """The ``FaultBounds`` of plain SI bounds (a tension lower bound above 0 is not a fault: refused)."""
    f_lo, f_hi, l_lo, l_hi = (np.asarray(a, float) for a in (f_lo, f_hi, l_lo, l_hi))
    if (f_lo > 0).any():
        raise ValueError("tension_box: a tension lower bound is 0 (a lower tension comes from a motor-length bound)")
    shape = np.broadcast_shapes(f_lo.shape, f_hi.shape, l_lo.shape, l_hi.shape)
    lo, hi, f_hi = (np.broadcast_to(a, shape) for a in (l_lo, l_hi, f_hi))
    off = np.zeros(shape, bool)
    k, alpha = (np.broadcast_to(np.asarray(v, float), shape[-1:]) for v in (spring.k_n, spring.alpha_per_m))
    has_lo = np.isfinite(lo)  # a lower length bound alone: a band [lo, inf)
    return FaultBounds(off, np.isfinite(hi), off, has_lo, np.where(np.isfinite(hi), hi, np.nan),
                       np.where(has_lo, lo, np.nan), np.where(has_lo, np.inf, np.nan), np.array(f_hi), k, alpha)


def least_squares_tensions(G, tau, f_ref, f_lo, f_hi, reg: float = 1e-6, num_threads: int = 1) -> np.ndarray:
    """``argmin ||G^T f + tau||^2 + reg s ||f - f_ref||^2`` over ``f_lo <= f <= f_hi`` per case (B, M) [N], with
    ``s`` the mean squared moment arm of the case (so ``reg`` is dimensionless): the batched dual Newton, then
    proxsuite's batch API on the cases it leaves (the objective divided by ``reg s``, solved to ``LS_EPS_N``)."""
    m = G.shape[1]
    f, done = box_least_squares(G, tau, f_ref, f_lo, f_hi, reg)
    weight = least_squares_weight(G, reg)
    if not done.all():  # proxsuite's batch API on the few the Newton iteration did not settle
        H = G[~done] @ np.swapaxes(G[~done], 1, 2) / weight[~done, None, None] + np.eye(m)  # (b, M, M)
        g = np.einsum("bmn,bn->bm", G[~done], tau[~done]) / weight[~done, None] - f_ref[~done]
        f[~done], _ = solve_qps_batched(H, g, None, None, f_lo[~done], f_hi[~done], LS_EPS_N, LS_MAX_ITER,
                                        num_threads)
    return np.clip(f, f_lo, f_hi)


def fault_command(l_geo_m, G, tau_nm, f_ref, f_lo, f_hi, l_lo, l_hi, spring: SpringParams, reg: float = 1e-6,
                  max_iter: int = QP_MAX_ITER, num_threads: int = 1):
    """Command ``(l_motor (B, M) [m], f (B, M) [N], status (B,))`` on the body ``(l_geo_m, G, tau_nm)`` closest to
    ``f_ref`` (module docstring). Every row is finite and meets every bound (the box and the motor-length bounds);
    rows whose status is ``"infeasible_learned"`` miss the torque balance (least squares) and are not commands.
    ``max_iter``: proxsuite's iteration limit of the equilibrium QP; ``num_threads``: 1 solves the equilibrium QPs
    as the dataset does (one QP updated per case), more through proxsuite's batch API on that many threads."""
    box_lo, box_hi = tension_box(l_geo_m, f_lo, f_hi, l_lo, l_hi, spring)
    ok = ~(box_lo > box_hi).any(1)  # crossed bounds: no tension meets them, straight to least squares
    box_lo = np.minimum(box_lo, box_hi)
    f, run = np.empty(box_lo.shape), ok.copy()
    f[run], ok[run] = dual_newton(G[run], tau_nm[run], f_ref[run], box_lo[run], box_hi[run], 0.0, NEWTON_TOL_NM)
    run &= ~ok  # stalled: an unholdable torque (no root), or a slow active set: proxsuite decides
    if run.any():
        f[run], ok[run] = solve_equilibrium_qp(G[run], tau_nm[run], f_ref[run], box_hi[run], box_lo[run],
                                               solver="proxqp", max_iter=max_iter, batched=num_threads > 1,
                                               num_threads=num_threads)
    if not ok.all():
        f[~ok] = least_squares_tensions(G[~ok], tau_nm[~ok], f_ref[~ok], box_lo[~ok], box_hi[~ok], reg, num_threads)
    l_motor = l_geo_m - elongation_from_tension(f, spring)
    slack = (f <= 0.0) & np.isfinite(l_lo)  # a slack wire: the motor may stand anywhere above l_geo
    l_motor = np.where(slack, np.maximum(l_motor, l_lo), l_motor)
    l_motor = np.minimum(l_motor, l_hi)  # rounding of exp/log1p only: the box already keeps l_motor <= l_hi
    status = np.full(len(ok), OK, dtype=object)
    status[~ok] = INFEASIBLE_LEARNED
    return l_motor, f, status


def balance_residual_nm(G, tau_nm, f) -> np.ndarray:
    """``|-G^T f - tau|`` per case (B,) [N m], the largest joint."""
    return np.abs(-np.einsum("bmn,bm->bn", G, f) - tau_nm).max(1)


__all__ = ["fault_command", "tension_box", "least_squares_tensions", "balance_residual_nm",
           "OK", "INFEASIBLE_LEARNED", "EQUILIBRIUM_TOL_NM"]
