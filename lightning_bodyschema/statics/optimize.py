"""Static optimization on the true body: the muscle tensions (and MuJoCo activations) that hold each posture, with
faults.

For each posture q (MuJoCo's kinematics: tendon lengths ``l(q)``, moment arms ``G = dl/dq``, the gravity and passive
torque ``tau_bias``), static equilibrium is ``-G^T f = tau_bias`` (``sim.model``). The tensions are bounded per
muscle, then one box QP with an identity Hessian is solved per posture (batched: ``sim.equilibrium``):

* ``objective="activation"`` (the default on bodies whose muscles are MuJoCo ``<muscle>`` actuators, e.g. MyoSuite):
  ``min sum a^2`` over activations ``0 <= a <= 1``, tension ``f = s(l) a + p(l)`` (``statics.muscles``: MuJoCo's
  force-length and passive curves at zero velocity). This is OpenSim's Static Optimization criterion (activation
  squared), what a MyoSuite user means by the word: load shared by the muscles' strength at their current length,
  passive force included.
* ``objective="tension"``: ``min ||f - f_ref||^2`` (``f_ref`` default 0: ``min sum f^2``), the dataset's objective
  (``sim.equilibrium``). On a body with muscle actuators the tensions stay those of activations in [0, 1]; on one
  without (a robot whose muscles are motors and springs) they lie in ``[0, f_max]`` of its spring
  (``sim.spring.spring_for_model``).

Faults (``faults.Faults``) bound the tensions as in ``faults.qp``: a cut muscle carries nothing (passive force
included: the tendon is ruptured), a weakened one at most its ``f_max_n``, a jammed motor or a length band bounds
``l_motor = l - delta(f)`` through the spring. Motor lengths follow from the spring.

Status per posture (``status.Status``): ``ok`` (holds, activations in [0, 1]), ``activation_above_one`` (held only
with some activation above 1: the answer with the cap lifted is returned), ``infeasible`` (no tension within the
bounds holds it: NaN), ``not_converged`` (the solver gave up without proving it infeasible: NaN).
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Mapping, Optional

import numpy as np
import torch

from ..errors import BodySchemaInputError
from ..faults.faults import Faults
from ..faults.bounds import FaultBounds
from .._numpy import to_numpy
from ..sim.model import MusculoskeletalModel, check_threads
from ..sim.spring import spring_for_model
from ..solvers import BoxQP, solve_box_qp, uncrossed_box
from ..status import Status, status_array
from .muscles import MuscleCurves, read_muscle_curves
from .qp_blocks import solve_in_pieces

OBJECTIVES = ("activation", "tension")
FAULT_KINDS = ("cut", "jam", "weak", "band")
# the dual Newton's stop [N m]: its tensions then agree with a tightly solved proxsuite's to ~1e-9 N
STATIC_TOL_NM = 1e-12
PROXQP_EPS, PROXQP_MAX_ITER = 1e-12, 100  # proxsuite's absolute tolerance (eps_rel 0) and outer iterations: a feasible
# row converges well within them; an unholdable one the screen misses runs to the limit (at 2000, seconds per row)


@dataclass
class StaticResult:
    """Static optimization of B postures: SI units, rows in the order of ``q``.

    tension_n (B, M) [N]; l_motor_m (B, M) motor lengths through the spring [m]; activation (B, M) MuJoCo muscle
    activations (None on a body without muscle actuators); status (B,) ``Status`` members. Rows whose status is
    ``infeasible`` or ``not_converged`` are NaN.
    """

    joints: list
    muscles: list
    q: np.ndarray
    tension_n: np.ndarray
    l_motor_m: np.ndarray
    activation: Optional[np.ndarray]
    status: np.ndarray
    objective: str
    faults: Faults
    actuators: list = field(default_factory=list)

    def take(self, idx) -> "StaticResult":
        """The rows ``idx`` (indices or a (B,) bool mask)."""
        pick = lambda a: None if a is None else np.asarray(a)[idx]  # noqa: E731
        return replace(self, q=pick(self.q), tension_n=pick(self.tension_n), l_motor_m=pick(self.l_motor_m),
                       activation=pick(self.activation), status=pick(self.status), faults=self.faults.take(idx))

    @property
    def ok(self) -> np.ndarray:
        """(B,) True where the posture is held with activations in [0, 1]."""
        return np.array([s is Status.OK for s in self.status], dtype=bool)


def check_solver(solver: str) -> None:
    if solver not in ("newton", "proxqp"):
        raise BodySchemaInputError(f"solver={solver!r}; allowed: ['newton', 'proxqp']")


def _solve_box_qp(G, column_scale, tau_nm, x_ref, lo, hi, solver: str, device=None, motion: bool = False):
    """``argmin ||x - x_ref||^2  s.t.  -(G c)^T x = tau,  lo <= x <= hi`` per row (B, M) and its status codes (B,),
    ``G c`` the moment arms ``G`` (B, M, N) with each muscle's row scaled by ``column_scale`` (B, M): the one QP,
    ``solvers.solve_box_qp`` by ``solver``: ``"newton"`` (the dual Newton to ``STATIC_TOL_NM``, the torque-reach
    screen, proxsuite within ``PROXQP_MAX_ITER`` on what they leave) or ``"proxqp"`` (proxsuite alone to
    ``PROXQP_EPS``) on torch ``device`` (None: the CPU), called per independent block and chunk of rows
    (``statics.qp_blocks``, which scales each piece's G: no scaled copy of the whole); ``motion``: the rows are a
    motion's consecutive frames, warm-started with ``"newton"`` (``statics.warm_start``). The caller discards the x
    of rows not ``ok``."""
    warm_tol_nm = STATIC_TOL_NM if motion and solver == "newton" else None
    return solve_in_pieces(lambda *arrays: _solve_piece(*arrays, solver, device), G, column_scale, tau_nm, x_ref, lo,
                           hi, device, warm_tol_nm)


@torch.inference_mode()  # numpy in and out: no tensor here needs autograd's version counters
def _solve_piece(G, tau_nm, x_ref, lo, hi, solver: str, device=None):
    """``_solve_box_qp`` of one block and chunk: one solver call."""
    solution = solve_box_qp(BoxQP.build(G, tau_nm, x_ref, lo, hi, device=device), solver, tol=STATIC_TOL_NM,
                            fallback_max_iter=PROXQP_MAX_ITER, fallback_eps_abs=PROXQP_EPS, least_squares=False)
    return np.clip(to_numpy(solution.f_n), lo, hi), to_numpy(solution.status)


class StaticBody:
    """The true body of static optimization, built once: a ``MusculoskeletalModel`` (any MJCF path, packaged name or
    ``myo:<name>``; ``muscles``, ``gravity``, ``locked_joints``, ``fixed_base`` as the data module takes them; the
    model's own ``<equality joint>`` couplings hold), its spring (``k_n``, ``alpha_per_m``, ``f_max_n``:
    ``sim.spring.spring_for_model``) and, where every muscle has one, its MuJoCo muscle actuators' curves.
    ``threads``: MuJoCo's kinematics of a batch on that many threads (the same answers whatever the count)."""

    def __init__(self, model: str = "paper_arm", muscles=None, gravity=None, locked_joints=None,
                 fixed_base: bool = False, k_n=None, alpha_per_m=20.0, f_max_n=None, threads: int = 1):
        if not isinstance(model, str):
            raise BodySchemaInputError(f"model={model!r}: give a packaged name, myo:<name>, an MJCF path or MJCF "
                                       "text (a StaticBody is built from the model's source)")
        self.model = MusculoskeletalModel(model, muscles=muscles, gravity=gravity, locked_joints=locked_joints,
                                          fixed_base=fixed_base)
        self.source, self.fixed_base = model, fixed_base  # a floating root's dynamics reads the source's free joints
        self.spring = spring_for_model(self.model, k_n, alpha_per_m, f_max_n)
        self.curves: Optional[MuscleCurves] = read_muscle_curves(model, self.model.muscle_names, fixed_base)
        self.threads = check_threads(threads)  # refused now, not at the first solve

    @property
    def default_objective(self) -> str:
        """``"activation"`` where every muscle is a MuJoCo muscle actuator, else ``"tension"``."""
        return "activation" if self.curves is not None else "tension"

    def fault_batch(self, faults, batch: int) -> Faults:
        """``faults`` (None, a ``Faults`` of 1 or ``batch`` rows, or ``{"cut": [names], "jam": {name: l_fixed_m},
        "weak": {name: f_max_n}, "band": {name: [lo_m, hi_m]}}``) as a validated ``Faults`` of ``batch`` rows."""
        names = self.model.muscle_names
        if faults is None:
            return Faults.none(batch, len(names))
        if isinstance(faults, Mapping):
            unknown = sorted(set(faults) - set(FAULT_KINDS))
            if unknown:
                raise BodySchemaInputError(f"unknown fault kind(s) {unknown}; allowed: {list(FAULT_KINDS)}")
            cut = faults.get("cut", ())
            cut = [cut] if isinstance(cut, str) else list(cut)
            faults = Faults.from_names(names, cut=[cut], jam=dict(faults.get("jam", {})),
                                       weak=dict(faults.get("weak", {})), band=dict(faults.get("band", {})), n_cases=1)
        if not isinstance(faults, Faults):
            raise BodySchemaInputError(f"faults is a {type(faults).__name__}; give a Faults, a dict with keys "
                                       f"{list(FAULT_KINDS)}, or None")
        faults.validate(len(names))
        if len(faults) not in (1, batch):
            raise BodySchemaInputError(f"faults has {len(faults)} rows for {batch} postures; give 1 or {batch}")
        return faults if len(faults) == batch else faults.take(np.zeros(batch, dtype=int))

    def fault_bounds(self, faults: Faults) -> FaultBounds:
        """``faults`` as SI bounds: the spring's f_max caps tensions on a body without muscle curves, nothing on one
        with them (their activations are capped instead)."""
        return FaultBounds.from_faults(faults, self.spring.f_max_n if self.curves is None else np.inf, self.spring)

    def tension_bounds(self, l_geo_m, faults: Faults, bounds: Optional[FaultBounds] = None):
        """``(lo, hi, s, p)`` (B, M) [N]: the tensions the faults and the spring allow (``fault_bounds``), and the
        affine tension ``f = s a + p`` (None without curves); a cut muscle has ``s = p = 0``."""
        lo, hi = (bounds or self.fault_bounds(faults)).tension_box(l_geo_m)
        if self.curves is None:
            return lo, hi, None, None
        s, p = self.curves.affine(l_geo_m)
        s, p = np.where(faults.cut, 0.0, s), np.where(faults.cut, 0.0, p)
        return np.maximum(lo, p), hi, s, p

    def solve(self, q, faults=None, objective: Optional[str] = None, f_ref=None, solver: str = "newton"):
        """``StaticResult`` of postures ``q (B, N)`` (free joints, ``model.joint_names``; inside their ranges) under
        ``faults`` (see ``fault_batch``); ``objective``: ``"activation"`` or ``"tension"`` (module docstring; default
        ``default_objective``); ``f_ref`` (M,) or (B, M) [N]: the tension objective's reference (default 0);
        ``solver``: ``"newton"`` (batched, proxsuite where it stalls) or ``"proxqp"`` (proxsuite per posture)."""
        objective = self._objective(objective)
        q = self.model.check_q(q, within_range=True)
        faults = self.fault_batch(faults, len(q))
        check_solver(solver)
        l_geo, G, tau = self.model.kinematics(q, self.threads)
        return self.solve_torque(q, l_geo, G, tau, faults, objective, f_ref, solver)[0]

    def solve_torque(self, q, l_geo, G, tau_nm, faults: Faults, objective: str, f_ref=None, solver: str = "newton",
                     active_factor=None, residual=None, device=None, motion: bool = False):
        """``(StaticResult, residual (B, R) [N m] or None)``: the optimization of ``solve`` on given kinematics, the
        muscles holding ``-G^T f = tau_nm`` (B, N) at tendon lengths ``l_geo`` (B, M) with moment arms ``G`` (B, M, N)
        (``statics.dynamics`` passes the torque a motion needs). ``active_factor`` (B, M): a factor on each muscle's
        active force (MuJoCo's force-velocity curve; None: 1). ``residual``: ``(directions (R, N), unit (R,))``
        residual actuators, each adding ``unit x`` [N m] along its direction with ``x^2`` in the objective, unbounded.
        ``device``: the QP's torch device (None: the CPU). ``motion``: the rows are a motion's consecutive frames (the
        QPs warm-started: ``statics.warm_start``). ``faults`` validated, ``objective`` checked by the caller."""
        bounds = self.fault_bounds(faults)
        lo, hi, s, p = self.tension_bounds(l_geo, faults, bounds)
        if s is not None and active_factor is not None:
            s = s * active_factor
        # the QP's variable: activations, or tensions in units of the mean f_max (the same argmin, and proxsuite's
        # absolute tolerance then means the same as on activations)
        unit = float(np.mean(self.spring.f_max_n))
        scale, offset = (s, p) if objective == "activation" else (np.full(lo.shape, unit), np.zeros_like(lo))
        x_ref = np.zeros_like(lo) if objective == "activation" else self._f_ref(f_ref, lo.shape) / unit
        capped = hi if s is None else np.minimum(hi, p + s)
        columns = _Columns(G, tau_nm, lo, scale, offset, x_ref, residual)
        f, status = _held(*columns.args(capped), solver, Status.OK, device, motion)
        if s is not None and (status != Status.OK).any():
            rest = status != Status.OK
            relaxed = np.minimum(hi, p + RELAXED_ACTIVATION * s)
            f[rest], status[rest] = _held(*columns.args(relaxed, rest), solver, Status.ACTIVATION_ABOVE_ONE, device,
                                          motion)
        f, residual_nm = f[:, :lo.shape[1]], (f[:, lo.shape[1]:] if residual is not None else None)
        activation = None if s is None else np.where(s > 0, (f - p) / np.where(s > 0, s, 1.0), f * 0.0)  # NaN stays
        if activation is not None:  # a relaxed answer within the cap is the capped problem's answer too
            with np.errstate(invalid="ignore"):
                status[(status == Status.ACTIVATION_ABOVE_ONE) & (activation.max(1) <= 1.0 + 1e-12)] = Status.OK
        return StaticResult(self.model.joint_names, self.model.muscle_names, q, f,
                            bounds.motor_length_m(l_geo, f), activation, status, objective,
                            faults, [] if self.curves is None else list(self.curves.actuators)), residual_nm

    def _objective(self, objective):
        objective = objective or self.default_objective
        if objective not in OBJECTIVES:
            raise BodySchemaInputError(f"objective={objective!r}; allowed: {list(OBJECTIVES)}")
        if objective == "activation" and self.curves is None:
            raise BodySchemaInputError("objective='activation' needs a MuJoCo <muscle> actuator on every muscle; this "
                                       "body has none on some: use objective='tension'")
        return objective

    def _f_ref(self, f_ref, shape):
        if f_ref is None:
            return np.zeros(shape)
        f_ref = np.asarray(f_ref, float)
        if f_ref.shape not in ((shape[1],), shape) or not np.isfinite(f_ref).all():
            raise BodySchemaInputError(f"f_ref has shape {f_ref.shape}; give finite tensions of shape ({shape[1]},) "
                                       f"or {shape} [N]")
        return np.broadcast_to(f_ref, shape).copy()


RELAXED_ACTIVATION = 1e3  # the activation cap of the second solve: held above it counts as infeasible


class _Columns:
    """The QP's columns: the muscles, then any residual actuators (unbounded, ``unit x`` [N m] along a direction of
    the joints, ``-G^T`` of it the torque: their G rows are ``-direction``)."""

    def __init__(self, G, tau_nm, lo, scale, offset, x_ref, residual):
        self.G, self.tau, self.lo, self.scale, self.offset, self.x_ref = G, tau_nm, lo, scale, offset, x_ref
        self.n_extra = 0
        if residual is not None:
            directions, unit = (np.asarray(a, float) for a in residual)
            batch, self.n_extra = len(G), len(unit)
            extra = lambda value: np.broadcast_to(value, (batch, self.n_extra))  # noqa: E731
            self.G = np.concatenate([G, np.broadcast_to(-directions, (batch, *directions.shape))], axis=1)
            self.lo, self.scale = np.hstack([lo, extra(-np.inf)]), np.hstack([scale, extra(unit)])
            self.offset, self.x_ref = np.hstack([offset, extra(0.0)]), np.hstack([x_ref, extra(0.0)])

    def args(self, hi, rows=slice(None)):
        """``_held``'s arrays with the muscles' upper bounds ``hi`` (B, M), of ``rows``."""
        hi = np.hstack([hi, np.full((len(hi), self.n_extra), np.inf)])
        return tuple(a[rows] for a in (self.G, self.tau, self.lo, hi, self.scale, self.offset, self.x_ref))


def _held(G, tau_nm, lo, hi, scale, offset, x_ref, solver: str, held: Status, device=None, motion: bool = False):
    """Tensions ``f = scale x + offset`` (B, M) [N] in ``[lo, hi]`` holding each posture, the QP in x, and the status:
    ``held`` where it holds, else ``infeasible`` (crossed bounds, a torque out of reach) or ``not_converged``;
    ``motion``: the rows are consecutive frames (``_solve_box_qp``)."""
    positive = scale > 0
    unit = np.where(positive, scale, 1.0)
    x_lo = np.where(positive, (lo - offset) / unit, np.where(lo <= offset, 0.0, 1.0))  # scale 0: f = offset
    x_hi = np.where(positive, (hi - offset) / unit, np.where(offset <= hi, 0.0, -1.0))
    column_scale, tau_x = np.where(positive, scale, 0.0), tau_nm + np.einsum("bmn,bm->bn", G, offset)
    x_lo, crossed = uncrossed_box(x_lo, x_hi)
    x, code = np.full(lo.shape, np.nan), np.full(len(lo), Status.INFEASIBLE.code)  # crossed: infeasible
    if not crossed.any():  # every row: no copies
        x, code = _solve_box_qp(G, column_scale, tau_x, x_ref, x_lo, x_hi, solver, device, motion)
    elif not crossed.all():
        x[~crossed], code[~crossed] = _solve_box_qp(*(a[~crossed] for a in (G, column_scale, tau_x, x_ref, x_lo, x_hi)),
                                                    solver, device, motion)
    ok = code == Status.OK.code
    status = status_array(code)
    status[ok] = held
    f = np.where(ok[:, None], scale * x + offset, np.nan)
    return f, status


def static_optimization(model, q, faults=None, objective: Optional[str] = None, f_ref=None, solver: str = "newton",
                        **body_options) -> StaticResult:
    """Static optimization of postures ``q (B, N)`` [rad or m] on the true body, with faults.

    ``model``: a ``StaticBody`` (build it once for many calls), or its source (a packaged name, ``myo:<name>``, an
    MJCF path or text), then ``body_options`` are ``StaticBody``'s (``locked_joints``, ``fixed_base``, ...).
    ``faults``: None, a ``faults.Faults`` (1 or B rows) or ``{"cut": [...], "jam": {...}, "weak": {...},
    "band": {...}}`` by muscle name. ``objective``: ``"activation"`` (``min sum a^2``, MuJoCo's muscle curves; the
    default where every muscle is a MuJoCo muscle actuator) or ``"tension"`` (``min ||f - f_ref||^2``). Returns a
    ``StaticResult`` (tensions [N], motor lengths [m], activations, per-row ``status.Status``); the objectives, the
    bounds and the statuses are in the module docstring. Postures outside the joint ranges, NaN and unknown muscle
    names raise ``BodySchemaInputError``.

        >>> body = StaticBody("myo:myoelbow_2dof")
        >>> result = static_optimization(body, [[0.0, 1.2]], faults={"cut": ["BIClong_tendon"]})
        >>> result.activation, result.status
    """
    body = model if isinstance(model, StaticBody) else StaticBody(model, **body_options)
    if isinstance(model, StaticBody) and body_options:
        raise BodySchemaInputError(f"options {sorted(body_options)} build a body; this StaticBody is already built")
    return body.solve(q, faults, objective, f_ref, solver)
