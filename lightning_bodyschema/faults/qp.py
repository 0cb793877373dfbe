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

from .._arrays import namespace
from ..sim.spring import SpringParams
from ..solvers import EQUILIBRIUM_TOL_NM, LS_REG, BoxQP, solve_box_qp
from ..status import Status, status_array
from .bounds import FaultBounds

OK, INFEASIBLE_LEARNED = Status.OK, Status.INFEASIBLE_LEARNED
# proxsuite iterations per command QP the dual Newton leaves: a feasible one converges well within it
# (BENCHMARKS.md, "Structured schema's command QPs"); one without a solution runs to it
QP_MAX_ITER = 50


def learned_body_status(codes):
    """A solver's status codes on the learned body as the command's (numpy or torch ints, same dtype): no tension
    balancing the learned torque (``infeasible``) reads ``infeasible_learned``, since ``infeasible`` is the true
    body's (the physics check's) to say; every other code stays. The one place that renames it (``bounds_command``,
    the exported ``deploy.structured``)."""
    return namespace(codes).where(codes == Status.INFEASIBLE.code, INFEASIBLE_LEARNED.code, codes)


_AS_COMMAND = status_array(learned_body_status(np.arange(len(Status))))  # code -> the command's member, one lookup


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


def fault_command(l_geo_m, G, tau_nm, f_ref, f_lo, f_hi, l_lo, l_hi, spring: SpringParams, reg: float = LS_REG,
                  max_iter: int = QP_MAX_ITER, num_threads: int = 1):
    """Command ``(l_motor (B, M) [m], f (B, M) [N], status (B,))`` on the body ``(l_geo_m, G, tau_nm)`` closest to
    ``f_ref`` (module docstring). Every row is finite and meets every bound (the box and the motor-length bounds);
    rows whose status is ``"infeasible_learned"`` miss the torque balance (least squares) and are not commands
    (``"not_converged"``: no solver settled the row; ``"bad_input"``: a non-finite body, NaN rows).
    ``max_iter``: proxsuite's iteration limit of an equilibrium QP the dual Newton leaves; ``num_threads``:
    proxsuite's threads (more than 1: its batch API)."""
    return bounds_command(l_geo_m, G, tau_nm, f_ref, _bounds_of(f_lo, f_hi, l_lo, l_hi, spring), reg, max_iter,
                          num_threads)


def bounds_command(l_geo_m, G, tau_nm, f_ref, bounds: FaultBounds, reg: float = LS_REG, max_iter: int = QP_MAX_ITER,
                   num_threads: int = 1):
    """``fault_command`` with the bounds as a host ``FaultBounds`` (numpy fields, with its spring): the motor lengths
    by ``FaultBounds.motor_length_m``."""
    box_lo, box_hi = bounds.tension_box(np.asarray(l_geo_m, float))
    solution = solve_box_qp(BoxQP.build(G, tau_nm, f_ref, box_lo, box_hi), fallback_max_iter=max_iter, ls_reg=reg,
                            num_threads=num_threads)
    f, codes = solution.f_n.cpu().numpy(), solution.status.cpu().numpy()
    return bounds.motor_length_m(l_geo_m, f), f, _AS_COMMAND[codes]


def balance_residual_nm(G, tau_nm, f) -> np.ndarray:
    """``|-G^T f - tau|`` per case (B,) [N m], the largest joint."""
    return np.abs(-np.einsum("bmn,bm->bn", G, f) - tau_nm).max(1)


__all__ = ["fault_command", "bounds_command", "tension_box", "learned_body_status", "balance_residual_nm", "OK",
           "INFEASIBLE_LEARNED", "EQUILIBRIUM_TOL_NM"]
