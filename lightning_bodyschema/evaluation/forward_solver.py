"""The posture ``q_hat`` that a command ``(l_motor, f)`` would realize (paper section IV-B).

Physical simulation with slack wires is hard, so the paper (and we) find ``q_hat`` by optimisation:

    min_q  sum_i rho_huber(r_i(q) / s_l) + lambda_tau ||tau(q) / s_tau||^2 + lambda_q ||q - q_ref||^2

with, re-classified at every iterate (E = taut set, see ``classify_muscles``):

* taut muscles  i in E:            r_eq    = l_motor_i + phi^-1(f_i) - l_geo_i(q)
* slack healthy muscles i not in E: r_slack = max(0, l_geo_i(q) - l_motor_i)
* jammed muscles j:                 r_fix   = max(0, l_geo_j(q) - (l_fixed_j + phi^-1(f_j)))
* ruptured muscles:                 excluded
* torque imbalance tau(q) = -G(q)^T f_eff - tau_bias(q), ``f_eff = f`` on E and 0 elsewhere.

The two faults beyond the paper (weakened muscles, banded motors) rewrite the command before the solve
(``posture_command.prepare_command``); without them every array is the paper's, bit for bit.

The paper writes the length terms as ``sum w_i (r_i/s_l)^2`` solved by IRLS "minimizing the Huber
loss"; we take the Huber loss itself, ``rho(u) = u^2 (|u| <= d), 2 d |u| - d^2 (otherwise)``, as the
true objective and ``w = min(1, d/|u|)`` as the IRLS weights (the weighted quadratic majorizes rho,
so IRLS steps descend on it).

Solver: batched Levenberg-Marquardt (``(J^T W J + mu I) dq = -J^T W r``) on all still-running cases at
once, started at q_ref; one ``model.kinematics`` call per iterate, which also carries the
forward-difference postures of the torque Jacobian. A step is kept only if the true objective
decreases; mu follows Fletcher's gain-ratio rule (as in mujoco's ``minimize.least_squares``), and a
step is at most ``max_step_rad`` long. Joint limits are honoured by a projected step: joints held at a
limit by the gradient are frozen, the rest are clipped into ``model.q_range``.

Jacobians: d r_eq/dq = -G, d r_slack/dq = d r_fix/dq = +G where the hinge is active, 0 otherwise
(exact, from MuJoCo's G). d tau/dq by forward differences (step 1e-6 rad) of MuJoCo's G and
tau_bias with f_eff held fixed, because neither is constant on a general MJCF (on the paper arm G is).

The objective is discontinuous: a taut muscle that turns slack drops its r_eq (a jump of about
rho(phi^-1(f)/s_l)) and its tension from the torque balance. Hence many cases stop with
NO_IMPROVEMENT at such a seam (a local minimum of the true objective to solver precision), and
q_hat is the local minimum reached from q_ref, not a global one.

numpy only; never imports Lightning.
"""
from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from ..errors import BodySchemaInputError
from ..sim.model import MusculoskeletalModel
from ..sim.spring import SpringParams
from .posture_command import PostureCommand, prepare_command


class SolverStatus(enum.IntEnum):
    """Why the solver stopped for one case (stored as ints in ``PostureResult.status``)."""

    G_TOL = 0  # gradient on the free joints below gtol: converged
    DX_TOL = 1  # an accepted step shorter than xtol [rad]: converged
    NO_IMPROVEMENT = 2  # mu reached mu_max and no step lowered the objective: a kink (taut/slack switch)
    MAX_ITER = 3  # iteration budget used up
    NONFINITE_COMMAND = 4  # l_motor or f has NaN/inf: not solved, q_hat is NaN
    F_TOL = 5  # the model predicts a decrease below floating-point resolution of the objective: converged


CONVERGED = (SolverStatus.G_TOL, SolverStatus.DX_TOL, SolverStatus.F_TOL)
_F_RESOLUTION = 1e-12  # relative objective decrease that rounding can no longer show


@dataclass(frozen=True)
class ForwardSolverParams:
    """Objective weights (paper values) and solver settings.

    ``huber_delta`` is in units of ``s_l``: 0.1 means residuals up to 3 mm count quadratically and
    larger ones linearly. 3 mm is about half the spring's full stretch (delta(f_max) ~ 7 mm), so a
    consistent command stays in the quadratic (Gauss-Newton) regime while one muscle that cannot be
    satisfied (centimetres off) does not drag q_hat on its own.
    """

    eps_slack_m: float = 1e-5  # slack tolerance epsilon^slack [m]
    s_l_m: float = 0.03  # length scale s_l [m]
    s_tau_nm: float = 5.0  # torque scale s_tau [N m]
    lambda_tau: float = 0.1  # weight of the static-equilibrium term
    lambda_q: float = 1e-3  # weight of the prior toward q_ref [1/rad^2]
    huber_delta: float = 0.1  # Huber threshold on r / s_l (dimensionless)
    max_iter: int = 300  # iterations (= kinematics calls) per case; IRLS converges linearly
    xtol_rad: float = 1e-9  # converged when an accepted step is shorter than this [rad]
    gtol: float = 1e-12  # converged when |J^T W r| on free joints is below this [1/rad]
    mu_min: float = 1e-9  # Levenberg damping floor [1/rad^2]
    mu_max: float = 1e8  # give up (NO_IMPROVEMENT) when rejections push mu past this
    mu_factor: float = 10.0  # damping multiplier on rejection / poor gain
    fd_step_rad: float = 1e-6  # forward-difference step for d tau / d q [rad]
    max_step_rad: float = 0.5  # longest step per iteration [rad]: keeps the search near q_ref
    curvature: str = "irls"  # "irls" (paper): w = min(1, d/|u|); "newton": rho''/2 in {0, 1}
    jammed_tension_in_torque: bool = False  # paper: E excludes jammed muscles, so f_eff_j = 0

    def __post_init__(self):
        positive = ("eps_slack_m", "s_l_m", "s_tau_nm", "huber_delta", "max_iter", "xtol_rad",
                    "gtol", "mu_min", "mu_max", "fd_step_rad", "max_step_rad")
        for name in positive:
            value = getattr(self, name)
            if not np.isfinite(value) or value <= 0:
                raise BodySchemaInputError(f"ForwardSolverParams.{name}={value!r} must be finite and > 0")
        for name in ("lambda_tau", "lambda_q"):
            if not np.isfinite(getattr(self, name)) or getattr(self, name) < 0:
                raise BodySchemaInputError(f"ForwardSolverParams.{name} must be finite and >= 0")
        if self.curvature not in ("irls", "newton"):
            raise BodySchemaInputError(f"ForwardSolverParams.curvature={self.curvature!r}; use 'irls' or 'newton'")
        if self.mu_factor <= 1:
            raise BodySchemaInputError(f"ForwardSolverParams.mu_factor={self.mu_factor!r} must be > 1")


@dataclass
class PostureResult:
    """Batched solver output; prints nothing, like mujoco's ``minimize``.

    q_hat (B, N) [rad]; status (B,) ``SolverStatus`` ints; n_iter (B,) kinematics calls per case;
    objective (B,) at q_hat; taut (B, M) the set E at q_hat; tau_nm (B, N) the torque imbalance
    ``-G^T f_eff - tau_bias`` at q_hat [N m]. Rows of NONFINITE_COMMAND cases are NaN.
    """

    q_hat: np.ndarray
    status: np.ndarray
    n_iter: np.ndarray
    objective: np.ndarray
    taut: np.ndarray
    tau_nm: np.ndarray

    @property
    def converged(self) -> np.ndarray:
        """(B,) bool: stopped on the gradient or step tolerance."""
        return np.isin(self.status, [int(s) for s in CONVERGED])

    @property
    def solved(self) -> np.ndarray:
        """(B,) bool: converged, or stopped at a kink no small step improves (a non-smooth local minimum)."""
        return self.converged | (self.status == SolverStatus.NO_IMPROVEMENT)

    @property
    def status_names(self) -> list[str]:
        return [SolverStatus(int(s)).name for s in self.status]


class _Point(NamedTuple):
    """Objective, residuals and Jacobians at a batch of postures."""

    q: np.ndarray  # (B, N)
    objective: np.ndarray  # (B,)
    r: np.ndarray  # (B, M) length residuals / s_l (0 for excluded muscles)
    J: np.ndarray  # (B, M, N) d r / d q
    rt: np.ndarray  # (B, N) sqrt(lambda_tau) tau / s_tau
    Jt: np.ndarray  # (B, N, N) d rt / d q (forward differences)
    taut: np.ndarray  # (B, M) set E
    tau: np.ndarray  # (B, N) torque imbalance [N m]


# ---------------------------------------------------------------------------- objective pieces
def huber(u: np.ndarray, delta: float) -> np.ndarray:
    """rho(u) = u^2 for |u| <= delta, 2 delta |u| - delta^2 beyond (same slope at the seam)."""
    a = np.abs(u)
    return np.where(a <= delta, u * u, 2.0 * delta * a - delta * delta)


def huber_weight(u: np.ndarray, delta: float) -> np.ndarray:
    """IRLS weight w = rho'(u) / (2u) = min(1, delta/|u|)."""
    return np.minimum(1.0, delta / np.maximum(np.abs(u), 1e-300))


def classify_muscles(l_geo, cmd: PostureCommand, params: ForwardSolverParams):
    """Taut set E, length residuals and their Jacobian signs (all (B, M)).

    E = {i not cut, not jammed | f_i > 0, l_geo_i - l_motor_i >= -eps_slack} (paper, verbatim).
    A weakened muscle's overstretch terms (-r_eq, r_slack, r_fix) stop growing at its slip margin ``slip_m``.
    Returns ``taut``, ``r`` [m] and ``sign`` with d r / d q = sign * G.
    """
    healthy = ~(cmd.cut | cmd.fix)
    stretch = l_geo - cmd.l_motor
    taut = healthy & (cmd.f > 0) & (stretch >= -params.eps_slack_m)
    slack = healthy & ~taut
    over_fix = np.maximum(0.0, l_geo - (cmd.l_fixed + cmd.delta))
    r_eq = cmd.l_motor + cmd.delta - l_geo
    cap = cmd.slip_m  # inf without weakened muscles: then every line below is the paper's, bit for bit
    r = np.where(taut, np.maximum(r_eq, -cap), 0.0)
    r = np.where(slack, np.minimum(np.maximum(0.0, stretch), cap), r)
    r = np.where(cmd.fix, np.minimum(over_fix, cap), r)
    sign = np.where(taut & (r_eq > -cap), -1.0, 0.0)
    sign = np.where((slack & (stretch > 0) & (stretch < cap)) | (cmd.fix & (over_fix > 0) & (over_fix < cap)),
                    1.0, sign)
    return taut, r, sign


def effective_tension(l_geo, taut, cmd: PostureCommand, params: ForwardSolverParams):
    """f_eff (B, M) [N]: f on E (paper); optionally also on taut jammed muscles.

    ``jammed_tension_in_torque`` is not the paper: a jammed wire still pulls on the joints. Its motor
    sits at min(l_motor, l_fixed) (it can reel in, not pay out), so it counts when f > 0 and
    l_geo - min(l_motor, l_fixed) >= -eps_slack.
    """
    mask = taut
    if params.jammed_tension_in_torque:
        motor = np.minimum(cmd.l_motor, cmd.l_fixed)
        mask = mask | (cmd.fix & (cmd.f > 0) & (l_geo - motor >= -params.eps_slack_m))
    return np.where(mask, cmd.f, 0.0)


def _torque(G, tau_bias, f_eff):
    """tau = -G^T f_eff - tau_bias [N m], batched over leading axes."""
    return -np.einsum("...mn,...m->...n", G, f_eff) - tau_bias


# ---------------------------------------------------------------------------- evaluation at postures
def _stacked_kinematics(model: MusculoskeletalModel, q, h):
    """One kinematics call for q and the N forward-difference postures q + h e_k."""
    batch, n = q.shape
    q_all = np.concatenate([q[None], q[None] + h * np.eye(n)[:, None, :]]).reshape(-1, n)
    l_geo, G, bias = model.kinematics(q_all)
    shape = lambda a: a.reshape((n + 1, batch) + a.shape[1:])  # noqa: E731
    return shape(l_geo)[0], shape(G), shape(bias)


def _evaluate(model, q, cmd: PostureCommand, params: ForwardSolverParams) -> _Point:
    """Objective, residuals and Jacobians at q (B, N).

    d tau / d q by forward differences of MuJoCo's G and tau_bias with f_eff held fixed: G varies
    with q on a general MJCF (wrapping, via points) and gravity torque always does; the FD postures
    ride along in the same batched kinematics call, so the cost is (N+1) postures per case.
    """
    l_geo, G_all, bias_all = _stacked_kinematics(model, q, params.fd_step_rad)
    G = G_all[0]
    taut, r, sign = classify_muscles(l_geo, cmd, params)
    f_eff = effective_tension(l_geo, taut, cmd, params)
    tau_all = _torque(G_all, bias_all, f_eff[None])  # (N+1, B, N)
    dtau = np.moveaxis((tau_all[1:] - tau_all[0]) / params.fd_step_rad, 0, -1)  # (B, N, N): [:, n, k]
    t_scale = np.sqrt(params.lambda_tau) / params.s_tau_nm
    u = r / params.s_l_m
    rt = t_scale * tau_all[0]
    prior = params.lambda_q * np.sum((q - cmd.q_ref) ** 2, axis=1)
    objective = huber(u, params.huber_delta).sum(axis=1) + np.sum(rt ** 2, axis=1) + prior
    J = sign[..., None] * G / params.s_l_m
    return _Point(q, objective, u, J, rt, t_scale * dtau, taut, tau_all[0])


# ---------------------------------------------------------------------------- one LM step
def _normal_equations(p: _Point, cmd: PostureCommand, params: ForwardSolverParams):
    """Gauss-Newton Hessian H (B, N, N) and half-gradient g (B, N) of the IRLS-weighted objective."""
    w_irls = huber_weight(p.r, params.huber_delta)  # w r = rho'(r)/2: the gradient in both variants
    if params.curvature == "irls":
        w = w_irls
    else:  # rho''/2: 1 in the quadratic zone, 0 in the linear zone
        w = (np.abs(p.r) <= params.huber_delta).astype(float)
    H = np.einsum("bmi,bm,bmj->bij", p.J, w, p.J) + np.einsum("bki,bkj->bij", p.Jt, p.Jt)
    H = H + params.lambda_q * np.eye(p.q.shape[1])
    g = np.einsum("bmi,bm->bi", p.J, w_irls * p.r) + np.einsum("bki,bk->bi", p.Jt, p.rt)
    return H, g + params.lambda_q * (p.q - cmd.q_ref)


def _free_joints(q, g, q_range):
    """Joints not held at a limit by the gradient (projected Newton active set)."""
    lo, hi = q_range[:, 0], q_range[:, 1]
    return ~(((q <= lo) & (g > 0)) | ((q >= hi) & (g < 0)))


def _lm_step(H, g, free, mu, max_step):
    """Solve (H + mu I) dq = -g on the free joints (frozen joints get dq = 0); cap |dq| at max_step."""
    n = g.shape[1]
    both = free[:, :, None] & free[:, None, :]
    A = np.where(both, H, 0.0) + np.eye(n) * np.where(free, mu[:, None], 1.0)[:, :, None]
    dq = np.linalg.solve(A, -np.where(free, g, 0.0)[..., None])[..., 0]
    norm = np.linalg.norm(dq, axis=1, keepdims=True)
    return dq * np.minimum(1.0, max_step / np.maximum(norm, 1e-300))


# ---------------------------------------------------------------------------- the solver
def solve_posture(model: MusculoskeletalModel, l_motor, f, q_ref, cut, fix, l_fixed,
                  spring: SpringParams = SpringParams(),
                  params: ForwardSolverParams = ForwardSolverParams(), *,
                  f_max_n=None, l_band_m=None) -> PostureResult:
    """The postures q_hat (B, N) [rad] that commands (l_motor [m], f [N]) (B, M) would realize.

    ``cut``/``fix`` (B, M) bool mark ruptured / jammed muscles; ``l_fixed`` (B, M) [m] is the motor
    length at jamming (ignored, may be NaN, where not jammed). ``f_max_n`` (B, M) [N]: a weakened
    muscle's tension limit f_max'; ``l_band_m`` (B, M, 2) [m]: a banded motor's [lo, hi]; NaN (or None
    for the batch) where there is no such fault. The search starts at ``q_ref`` (clipped into the joint
    limits) and stays inside ``model.q_range``. ``tau_nm`` counts a weakened muscle at ``min(f, f_max')``.
    """
    cmd, finite = prepare_command(model, l_motor, f, q_ref, cut, fix, l_fixed, spring, f_max_n, l_band_m)
    batch, n_j, n_m = cmd.q_ref.shape[0], model.n_joints, model.n_muscles
    out = PostureResult(np.full((batch, n_j), np.nan), np.full(batch, int(SolverStatus.MAX_ITER), np.int8),
                        np.zeros(batch, int), np.full(batch, np.nan), np.zeros((batch, n_m), bool),
                        np.full((batch, n_j), np.nan))
    out.status[~finite] = SolverStatus.NONFINITE_COMMAND
    idx = np.flatnonzero(finite)
    if idx.size:
        _run(model, cmd.take(idx), idx, params, out)
    return out


def _finish(out: PostureResult, idx, p: _Point, mask, status):
    """Write the current point of the cases ``idx[mask]`` into the result, with their status."""
    if mask.any():
        rows = idx[mask]
        out.q_hat[rows], out.objective[rows] = p.q[mask], p.objective[mask]
        out.taut[rows], out.tau_nm[rows] = p.taut[mask], p.tau[mask]
        out.status[rows] = status


def _keep(p: _Point, cmd: PostureCommand, idx, mu, keep):
    """Drop finished cases from every per-case array, so later iterates cost only the running ones."""
    return _Point(*(a[keep] for a in p)), cmd.take(keep), idx[keep], mu[keep]


def _run(model, cmd: PostureCommand, idx, params: ForwardSolverParams, out: PostureResult):
    """Batched Levenberg-Marquardt; ``idx`` maps the rows of ``cmd`` to rows of ``out``."""
    p = _evaluate(model, cmd.q_ref, cmd, params)
    mu = np.full(len(idx), params.mu_min)
    out.n_iter[idx] = 1
    for _ in range(params.max_iter - 1):
        H, g = _normal_equations(p, cmd, params)
        free = _free_joints(p.q, g, model.q_range)
        done = np.max(np.abs(np.where(free, g, 0.0)), axis=1) <= params.gtol
        _finish(out, idx, p, done, SolverStatus.G_TOL)
        if done.all():
            return
        H, g, free = H[~done], g[~done], free[~done]
        p, cmd, idx, mu = _keep(p, cmd, idx, mu, ~done)
        q_try = np.clip(p.q + _lm_step(H, g, free, mu, params.max_step_rad), *model.q_range.T)
        trial = _evaluate(model, q_try, cmd, params)
        out.n_iter[idx] += 1
        p, mu, status = _accept(p, trial, H, g, mu, params)
        for code in (SolverStatus.DX_TOL, SolverStatus.F_TOL, SolverStatus.NO_IMPROVEMENT):
            _finish(out, idx, p, status == code, code)
        running = status < 0
        if not running.any():
            return
        p, cmd, idx, mu = _keep(p, cmd, idx, mu, running)
    _finish(out, idx, p, np.ones(len(idx), bool), SolverStatus.MAX_ITER)


def _accept(p: _Point, trial: _Point, H, g, mu, params: ForwardSolverParams):
    """Keep the trial where the true objective fell; adapt mu by the gain ratio (Fletcher 1971).

    Returns the new point, mu and a (B,) status: DX_TOL / NO_IMPROVEMENT for stopped cases, -1 else.
    An undamped (mu at its floor) step shorter than xtol also counts as converged even if rounding
    kept the objective from falling: Gauss-Newton has nothing left to move.
    """
    step = trial.q - p.q
    better = trial.objective < p.objective
    predicted = -(2.0 * np.einsum("bi,bi->b", g, step) + np.einsum("bi,bij,bj->b", step, H, step))
    ratio = (p.objective - trial.objective) / np.maximum(predicted, 1e-300)
    small = (better | (mu <= params.mu_min)) & (np.linalg.norm(step, axis=1) < params.xtol_rad)
    # a rejected step whose predicted gain is below rounding: nothing measurable is left to gain
    flat = ~better & ~small & (predicted <= _F_RESOLUTION * np.abs(p.objective))
    mu = np.where(better & (ratio > 0.75), np.maximum(mu / params.mu_factor, params.mu_min), mu)
    mu = np.where(~better | (ratio < 0.25), mu * params.mu_factor, mu)
    new = _Point(*(np.where(better.reshape((-1,) + (1,) * (a.ndim - 1)), t, a) for t, a in zip(trial, p)))
    status = np.where(small, int(SolverStatus.DX_TOL), np.where(flat, int(SolverStatus.F_TOL), -1))
    status = np.where(~small & ~better & (mu > params.mu_max), int(SolverStatus.NO_IMPROVEMENT), status)
    return new, mu, status
