"""Static-equilibrium tensions by quadratic programming (paper section IV-A), and the healthy dataset.

For each posture q:  f = argmin ||f - f_ref||^2  s.t.  -G(q)^T f = tau_bias(q),  0 <= f <= f_max,
then ``l_motor = l_geo(q) - delta(f)`` (eq:muscle-elongation). Draws whose QP has no solution are
re-drawn and counted.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import proxsuite

from ..errors import BodySchemaInputError
from .dual_newton import NEWTON_TOL_NM, dual_newton
from .model import MusculoskeletalModel
from .spring import SpringParams, elongation_from_tension
from .torque_reach import outside_torque_reach

EQUILIBRIUM_TOL_NM = 1e-6  # a tension vector is an equilibrium if every joint torque residual is below this
QP_EPS_ABS = 1e-9  # proxsuite's tolerance on the equilibrium QP: far below EQUILIBRIUM_TOL_NM
_SOLVED = proxsuite.proxqp.QPSolverOutput.PROXQP_SOLVED


def _proxqp_solve(G, tau_bias, f_ref, f_lo, f_hi, max_iter: int = 2000):
    """proxsuite's own dense API, one small QP per posture: the fast path.

    One QP object is initialised once and updated per posture (no re-allocation per posture); eps_abs 1e-9
    keeps the torque residual far below EQUILIBRIUM_TOL_NM. Returns f (B, M) [N] and solved (B,) bool.
    """
    batch, n_muscles, n_joints = G.shape
    A = np.ascontiguousarray(-np.swapaxes(G, 1, 2))  # (B, N, M): equality rows -G^T f = tau_bias
    g = np.ascontiguousarray(-f_ref)
    lo, hi = np.ascontiguousarray(f_lo, dtype=float), np.ascontiguousarray(f_hi, dtype=float)
    qp = proxsuite.proxqp.dense.QP(n_muscles, n_joints, 0, box_constraints=True)
    qp.settings.eps_abs, qp.settings.eps_rel = QP_EPS_ABS, 0.0
    qp.settings.max_iter, qp.settings.verbose = max_iter, False
    f = np.zeros((batch, n_muscles))
    solved = np.zeros(batch, dtype=bool)
    for b in range(batch):  # proxsuite solves one QP per call
        if b == 0:
            qp.init(np.eye(n_muscles), g[0], A[0], tau_bias[0], None, None, None, l_box=lo[0], u_box=hi[0])
        else:
            qp.update(g=g[b], A=A[b], b=tau_bias[b], l_box=lo[b], u_box=hi[b], update_preconditioner=False)
        qp.solve()
        solved[b] = qp.results.info.status == _SOLVED
        f[b] = qp.results.x  # copies: results.x is overwritten by the next solve
    return f, solved


def _dense_qp(n, n_eq, eps_abs, max_iter, qps=None):
    """A proxsuite dense QP of n variables, n_eq equalities and an n-row box (built in the BatchQP ``qps`` if given),
    with the tolerance and iteration limit set."""
    qp = proxsuite.proxqp.dense.QP(n, n_eq, n) if qps is None else qps.init_qp_in_place(n, n_eq, n)
    qp.settings.eps_abs, qp.settings.eps_rel = eps_abs, 0.0
    qp.settings.max_iter, qp.settings.verbose = max_iter, False
    return qp


def solve_qps_batched(H, g, A, b, lo, hi, eps_abs: float, max_iter: int, num_threads: int = 1):
    """``argmin 0.5 x^T H x + g^T x  s.t.  A x = b,  lo <= x <= hi`` per case.

    Args:
        H: (n, n) or (B, n, n); g: (B, n); A: (B, n_eq, n) and b: (B, n_eq), or both None; lo, hi: (B, n) (+-inf
        where unbounded). eps_abs: proxsuite's absolute tolerance (eps_rel 0); max_iter: its iteration limit.
        num_threads: 1 sets up and solves each case on one proxsuite QP in turn; more solves them through
            proxsuite's ``BatchQP`` and ``solve_in_parallel`` on that many OpenMP threads. Either way the answers
            agree to the tolerance; from run to run they may differ in the last bits (proxsuite's dense solves do).

    Returns:
        x (B, n) as proxsuite returns it (not clipped) and solved (B,) bool (proxsuite's status SOLVED).
    """
    batch, n = g.shape
    H = np.broadcast_to(H, (batch, n, n))
    n_eq = 0 if A is None else A.shape[1]
    eye, x, solved = np.eye(n), np.zeros((batch, n)), np.zeros(batch, dtype=bool)
    parallel = proxsuite.proxqp.dense.BatchQP(batch) if num_threads > 1 else None
    qp = _dense_qp(n, n_eq, eps_abs, max_iter) if parallel is None else None
    for k in range(batch):  # proxsuite sets its QPs up one at a time; the box as n inequality rows
        case = qp if qp is not None else _dense_qp(n, n_eq, eps_abs, max_iter, parallel)
        case.init(H[k], g[k], None if A is None else A[k], None if A is None else b[k], eye, lo[k], hi[k])
        if parallel is None:
            case.solve()
            x[k], solved[k] = case.results.x, case.results.info.status == _SOLVED
    if parallel is not None and batch:
        proxsuite.proxqp.dense.solve_in_parallel(num_threads=int(num_threads), qps=parallel)
        for k in range(batch):
            results = parallel.get(k).results
            x[k], solved[k] = results.x, results.info.status == _SOLVED
    return x, solved


def _newton_solve(G, tau_bias, f_ref, f_lo, f_hi, max_iter: int):
    """The batched dual Newton (``sim.dual_newton``) on every posture at once, the same bytes in every process
    (proxsuite's dense solves may differ in the last bits from run to run); proxsuite's own API on the postures it
    leaves unsettled and the torque-reach screen (``sim.torque_reach``) does not rule out."""
    f, solved = dual_newton(G, tau_bias, f_ref, f_lo, f_hi, 0.0, NEWTON_TOL_NM)
    rest = ~solved
    if rest.any():  # a torque out of the box's reach has no solution: proxsuite would only run to max_iter
        rest[rest] = ~outside_torque_reach(G[rest], tau_bias[rest], f_lo[rest], f_hi[rest], EQUILIBRIUM_TOL_NM)
    if rest.any():
        f[rest], solved[rest] = _proxqp_solve(G[rest], tau_bias[rest], f_ref[rest], f_lo[rest], f_hi[rest], max_iter)
    return f, solved


def _qpsolvers_solve(G, tau_bias, f_ref, f_lo, f_hi, solver):
    """qpsolvers' unified interface, so a user can plug in any QP solver it knows."""
    import qpsolvers

    batch, n_muscles, _ = G.shape
    f = np.zeros((batch, n_muscles))
    solved = np.zeros(batch, dtype=bool)
    for b in range(batch):
        x = qpsolvers.solve_qp(np.eye(n_muscles), -f_ref[b], A=-G[b].T, b=tau_bias[b],
                               lb=f_lo[b], ub=f_hi[b], solver=solver)
        if x is not None:
            f[b], solved[b] = x, True
    return f, solved


def check_qp_solver(solver: str) -> str:
    """Refuse a QP solver name that qpsolvers does not have installed."""
    if solver in ("newton", "proxqp"):
        return solver
    import qpsolvers

    if solver not in qpsolvers.available_solvers:
        raise BodySchemaInputError(
            f"unknown QP solver {solver!r}; installed: {sorted(qpsolvers.available_solvers)}")
    return solver


def solve_equilibrium_qp(G, tau_bias, f_ref, f_max, f_min=0.0, solver: str = "newton", max_iter: int = 2000,
                         batched: bool = False, num_threads: int = 1):
    """Tensions closest to ``f_ref`` that hold each posture in static equilibrium.

    Args:
        G: (B, M, N) muscle Jacobians; tau_bias: (B, N); f_ref: (B, M) [N];
        f_max, f_min: scalars, (M,) or (B, M) tension bounds [N] (a per-case f_max of 0 models a cut).
        solver: ``"newton"`` (the batched dual Newton, proxsuite where it stalls: fast, the same bytes in every
            process), ``"proxqp"`` (proxsuite's own API) or any qpsolvers solver name.
        max_iter: proxsuite's iteration limit per posture (proxqp only); a posture with no solution runs to it.
        batched: proxqp through ``solve_qps_batched`` (each QP set up and preconditioned on its own; ``num_threads``
            > 1: proxsuite's batch API) instead of one QP updated per posture (the dataset's bytes).

    Returns:
        ``f (B, M)`` clipped into the bounds, and ``ok (B,)``: solved and equilibrium residual
        ``|-G^T f - tau_bias|`` below ``EQUILIBRIUM_TOL_NM`` on every joint.
    """
    batch, n_muscles, _ = G.shape
    f_lo = np.broadcast_to(np.asarray(f_min, float), (batch, n_muscles))
    f_hi = np.broadcast_to(np.asarray(f_max, float), (batch, n_muscles))
    if check_qp_solver(solver) == "proxqp" and batched:
        f, solved = solve_qps_batched(np.eye(n_muscles), -f_ref, -np.swapaxes(G, 1, 2), tau_bias, f_lo, f_hi,
                                      QP_EPS_ABS, max_iter, num_threads)
    elif solver == "proxqp":
        f, solved = _proxqp_solve(G, tau_bias, f_ref, f_lo, f_hi, max_iter)
    elif solver == "newton":
        f, solved = _newton_solve(G, tau_bias, np.asarray(f_ref, float), f_lo, f_hi, max_iter)
    else:
        f, solved = _qpsolvers_solve(G, tau_bias, f_ref, f_lo, f_hi, solver)
    f = np.clip(f, f_lo, f_hi)  # remove the solver's ~1e-12 excursions outside the box
    residual = np.abs(np.einsum("bmn,bm->bn", -G, f) - tau_bias).max(axis=1)
    return f, solved & (residual <= EQUILIBRIUM_TOL_NM)


@dataclass
class EquilibriumSamples:
    """Healthy samples in SI units: postures [rad], motor lengths [m], tensions [N]."""

    q: np.ndarray  # (n, N)
    l_motor: np.ndarray  # (n, M)
    f: np.ndarray  # (n, M)
    n_redrawn: int  # infeasible draws that were replaced

    @property
    def accepted_fraction(self) -> float:
        """Share of drawn postures that some tensions could hold (the rest were re-drawn)."""
        return len(self.q) / (len(self.q) + self.n_redrawn)


def _unholdable_message(model: MusculoskeletalModel, n_kept: int, n_drawn: int, spring: SpringParams,
                        shortfall_nm: np.ndarray) -> str:
    """The error when too few postures can be held: which joints the muscles fail to hold, and what to do."""
    median = np.median(shortfall_nm, axis=0) if len(shortfall_nm) else np.zeros(model.n_joints)
    worst = np.argsort(-median)
    names = [f"{model.joint_names[j]} ({median[j]:.3g} N m)" for j in worst if median[j] > EQUILIBRIUM_TOL_NM][:6]
    return (f"only {n_kept} of {n_drawn} postures ({100 * n_kept / max(n_drawn, 1):.2g} %) can be held in equilibrium "
            f"with f_max={spring.f_max_n} N: the muscles are too weak for this model's gravity at joints {names} (median torque shortfall of the "
            "unholdable draws): lock them (data.locked_joints: {name: rad}), narrow their range, or raise f_max_n")


def generate_equilibrium_samples(model: MusculoskeletalModel, n: int, seed: int,
                                 spring: SpringParams = SpringParams(), solver: str = "newton",
                                 max_draw_factor: int = 20, qp=None) -> EquilibriumSamples:
    """Draw ``n`` healthy equilibrium samples: uniform q in the joint range, uniform f_ref in [0, f_max].

    Postures no tension can hold are re-drawn; at most ``max_draw_factor * n`` postures are drawn (an
    accepted fraction of 1/max_draw_factor), past which the error names the joints the muscles fail to hold.
    qp: the tension solve, called as ``solve_equilibrium_qp`` (its default) is; ``sim.sampling`` passes one whose
    answers are the same bytes in every process.
    """
    if int(n) != n or n <= 0:
        raise BodySchemaInputError(f"dataset size n={n!r} must be a positive integer")
    rng = np.random.default_rng(seed)
    f_max = np.broadcast_to(np.asarray(spring.f_max_n, float), (model.n_muscles,))
    kept, n_drawn, shortfall = [], 0, []
    while sum(len(k[0]) for k in kept) < n:
        if n_drawn >= max_draw_factor * n:
            raise BodySchemaInputError(_unholdable_message(model, sum(len(k[0]) for k in kept), n_drawn, spring,
                                                           np.concatenate(shortfall)))
        batch = n - sum(len(k[0]) for k in kept)
        q = model.sample_q(rng, batch)
        f_ref = f_max * rng.random((batch, model.n_muscles))
        l_geo, G, tau_bias = model.kinematics(q)
        f, ok = (qp or solve_equilibrium_qp)(G, tau_bias, f_ref, f_max, solver=solver)
        kept.append((q[ok], l_geo[ok] - elongation_from_tension(f[ok], spring), f[ok]))
        shortfall.append(np.abs(np.einsum("bmn,bm->bn", -G[~ok], f[~ok]) - tau_bias[~ok]))
        n_drawn += batch
    q, l_motor, f = (np.concatenate(parts)[:n] for parts in zip(*kept))
    return EquilibriumSamples(q=q, l_motor=l_motor, f=f, n_redrawn=n_drawn - n)
