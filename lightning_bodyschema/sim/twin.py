"""``TorchKinematicTwin``: a differentiable, batched torch copy of a model's kinematic tree.

MuJoCo stays the source of truth (``MusculoskeletalModel``); this twin, built with
pytorch-kinematics, gives site positions ``(B, 3)`` [m] with autograd Jacobians for inverse
kinematics and gradient-based planning. ``tests/sim/test_twin.py`` checks it against MuJoCo.

pytorch-kinematics 0.10 needs four work-arounds, all handled here:

* ``build_chain_from_mjcf`` looks joint types up in a dict keyed by ``mujoco.mjtJoint`` enums; with
  MuJoCo 4 the types arrive as ``np.int32`` and the lookup raises ``KeyError``. We re-key the dict by int.
* It re-compiles the XML text, so meshes or textures named by relative path cannot load, and it
  supports one joint per body. We therefore hand it a kinematic skeleton (bodies, joints, sites and
  one small sphere per body) rebuilt from the compiled model, with multi-joint bodies split.
* It rotates a hinge about the body origin and ignores the joint's ``pos``. The skeleton moves each
  body origin onto its joint anchor (children shifted back), which is the same rigid motion.
* It builds every offset in float32, and ``MjSpec.to_xml`` rounds numbers to 6 significant digits.
  We overwrite all offsets and axes with the float64 numbers of the compiled MuJoCo model.

Frame names in the chain are ``body:<name>`` and ``site:<name>`` (sites and bodies may share a name
in MuJoCo but share one namespace in pytorch-kinematics); joints keep their MuJoCo names.
Never imports Lightning.
"""
from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np
import pytorch_kinematics as pk
import torch

from ..errors import BodySchemaInputError
from .model import MusculoskeletalModel

_HINGE = int(mujoco.mjtJoint.mjJNT_HINGE)
_OBJ_BODY, _OBJ_SITE = mujoco.mjtObj.mjOBJ_BODY, mujoco.mjtObj.mjOBJ_SITE
_IDENTITY_QUAT = np.array([1.0, 0.0, 0.0, 0.0])


def _rekey_pk_joint_types():
    """Make pytorch-kinematics' MJCF joint-type table accept MuJoCo 4's np.int32 joint types."""
    table = pk.mjcf.JOINT_TYPE_MAP
    as_int = {int(k): v for k, v in table.items()}
    table.clear()
    table.update(as_int)  # int keys still match the enums (equal value and hash)


def _name(m: mujoco.MjModel, kind, i: int) -> str:
    return mujoco.mj_id2name(m, kind, i) or f"#{i}"


def _joint_chain(m: mujoco.MjModel, b: int) -> list[tuple[int, np.ndarray]]:
    """(joint id, anchor in body frame) for body b's joints; a slide joint keeps the previous anchor."""
    anchor, out = np.zeros(3), []
    for j in range(m.body_jntadr[b], m.body_jntadr[b] + m.body_jntnum[b]):
        anchor = m.jnt_pos[j].copy() if int(m.jnt_type[j]) == _HINGE else anchor
        out.append((j, anchor))
    return out


def _rotate(quat: np.ndarray, v: np.ndarray) -> np.ndarray:
    out = np.zeros(3)
    mujoco.mju_rotVecQuat(out, v, quat)
    return out


class _Skeleton:
    """Kinematic-only copy of a compiled model; records each chain frame's float64 pose and axis."""

    def __init__(self, m: mujoco.MjModel):
        self.m, self.spec = m, mujoco.MjSpec()
        self.spec.compiler.degree = False
        self.poses: dict[str, tuple[np.ndarray, np.ndarray]] = {}  # frame -> (pos, quat) in parent frame
        self.axes: dict[str, np.ndarray] = {}  # joint name -> unit axis
        self.anchor = {0: np.zeros(3)}  # body id -> its chain frame origin, in body coordinates
        self.spec_body = {0: self.spec.worldbody}  # body id -> skeleton body holding its sites and children
        self._add_sites(0, self.spec.worldbody)
        for b in range(1, m.nbody):  # parents always precede children in MuJoCo's body order
            self._add_body(b)

    def _add_body(self, b: int):
        """One skeleton body per joint (pytorch-kinematics takes one per body), its origin on the joint anchor."""
        m, parent = self.m, int(self.m.body_parentid[b])
        spec_body, prev = self.spec_body[parent], np.zeros(3)
        pos, quat = m.body_pos[b] - self.anchor[parent], m.body_quat[b].copy()
        joints = _joint_chain(m, b) or [(None, np.zeros(3))]
        for k, (j, anchor) in enumerate(joints):
            name = f"body:{_name(m, _OBJ_BODY, b)}" + ("" if k == len(joints) - 1 else f"/{k}")
            if k == 0:  # placed in the parent's frame
                spec_body = self._add_frame(spec_body, name, pos + _rotate(quat, anchor), quat, j)
            else:  # stacked in this body's own (unrotated) frame
                spec_body = self._add_frame(spec_body, name, anchor - prev, _IDENTITY_QUAT, j)
            prev = anchor
        self.anchor[b], self.spec_body[b] = prev, spec_body
        self._add_sites(b, spec_body)

    def _add_frame(self, parent, name, pos, quat, j):
        body = parent.add_body(name=name, pos=pos, quat=quat)
        body.add_geom(type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[0.01, 0, 0])  # gives the body mass
        self.poses[name] = (pos, quat)
        if j is not None:
            jname = _name(self.m, mujoco.mjtObj.mjOBJ_JOINT, j)
            body.add_joint(name=jname, type=mujoco.mjtJoint(int(self.m.jnt_type[j])),
                           axis=self.m.jnt_axis[j], range=self.m.jnt_range[j])
            self.axes[jname] = self.m.jnt_axis[j] / np.linalg.norm(self.m.jnt_axis[j])
        return body

    def _add_sites(self, b: int, spec_body):
        for s in np.flatnonzero(self.m.site_bodyid == b):
            name = f"site:{_name(self.m, _OBJ_SITE, int(s))}"
            pos = self.m.site_pos[s] - self.anchor[b]
            spec_body.add_site(name=name, pos=pos, quat=self.m.site_quat[s])
            self.poses[name] = (pos, self.m.site_quat[s].copy())


def _set_exact_offsets(frame: pk.Frame, skeleton: _Skeleton, dtype):
    """Replace pytorch-kinematics' float32 offsets and axes with the compiled model's numbers."""
    if frame.name in skeleton.poses:
        pos, quat = skeleton.poses[frame.name]
        frame.link.offset = pk.Transform3d(rot=torch.tensor(quat, dtype=dtype),
                                           pos=torch.tensor(pos, dtype=dtype), dtype=dtype)
    elif frame.link.offset is not None:  # the world frame: identity, exact in any dtype
        frame.link.offset = frame.link.offset.to("cpu", dtype=dtype)
    if frame.joint.joint_type != "fixed":
        frame.joint.axis = torch.tensor(skeleton.axes[frame.joint.name], dtype=dtype)
    frame.joint.offset = None  # the skeleton puts every joint at its frame origin
    for child in frame.children:
        _set_exact_offsets(child, skeleton, dtype)


def build_twin_chain(model: MusculoskeletalModel, dtype=torch.float64) -> pk.Chain:
    """A pytorch-kinematics chain equal to the model's kinematic tree, in ``dtype``."""
    _rekey_pk_joint_types()
    skeleton = _Skeleton(model.mj_model)
    try:
        skeleton.spec.compile()
        chain = pk.build_chain_from_mjcf(skeleton.spec.to_xml())
    except Exception as err:
        raise BodySchemaInputError(f"pytorch-kinematics cannot build the model's kinematic tree: {err}") from None
    root = chain.find_frame("world")
    _set_exact_offsets(root, skeleton, dtype)
    return pk.Chain(root, dtype=dtype)


@dataclass(frozen=True)
class IKResult:
    """Inverse-kinematics outcome per target: joint values in MuJoCo qpos order and final site error."""

    q: torch.Tensor  # (B, N) [rad or m], inside the joint limits
    reached: torch.Tensor  # (B,) bool, error_m <= tol_m
    error_m: torch.Tensor  # (B,) distance between site and target [m]
    iterations: int  # LM iterations run


class TorchKinematicTwin:
    """Batched, differentiable forward and inverse kinematics of a ``MusculoskeletalModel``.

    Args:
        model: the MuJoCo model; joint order, ranges and reference angles come from it.
        dtype: torch dtype of every computation (float64 matches MuJoCo's site positions to rounding).
    """

    def __init__(self, model: MusculoskeletalModel, dtype: torch.dtype = torch.float64):
        if not model.joint_map.identity:
            raise BodySchemaInputError(
                f"the kinematic twin (inverse kinematics, adapt_to_target) does not support coupled or locked joints "
                f"yet; model {model!r} has locked {sorted(model.locked_joints)} and "
                f"{len(model.joint_map.deps)} coupled joints: give q_ref to adapt() instead")
        self.model, self.dtype = model, dtype
        self.chain = build_twin_chain(model, dtype)
        names = model.joint_names
        self._perm = torch.tensor([names.index(n) for n in self.chain.get_joint_parameter_names()])
        m = model.mj_model
        self._qpos0 = torch.tensor(m.qpos0[m.jnt_qposadr[: model.n_joints]], dtype=dtype)
        self.q_lo_hi = torch.tensor(model.q_range, dtype=dtype)  # (N, 2)
        self._site_frames = {f[len("site:"):]: f for f in self.chain.get_frame_names(exclude_fixed=False)
                             if f.startswith("site:")}

    @property
    def site_names(self) -> list[str]:
        return sorted(self._site_frames)

    def _frame_index(self, site: str) -> int:
        if site not in self._site_frames:
            raise BodySchemaInputError(f"unknown site {site!r}; the model's sites are {self.site_names}")
        return int(self.chain.frame_to_idx[self._site_frames[site]])

    def check_q(self, q) -> torch.Tensor:
        """q as a (B, N) tensor of the twin's dtype; keeps the autograd graph of a tensor input."""
        q = torch.atleast_2d(_as_tensor(q, self.dtype))
        if q.ndim != 2 or q.shape[1] != self.model.n_joints:
            raise BodySchemaInputError(f"q has shape {tuple(q.shape)}; expected (B, {self.model.n_joints})")
        if not torch.isfinite(q).all():
            raise BodySchemaInputError("q contains NaN or inf")
        return q

    def site_position(self, q, site: str = "hand") -> torch.Tensor:
        """World position (B, 3) [m] of a named site at postures ``q (B, N)``; differentiable in q."""
        idx = self._frame_index(site)
        q = self.check_q(q)
        transforms = self.chain.forward_kinematics_tensor((q - self._qpos0)[:, self._perm])
        return transforms[idx, :, :3, 3]

    def site_jacobian(self, q, site: str = "hand") -> tuple[torch.Tensor, torch.Tensor]:
        """Site position (B, 3) [m] and its Jacobian d pos / d q (B, 3, N) [m/rad], detached."""
        q = self.check_q(q).detach().requires_grad_(True)
        with torch.enable_grad():
            pos = self.site_position(q, site)
            rows = [torch.autograd.grad(pos[:, k].sum(), q, retain_graph=k < 2)[0] for k in range(3)]
        return pos.detach(), torch.stack(rows, dim=1)

    def inverse_kinematics(self, target_xyz, q0=None, site: str = "hand", max_iter: int = 100,
                           tol_m: float = 1e-4, n_restarts: int = 8, seed: int = 0) -> IKResult:
        """Joint values that put ``site`` on each target ``(B, 3)`` [m], within the joint limits.

        Levenberg-Marquardt (damped least squares) on all targets and starts at once, each iterate
        clamped to the joint range and accepted only if it lowers that start's error. Starts are
        ``q0`` (if given, clamped) plus ``n_restarts`` uniform random postures (seeded); the best start
        per target is returned. Random starts matter: a straight arm is a singular posture from which
        the elbow never bends.
        """
        target = self._check_target(target_xyz)
        self._frame_index(site)
        _check_ik_options(max_iter, tol_m, n_restarts, q0 is None)
        starts = self._ik_starts(target.shape[0], q0, n_restarts, seed)  # (S, B, N)
        n_starts, batch = starts.shape[:2]
        q, err, iters = self._lm(starts.reshape(-1, starts.shape[-1]), target.repeat(n_starts, 1),
                                 site, max_iter, tol_m, n_starts)
        best = err.reshape(n_starts, batch).argmin(dim=0)
        q_best = q.reshape(n_starts, batch, -1)[best, torch.arange(batch)]
        err_best = err.reshape(n_starts, batch)[best, torch.arange(batch)]
        return IKResult(q=q_best, reached=err_best <= tol_m, error_m=err_best, iterations=iters)

    def _check_target(self, target_xyz) -> torch.Tensor:
        target = torch.atleast_2d(_as_tensor(target_xyz, self.dtype).detach())
        if target.ndim != 2 or target.shape[1] != 3:
            raise BodySchemaInputError(f"target_xyz has shape {tuple(target.shape)}; expected (B, 3) in metres")
        if not torch.isfinite(target).all():
            raise BodySchemaInputError("target_xyz contains NaN or inf")
        return target

    def _ik_starts(self, batch: int, q0, n_restarts: int, seed: int) -> torch.Tensor:
        """(S, B, N) initial postures: q0 (clamped into range) then seeded uniform random ones."""
        lo, hi = self.q_lo_hi.T
        starts = [] if q0 is None else [torch.clamp(self._check_q0(q0, batch), lo, hi)]
        gen = torch.Generator().manual_seed(seed)
        rand = torch.rand((n_restarts, batch, len(lo)), generator=gen, dtype=self.dtype)
        return torch.cat([torch.stack(starts), lo + (hi - lo) * rand] if starts else [lo + (hi - lo) * rand])

    def _check_q0(self, q0, batch: int) -> torch.Tensor:
        q0 = self.check_q(q0).detach()
        if q0.shape[0] not in (1, batch):
            raise BodySchemaInputError(f"q0 has {q0.shape[0]} rows for {batch} targets; give 1 or {batch}")
        return q0.expand(batch, -1)

    def _lm(self, q, target, site, max_iter, tol_m, n_starts):
        """Batched projected Levenberg-Marquardt; stops when every target has one start within tol_m."""
        lo, hi = self.q_lo_hi.T
        damping = torch.full((q.shape[0],), 1e-3, dtype=self.dtype)  # [m^2]
        eye = torch.eye(q.shape[1], dtype=self.dtype)
        pos, jac = self.site_jacobian(q, site)
        err = (target - pos).norm(dim=1)
        for it in range(max_iter):
            if (err.reshape(n_starts, -1).min(dim=0).values <= tol_m).all():
                return q, err, it
            residual = (target - pos).unsqueeze(-1)
            jt = jac.transpose(1, 2)
            step = torch.linalg.solve(jt @ jac + damping[:, None, None] * eye, jt @ residual).squeeze(-1)
            q_new = torch.clamp(q + step, lo, hi)
            pos_new, jac_new = self.site_jacobian(q_new, site)
            err_new = (target - pos_new).norm(dim=1)
            better = err_new < err
            q, pos, jac, err = (torch.where(better[:, None], q_new, q), torch.where(better[:, None], pos_new, pos),
                                torch.where(better[:, None, None], jac_new, jac), torch.minimum(err_new, err))
            damping = torch.where(better, damping / 3.0, damping * 4.0).clamp(1e-12, 1e6)
        return q, err, max_iter


def _as_tensor(x, dtype) -> torch.Tensor:
    """A tensor of ``dtype`` from a tensor (graph kept), an array or nested lists."""
    if torch.is_tensor(x):
        return x.to(dtype)
    try:
        return torch.as_tensor(np.asarray(x, dtype=np.float64), dtype=dtype)
    except (TypeError, ValueError) as err:
        raise BodySchemaInputError(f"expected numbers, got {type(x).__name__}: {err}") from None


def _check_ik_options(max_iter, tol_m, n_restarts, no_q0):
    if int(max_iter) < 1:
        raise BodySchemaInputError(f"max_iter={max_iter}; need an integer >= 1")
    if not tol_m > 0:
        raise BodySchemaInputError(f"tol_m={tol_m}; need a positive distance in metres")
    if int(n_restarts) < 0 or (no_q0 and int(n_restarts) < 1):
        raise BodySchemaInputError(f"n_restarts={n_restarts}; need >= 0, and >= 1 when q0 is not given")
