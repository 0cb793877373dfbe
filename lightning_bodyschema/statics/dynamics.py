"""Muscles for a motion: inverse dynamics with faults on the true body, batched over frames.

Per frame (free joints ``q``, ``qvel``, ``qacc``; every joint of the model from them through the locks and couplings,
``qacc_full = E qacc + (dE/dt) qvel``, ``sim/joints.py``), MuJoCo's inverse dynamics (``mj_inverse``'s answer by
a leaner call sequence, ``statics.mujoco_inverse``; constraints off: the free coordinates carry the locks and
couplings exactly) gives the generalized force the motion needs, ``M qacc + bias - passive`` (gravity, Coriolis,
joint damping and springs), and in the free joints ``tau = E^T qfrc_inverse``. A floating root: ``statics.root``. The
muscles must supply it: ``-G^T f = tau`` with ``f = FV(v) s(l) a + p(l)`` at each muscle's tendon velocity
``v = G qvel`` (MuJoCo's force-velocity curve, ``statics.muscles``). Then the static optimization's QP per frame
(``StaticBody.solve_torque``: ``min sum a^2`` or the tension objective, faults, statuses), all frames in one batch.

Residual actuators (``residual_dofs``: free joints, e.g. one the muscles cannot drive) add a torque ``r`` [N m] there
with ``residual_weight r^2`` in the objective (in the objective's units: activation^2, or (f / mean f_max)^2),
unbounded, reported per frame. ``control``: the excitations MuJoCo's activation dynamics turn from each frame's
activations into the next frame's over the frame step (``statics.activation``); the last frame holds its activation.
numpy, MuJoCo and torch (the QP, on any device); never imports Lightning.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Optional, Sequence

import mujoco
import numpy as np

from ..errors import BodySchemaInputError
from ..sim.mjcf import compile_spec
from ..sim.model import UNCROSSED_ARM_M
from .activation import excitation
from .optimize import StaticBody, StaticResult, check_solver
from .mujoco_inverse import assemble, lean_inverse, lean_model, uses_lean
from .root import FrameLayout, floating_spec, muscles_span_root

DEFAULT_RESIDUAL_WEIGHT = 1.0  # 1 N m of residual costs as much as one muscle at full activation


@dataclass
class MotionResult(StaticResult):
    """``StaticResult`` of B frames of a motion, plus: ``qvel``, ``qacc`` (B, N) [rad/s, rad/s^2] the frames' velocities
    and accelerations; ``tau_nm`` (B, N) the generalized force the motion needs (free joints); ``control`` (B, M)
    MuJoCo excitations in [0, 1] (None without muscle actuators; NaN where a frame or the next one has no
    activations); ``control_clipped`` (B, M) True where no excitation in [0, 1] reaches the next activation (the
    nearest is given); ``residual_nm`` (B, R) residual actuator torques on ``residual_dofs`` (None without);
    ``t`` (B,) [s]; on a floating root (``statics.root``): ``root_qpos`` (B, 7K), ``root_qvel``, ``root_qacc``
    (B, 6K) its motion and ``root_residual`` (B, 6K) the residual actuators that carry it, [N] along the world axes
    and [N m] about the root's own (``root_dofs`` names them); None on a body without one."""

    qvel: Optional[np.ndarray] = None
    qacc: Optional[np.ndarray] = None
    tau_nm: Optional[np.ndarray] = None
    control: Optional[np.ndarray] = None
    control_clipped: Optional[np.ndarray] = None
    residual_nm: Optional[np.ndarray] = None
    residual_dofs: list = field(default_factory=list)
    t: Optional[np.ndarray] = None
    root_qpos: Optional[np.ndarray] = None
    root_qvel: Optional[np.ndarray] = None
    root_qacc: Optional[np.ndarray] = None
    root_residual: Optional[np.ndarray] = None
    root_dofs: list = field(default_factory=list)

    def take(self, idx) -> "MotionResult":
        """The rows ``idx`` (indices or a (B,) bool mask); controls stay those computed on the whole motion."""
        pick = lambda a: None if a is None else np.asarray(a)[idx]  # noqa: E731
        rows = {k: pick(getattr(self, k)) for k in ("qvel", "qacc", "tau_nm", "control", "control_clipped",
                                                     "residual_nm", "t", "root_qpos", "root_qvel", "root_qacc",
                                                     "root_residual")}
        return replace(super().take(idx), **rows)


class InverseBody:
    """MuJoCo's inverse dynamics of a ``StaticBody``'s model: a private copy of the model (``floating``: with its
    source's free joints put back, ``statics.root``) with its constraints off (locks and couplings are carried by the
    free coordinates; contacts play no part), one ``MjData`` per thread (``body.threads``; the same numbers whatever
    the count). ``lean``: idle tendons left out and the lean call sequence (``statics.mujoco_inverse``); False: the
    whole model and ``mj_inverse`` itself, as a MuJoCo user calls it. Floating and lean: the muscles' paths are the
    welded body's (a path does not change when the whole body moves rigidly, and wrapping them again with 6 more dofs
    per root cost 2.5x the MuJoCo time on myoLegs), the forces the floating body's without any idle tendon."""

    def __init__(self, body: StaticBody, floating: bool = False, lean: bool = True):
        spec = floating_spec(body) if floating else mujoco.MjSpec.from_string(body.model.xml)
        self.arms = _inverse_body(body) if floating and lean else None  # the muscles' paths, welded
        if floating and lean and muscles_span_root(body.model.mj_model, body.model.muscle_ids):
            raise BodySchemaInputError("a muscle spans the floating root (its path touches the world or another "
                                       "root); muscles anchored outside the floating body are not supported")
        model = lean_model(spec, [] if self.arms else body.model.muscle_names) if lean else compile_spec(spec)
        self.body, self.layout = body, FrameLayout.of(body, floating, model)
        self.m = self.layout.m  # compiled here: this copy is private
        self.m.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_CONSTRAINT)
        self.lean = lean and uses_lean(self.m)
        self.datas = [mujoco.MjData(self.m) for _ in range(body.threads)]
        if self.arms is None:
            self.tendon_ids = np.array([mujoco.mj_name2id(self.m, mujoco.mjtObj.mjOBJ_TENDON, n)
                                        for n in body.model.muscle_names], dtype=int)
            self.index = self._muscle_index()
            self.plan = _ArmPlan.of(self.index, len(self.tendon_ids), self.layout, body.model.joint_map)

    def full_state(self, q, qvel, qacc):
        """Every joint's position, velocity and acceleration (B, nq) from the free joints' (B, N), and ``E``."""
        jm = self.body.model.joint_map
        full = jm.full_q(q)
        tangent = jm.tangent(q, full)
        qvel_full = np.einsum("bin,bn->bi", tangent, qvel)
        qacc_full = np.einsum("bin,bn->bi", tangent, qacc) + jm.tangent_rate(q, qvel, full)
        return full, qvel_full, qacc_full, tangent

    def inverse(self, q, qvel, qacc, root=None):
        """``(l_geo (B, M), G (B, M, N), tau (B, N), G_root, tau_root (B, 6K))``: tendon lengths, moment arms and the
        generalized force ``E^T qfrc_inverse`` [N m] the motion needs in the free joints (module docstring), and on a
        floating root (``root``: its checked ``(qpos, qvel, qacc)``) the root's generalized force [N, N m] and the
        muscles' moment arms about its dofs (B, M, 6K) (None where the paths are the welded body's: zero; both None
        without a root)."""
        full, qvel_full, qacc_full, tangent = self.full_state(q, qvel, qacc)
        layout = self.layout
        lengths, ten_j, force = self._run(layout.state(full, qvel_full, qacc_full, root), self.arms is None, True)
        rest_force = force if not layout.floating else force[:, layout.rest_dof]
        tau = np.einsum("bjn,bj->bn", tangent, rest_force)
        tau_root = None if not layout.floating else force[:, layout.root_dof]
        if self.arms is not None:
            return (*self.arms.paths(full, tangent), tau, None, tau_root)
        if not layout.floating:
            return lengths[:, self.tendon_ids], self.plan.moment_arms(ten_j, tangent), tau, None, None
        jac = self._jacobian(ten_j)
        return (lengths[:, self.tendon_ids], jac[:, :, layout.rest_dof] @ tangent, tau, jac[:, :, layout.root_dof],
                tau_root)

    def paths(self, full, tangent):
        """``(l_geo (B, M), G (B, M, N))`` at every joint's positions ``full`` (B, nq): MuJoCo's kinematics alone."""
        lengths, ten_j, _ = self._run((full, None, None), True, False)
        return lengths[:, self.tendon_ids], self.plan.moment_arms(ten_j, tangent)

    def _jacobian(self, ten_j):
        """(B, M, nv) the muscles' rows of every frame's sparse ``ten_J`` (B, nnz): one gather and scatter."""
        rows, cols, entries = self.index
        jac = np.zeros((len(ten_j), len(self.tendon_ids), self.m.nv))
        jac[:, rows, cols] = ten_j[:, entries]
        return jac

    def _run(self, state, paths: bool, forces: bool):
        """``(lengths, ten_J, force)`` of every frame (``_fill``), on the body's threads."""
        from concurrent.futures import ThreadPoolExecutor

        from ..sim.model import _thread_count

        m, batch = self.m, len(state[0])
        out = (np.empty((batch, m.ntendon)), np.empty((batch, len(self.datas[0].ten_J))), np.empty((batch, m.nv)),
               np.zeros((batch, m.nv)))
        threads = _thread_count(len(self.datas), batch)
        chunks = np.array_split(np.arange(batch), threads) if threads > 1 else [range(batch)]
        if threads == 1:
            self._fill(state, chunks[0], self.datas[0], out, paths, forces)
        else:  # MuJoCo releases the GIL inside its calls
            with ThreadPoolExecutor(threads) as pool:
                list(pool.map(self._fill, [state] * threads, chunks, self.datas[:threads], [out] * threads,
                              [paths] * threads, [forces] * threads))
        lengths, ten_j, force, passive = out
        if forces and self.lean:
            force = assemble(m, force, state[2], passive)
        return lengths, ten_j, force

    def _muscle_index(self):
        """``(rows, cols, entries)``: the muscles' entries of MuJoCo's sparse ``ten_J`` in this copy's model, their
        muscle (row) and dof (column)."""
        m = self.m
        tendons = np.repeat(np.arange(m.ntendon), m.ten_J_rownnz)
        entries = np.concatenate([np.arange(a, a + n) for a, n in zip(m.ten_J_rowadr, m.ten_J_rownnz)]
                                 + [np.zeros(0, int)])
        order = {int(t): k for k, t in enumerate(self.tendon_ids)}
        keep = np.array([int(t) in order for t in tendons], dtype=bool)
        return (np.array([order[int(t)] for t in tendons[keep]], dtype=int), m.ten_J_colind[entries[keep]],
                entries[keep])

    def _fill(self, state, rows, d, out, paths: bool, forces: bool) -> None:
        """MuJoCo on the frames ``rows`` (``statics.mujoco_inverse``): ``paths``: tendon lengths and ``ten_J``;
        ``forces``: the inverse dynamics' forces (lean: the RNE and the passive forces)."""
        full, qvel_full, qacc_full = state
        (lengths, ten_j, force, passive), m = out, self.m
        # d's arrays bound once: each read of an MjData attribute makes a new numpy view (~0.3 us, ~10 per frame)
        qpos, qvel, qacc, ten_length, ten_J, qfrc_passive = d.qpos, d.qvel, d.qacc, d.ten_length, d.ten_J, \
            d.qfrc_passive
        for b in rows:  # MuJoCo evaluates one state per call
            qpos[:] = full[b]
            if not forces:
                mujoco.mj_kinematics(m, d)
                mujoco.mj_comPos(m, d)
                mujoco.mj_tendon(m, d)
            elif self.lean:
                qvel[:], qacc[:] = qvel_full[b], qacc_full[b]
                lean_inverse(m, d, force[b])
                passive[b] = qfrc_passive
            else:
                qvel[:], qacc[:] = qvel_full[b], qacc_full[b]
                mujoco.mj_inverse(m, d)
                force[b] = d.qfrc_inverse
            if paths:
                lengths[b], ten_j[b] = ten_length, ten_J  # the muscles' entries gathered for all frames at once


@dataclass(frozen=True)
class _ArmPlan:
    """How the muscles' entries of ``ten_J`` make ``G = J E`` (B, M, N) without the dense (B, M, nv) J: E has at most
    one entry per joint (a free joint's 1; a follower's slope, in the column of the free joint it follows: a followed
    joint is free or locked, ``sim.joints``; none for a locked joint), so each entry e of J adds ``J_e E_j`` to one
    entry of G. ``entries`` (E,): positions in ``ten_J``; ``joints`` (E,): their rows of E; ``column`` (nq,): E's
    column of each row (0 where it has none: its entries are left out); ``starts``: where each entry of G
    (``targets``, flat in (M, N)) begins among the entries sorted by target; ``shape``: (M, N)."""

    entries: np.ndarray
    joints: np.ndarray
    column: np.ndarray
    starts: np.ndarray
    targets: np.ndarray
    shape: tuple

    @classmethod
    def of(cls, index, n_muscles: int, layout: FrameLayout, joint_map) -> "_ArmPlan":
        rows, dofs, entries = index
        column = np.full(len(joint_map.qpos0), -1)
        column[joint_map.free] = np.arange(len(joint_map.free))
        for joint, followed, _ in joint_map.deps:
            column[joint] = column[followed]  # -1 where it follows a locked joint
        joint_of_dof = np.full(layout.m.nv, -1)
        joint_of_dof[layout.rest_dof] = np.arange(len(layout.rest_dof))
        joints = joint_of_dof[dofs]
        live = joints >= 0
        live[live] = column[joints[live]] >= 0
        n = len(joint_map.free)
        target = rows[live] * n + column[joints[live]]
        order = np.argsort(target, kind="stable")
        target = target[order]
        starts = np.flatnonzero(np.r_[True, target[1:] != target[:-1]]) if len(target) else np.zeros(0, int)
        return cls(entries[live][order], joints[live][order], np.maximum(column, 0), starts, target[starts],
                   (n_muscles, n))

    def moment_arms(self, ten_j: np.ndarray, tangent: np.ndarray) -> np.ndarray:
        """``G`` (B, M, N) from every frame's ``ten_J`` (B, nnz) and ``E`` (B, nq, N)."""
        batch = len(ten_j)
        slope = tangent[:, np.arange(len(self.column)), self.column]  # (B, nq): each joint's entry of E
        G = np.zeros((batch, self.shape[0] * self.shape[1]))
        if len(self.targets):
            G[:, self.targets] = np.add.reduceat(ten_j[:, self.entries] * slope[:, self.joints], self.starts, axis=1)
        return G.reshape(batch, *self.shape)


def _inverse_body(body: StaticBody, floating: bool = False) -> InverseBody:
    """The body's ``InverseBody`` (welded or with its floating root), each made once."""
    cache = body.__dict__.setdefault("_inverse_bodies", {})
    if floating not in cache:
        cache[floating] = InverseBody(body, floating)
    return cache[floating]


def _frames(body: StaticBody, q, qvel, qacc):
    """The three (B, N) arrays checked: postures within range, finite velocities and accelerations of that shape."""
    q = body.model.check_q(q, within_range=True)
    out = [q]
    for name, x in (("qvel", qvel), ("qacc", qacc)):
        x = np.zeros_like(q) if x is None else np.atleast_2d(np.asarray(x, dtype=np.float64))
        if x.shape != q.shape:
            raise BodySchemaInputError(f"{name} has shape {x.shape}; expected {q.shape}, one row per posture of q "
                                       f"(free joints {body.model.joint_names})")
        if not np.isfinite(x).all():
            raise BodySchemaInputError(f"{name} contains NaN or inf (row {int(np.argwhere(~np.isfinite(x))[0, 0])})")
        out.append(x)
    return out


def _residual(body: StaticBody, residual_dofs, weight: float):
    """``(names, (directions (R, N), unit (R,)) or None)`` of the residual actuators on the free joints named."""
    names = list(residual_dofs or [])
    free = body.model.joint_names
    unknown = [n for n in names if n not in free]
    if unknown:
        raise BodySchemaInputError(f"residual_dofs {unknown} are not free joints of the body; allowed: {free}")
    if not np.isfinite(weight) or weight <= 0:
        raise BodySchemaInputError(f"residual_weight={weight!r}; give a positive number (objective weight per N m^2)")
    if not names:
        return names, None
    directions = np.eye(len(free))[[free.index(n) for n in names]]
    return names, (directions, np.full(len(names), 1.0 / np.sqrt(weight)))


def _times(t, batch: int, timestep_s: float) -> np.ndarray:
    """(B,) frame times [s]: ``t`` checked (finite, strictly increasing), or frames one model timestep apart."""
    if t is None:
        return timestep_s * np.arange(batch)
    t = np.asarray(t, dtype=np.float64).reshape(-1)
    if t.shape != (batch,) or not np.isfinite(t).all() or (np.diff(t) <= 0).any():
        raise BodySchemaInputError(f"t has shape {t.shape}; give ({batch},) finite times [s], strictly increasing")
    return t


def _device(device):
    """``device`` as a torch device (None stays None: the CPU, nothing initialized); refused when absent here."""
    if device is None:
        return None
    import torch

    try:
        device = torch.device(device)
    except (RuntimeError, TypeError):
        raise BodySchemaInputError(f"device={device!r}; give a torch device such as 'cpu' or 'cuda'") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise BodySchemaInputError(f"device={str(device)!r}, but torch sees no CUDA device here; use 'cpu'")
    return device


def frame_controls(body: StaticBody, activation, t) -> tuple[np.ndarray, np.ndarray]:
    """The excitations from each frame's activations to the next's (``statics.activation``), the last frame held."""
    target = np.vstack([activation[1:], activation[-1:]])
    dt = np.append(np.diff(t), np.diff(t)[-1] if len(t) > 1 else body.model.mj_model.opt.timestep)
    control, clipped = excitation(activation, target, body.curves.dynprm, dt, body.model.mj_model.opt.timestep)
    missing = np.isnan(activation) | np.isnan(target)
    return np.where(missing, np.nan, control), clipped & ~missing


def solve_motion(body: StaticBody, q, qvel, qacc, faults=None, tau_nm=None, residual_dofs=None,
                 residual_weight: float = DEFAULT_RESIDUAL_WEIGHT, objective=None, f_ref=None, solver="newton",
                 t=None, device=None, root=None) -> MotionResult:
    """``inverse_dynamics`` on a built body; ``tau_nm`` (B, N) given: the actuators' generalized force instead of
    the motion's (``muscles_for_torque``); ``root``: a floating root's ``(qpos, qvel, qacc)`` (``statics.root``)."""
    objective = body._objective(objective)
    q, qvel, qacc = _frames(body, q, qvel, qacc)
    faults = body.fault_batch(faults, len(q))
    check_solver(solver)
    inverse = _inverse_body(body, floating=root is not None)
    roots = {dof[:-3] for dof in inverse.layout.root_dofs}  # a floating root always has its residual actuators
    names, residual = _residual(body, [n for n in residual_dofs or () if n not in roots], residual_weight)
    t = _times(t, len(q), body.model.mj_model.opt.timestep)
    device = _device(device)
    root = inverse.layout.check_root(*(root or (None, None, None)), len(q))
    l_geo, G, tau, G_root, tau_root = inverse.inverse(q, qvel, qacc, root)
    if tau_nm is not None:
        tau = tau_nm
    factor = None if body.curves is None else body.curves.velocity_factor(np.einsum("bmn,bn->bm", G, qvel))
    result, residual_nm = body.solve_torque(q, l_geo, G, tau, faults, objective, f_ref, solver, factor, residual,
                                            device, motion=tau_nm is None)  # a motion's frames: warm-started QPs
    control, clipped = (None, None) if result.activation is None else frame_controls(body, result.activation, t)
    fields = {k: getattr(result, k) for k in StaticResult.__dataclass_fields__}
    return MotionResult(**fields, qvel=qvel, qacc=qacc, tau_nm=tau, control=control, control_clipped=clipped,
                        residual_nm=residual_nm, residual_dofs=names, t=t, **_root_fields(inverse, root, G_root,
                                                                                          tau_root, result))


def _root_fields(inverse: InverseBody, root, G_root, tau_root, result: StaticResult) -> dict:
    """A floating root's ``MotionResult`` fields: its motion and the residual actuators carrying it,
    ``tau_root + G_root^T f`` (the muscles' share, ``-G_root^T f``, is zero but for rounding: none spans the root)."""
    if root is None:
        return {}
    span = 0.0 if G_root is None else np.abs(G_root).max(initial=0.0)
    if span > UNCROSSED_ARM_M:  # a muscle anchored outside the floating tree: the root would need the QP
        raise BodySchemaInputError(f"a muscle spans the floating root (moment arm {span:.3g} m); muscles anchored to "
                                   "the world are not supported on a floating root: weld it (no root_qpos)")
    residual = tau_root if G_root is None else tau_root + np.einsum("bmr,bm->br", G_root, result.tension_n)
    return dict(root_qpos=root[0], root_qvel=root[1], root_qacc=root[2], root_residual=residual,
                root_dofs=list(inverse.layout.root_dofs))


def _body(model, body_options) -> StaticBody:
    body = model if isinstance(model, StaticBody) else StaticBody(model, **body_options)
    if isinstance(model, StaticBody) and body_options:
        raise BodySchemaInputError(f"options {sorted(body_options)} build a body; this StaticBody is already built")
    return body


def inverse_dynamics(model, q, qvel, qacc, faults=None, residual_dofs: Optional[Sequence[str]] = None,
                     residual_weight: float = DEFAULT_RESIDUAL_WEIGHT, objective: Optional[str] = None, f_ref=None,
                     solver: str = "newton", t=None, device=None, root_qpos=None, root_qvel=None, root_qacc=None,
                     **body_options) -> MotionResult:
    """Muscle activations, tensions and MuJoCo excitations that make the body move through frames ``q``, ``qvel``,
    ``qacc`` (B, N) [rad, rad/s, rad/s^2] of its free joints, with faults (module docstring).

    ``model``, ``faults``, ``objective``, ``f_ref``, ``solver``: as ``static_optimization``'s. ``residual_dofs``:
    free joints given a residual actuator, weighted ``residual_weight`` per N m^2. ``t`` (B,) [s]: frame times (the
    control's frame step; default: one model timestep apart). ``device``: the QP's torch device (e.g. ``"cuda"``;
    MuJoCo's part stays on the CPU). ``root_qpos`` (B, 7K), ``root_qvel``, ``root_qacc`` (B, 6K; default 0): the
    motion of a floating root in MuJoCo's convention (``statics.root``: position and unit quaternion; linear velocity
    in the world, angular in the root's frame), on a body whose source has free joints, built with
    ``fixed_base=True`` (the default when ``model`` is a source and ``root_qpos`` is given); MuJoCo's inverse
    dynamics then runs on the whole state and the root's 6 generalized forces per free joint are carried by residual
    actuators (``root_residual``; naming the root in ``residual_dofs`` changes nothing: no muscle spans it, so its
    residuals are those forces whatever their weight), the muscles on the rest. Returns a ``MotionResult``; with ``qvel = qacc = 0`` it is
    ``static_optimization``'s answer.

        >>> body = StaticBody("myo:myoelbow_2dof")
        >>> motion = inverse_dynamics(body, q, qvel, qacc, faults={"cut": ["BIClong_tendon"]}, t=t)
        >>> motion.activation, motion.control, motion.status
    """
    if root_qpos is not None and not isinstance(model, StaticBody):
        body_options.setdefault("fixed_base", True)  # statics welds the root; the dynamics puts it back
    body = _body(model, body_options)
    root = None if root_qpos is None and root_qvel is None and root_qacc is None else (root_qpos, root_qvel, root_qacc)
    return solve_motion(body, q, qvel, qacc, faults, None, residual_dofs, residual_weight, objective, f_ref, solver,
                        t, device, root)


def muscles_for_torque(model, q, tau_nm, qvel=None, faults=None, residual_dofs: Optional[Sequence[str]] = None,
                       residual_weight: float = DEFAULT_RESIDUAL_WEIGHT, objective: Optional[str] = None,
                       f_ref=None, solver: str = "newton", device=None, **body_options) -> MotionResult:
    """The muscle activations and tensions whose MuJoCo actuator force is the generalized force ``tau_nm`` (B, N)
    [N m] on the free joints (``E^T qfrc_actuator``: e.g. what ``mj_inverse`` says a motion needs, gravity included)
    at postures ``q`` (B, N), tendon velocities from ``qvel`` (default 0: MuJoCo's force-velocity factor 1). Options
    as ``inverse_dynamics``'; ``control`` holds each frame's activation (no frame step is known)."""
    body = _body(model, body_options)
    q = body.model.check_q(q, within_range=True)
    tau_nm = np.atleast_2d(np.asarray(tau_nm, dtype=np.float64))
    if tau_nm.shape != q.shape or not np.isfinite(tau_nm).all():
        raise BodySchemaInputError(f"tau_nm has shape {tau_nm.shape}; expected finite {q.shape} [N m], one row per "
                                   f"posture (free joints {body.model.joint_names})")
    result = solve_motion(body, q, qvel, None, faults, tau_nm, residual_dofs, residual_weight, objective, f_ref,
                          solver, None, device)
    return replace(result, control=result.activation, control_clipped=None, t=None)
