"""A floating root for inverse dynamics: the body's free joints (e.g. MyoSuite legs' pelvis) put back for the dynamics.

A ``StaticBody`` welds a free joint (``fixed_base``): statics holds postures of the joints the muscles span, and no
muscle can hold a floating body up. A motion of such a body moves its root too, and the root's acceleration loads
every joint. ``FrameLayout.of(body, floating=True)`` is the stored (welded) body with each free joint of its source
put back on the body that had it, compiled from the same full-precision XML: every other quantity is bit for bit the
welded body's. MuJoCo's state is then ``[root, rest]`` in MuJoCo's order; the joint map of the welded body gives the
rest from the free joints as before.

The root's motion per free joint, in MuJoCo's convention: ``qpos`` (B, 7) position [m] and unit quaternion
``(w, x, y, z)`` of the root body in the world; ``qvel`` (B, 6) its linear velocity in the world frame [m/s] and
angular velocity in its own frame [rad/s]; ``qacc`` (B, 6) their time derivatives. Several free joints: concatenated
in the model's order. No muscle spans a root (a muscle's length does not change when the whole body moves rigidly),
so its 6 generalized forces are carried by residual actuators, reported per frame (``root_dofs`` names them:
``<joint>_tx, _ty, _tz`` [N] along the world axes, ``_rx, _ry, _rz`` [N m] about the root body's own axes).
numpy and MuJoCo; never imports Lightning.
"""
from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from ..errors import BodySchemaInputError
from ..sim.mjcf import compile_spec, load_spec

ROOT_DOFS = ("tx", "ty", "tz", "rx", "ry", "rz")
QUAT_NORM_TOL = 1e-6  # a root quaternion this far from unit length is refused (not silently normalized)


def free_roots(source: str) -> list[tuple[str, str]]:
    """``(joint, body)`` of each free joint of the model ``source`` (any ``MusculoskeletalModel`` source)."""
    spec = load_spec(source)
    return [(j.name, j.parent.name) for j in spec.joints if j.type == mujoco.mjtJoint.mjJNT_FREE]


def floating_spec(body) -> mujoco.MjSpec:
    """The stored body's spec with its source's free joints put back (module docstring); refused without any."""
    roots = free_roots(body.source) if body.fixed_base else []
    if not roots:
        raise BodySchemaInputError("a root motion (root_qpos) was given, but this body has no floating root: build "
                                   "it from a model with a <freejoint> (e.g. myo:myolegs) and fixed_base=True")
    spec = mujoco.MjSpec.from_string(body.model.xml)
    for joint, name in roots:
        spec.body(name).add_freejoint(name=joint)
    return spec


def muscles_span_root(m: mujoco.MjModel, tendons) -> bool:
    """True where a tendon of ``tendons`` (ids of the welded model ``m``, whose bodies the floating one shares)
    touches bodies of two trees, or the world: then its path moves with a root and it spans the root's dofs."""
    owners = {int(mujoco.mjtWrap.mjWRAP_SITE): m.site_bodyid, int(mujoco.mjtWrap.mjWRAP_SPHERE): m.geom_bodyid,
              int(mujoco.mjtWrap.mjWRAP_CYLINDER): m.geom_bodyid}
    for tendon in tendons:
        start = m.tendon_adr[tendon]
        bodies = [owners[int(kind)][obj] for kind, obj in zip(m.wrap_type[start:start + m.tendon_num[tendon]],
                                                             m.wrap_objid[start:start + m.tendon_num[tendon]])
                  if int(kind) in owners]
        trees = {int(m.body_rootid[b]) for b in bodies}
        if 0 in trees or len(trees) > 1:
            return True
    return False


@dataclass
class FrameLayout:
    """Where the welded body's joints and the roots sit in a MuJoCo model's state: ``m`` the model; ``rest_qpos``
    (nq_w,), ``rest_dof`` (nv_w,) the welded body's joints; ``root_qpos`` (7K,), ``root_dof`` (6K,) the roots';
    ``root_dofs`` their names (K = 0: the welded body itself)."""

    m: mujoco.MjModel
    rest_qpos: np.ndarray
    rest_dof: np.ndarray
    root_qpos: np.ndarray
    root_dof: np.ndarray
    root_dofs: list

    @classmethod
    def of(cls, body, floating: bool, m: mujoco.MjModel | None = None) -> "FrameLayout":
        """The welded body's own layout, or (``floating``) the body with its roots back; ``m``: that model already
        compiled (e.g. with actuators added)."""
        welded = body.model.mj_model
        if not floating:
            m = welded if m is None else m
            return cls(m, np.arange(welded.nq), np.arange(welded.nv), np.zeros(0, int), np.zeros(0, int), [])
        m = compile_spec(floating_spec(body)) if m is None else m
        names = body.model.all_joint_names
        ids = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, n) for n in names]
        free = [j for j in range(m.njnt) if int(m.jnt_type[j]) == int(mujoco.mjtJoint.mjJNT_FREE)]
        span = lambda adr, n: np.concatenate([np.arange(a, a + n) for a in adr])  # noqa: E731
        joint_names = [mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_JOINT, j) for j in free]
        return cls(m, m.jnt_qposadr[ids], m.jnt_dofadr[ids], span(m.jnt_qposadr[free], 7), span(m.jnt_dofadr[free], 6),
                   [f"{j}_{d}" for j in joint_names for d in ROOT_DOFS])

    @property
    def floating(self) -> bool:
        return len(self.root_dof) > 0

    def state(self, full, qvel_full, qacc_full, root) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """MuJoCo's ``(qpos, qvel, qacc)`` (B, nq), (B, nv) from the welded body's and the roots' ``(qpos, qvel,
        qacc)`` (None without roots)."""
        if not self.floating:
            return full, qvel_full, qacc_full
        out = []
        for rest, root_part, rest_idx, root_idx, width in ((full, root[0], self.rest_qpos, self.root_qpos, self.m.nq),
                                                           (qvel_full, root[1], self.rest_dof, self.root_dof, self.m.nv),
                                                           (qacc_full, root[2], self.rest_dof, self.root_dof, self.m.nv)):
            x = np.empty((len(rest), width))
            x[:, rest_idx], x[:, root_idx] = rest, root_part
            out.append(x)
        return tuple(out)

    def check_root(self, root_qpos, root_qvel, root_qacc, batch: int):
        """The roots' ``(qpos (B, 7K), qvel (B, 6K), qacc (B, 6K))`` checked (finite, unit quaternions; qvel and
        qacc default 0), or None where the layout has no root and none is given."""
        if root_qpos is None:
            if root_qvel is not None or root_qacc is not None:
                raise BodySchemaInputError("root_qvel/root_qacc given without root_qpos; give the root's positions")
            if self.floating:
                raise BodySchemaInputError(f"this body's root floats ({self.root_dofs[0][:-3]}); give root_qpos")
            return None
        if not self.floating:
            raise BodySchemaInputError("root_qpos was given, but this body has no floating root")
        k = len(self.root_dof) // 6
        arrays = []
        for name, x, width in (("root_qpos", root_qpos, 7 * k), ("root_qvel", root_qvel, 6 * k),
                               ("root_qacc", root_qacc, 6 * k)):
            x = np.zeros((batch, width)) if x is None else np.atleast_2d(np.asarray(x, dtype=np.float64))
            if x.shape != (batch, width) or not np.isfinite(x).all():
                raise BodySchemaInputError(f"{name} has shape {x.shape}; expected finite ({batch}, {width}): per "
                                           f"frame {width // k} numbers per free joint ({k}), MuJoCo's convention")
            arrays.append(x)
        norms = np.linalg.norm(arrays[0].reshape(batch, k, 7)[:, :, 3:], axis=2)
        if np.abs(norms - 1.0).max() > QUAT_NORM_TOL:
            b = int(np.argmax(np.abs(norms - 1.0).max(1)))
            raise BodySchemaInputError(f"root_qpos[{b}]'s quaternion has norm {norms[b].min():.9g}; give unit "
                                       f"quaternions (w, x, y, z), within {QUAT_NORM_TOL:g}")
        return tuple(arrays)


def _quat_mul(a, b):
    """Hamilton products of quaternions (..., 4) ``(w, x, y, z)``."""
    aw, av, bw, bv = a[..., :1], a[..., 1:], b[..., :1], b[..., 1:]
    return np.concatenate([aw * bw - (av * bv).sum(-1, keepdims=True), aw * bv + bw * av + np.cross(av, bv)], -1)


def root_derivatives(t, root_qpos, differentiate) -> tuple[np.ndarray, np.ndarray]:
    """``(qvel, qacc)`` (B, 6K) of root positions (B, 7K) by ``differentiate(t, x) -> (xdot, xddot)``: the
    position's derivatives, and the angular velocity and acceleration in the root's frame, ``2 conj(q) qdot`` and
    ``2 conj(q) qddot`` (vector parts; ``conj(qdot) qdot`` is real), the quaternions first made continuous in sign."""
    batch = len(root_qpos)
    x = np.asarray(root_qpos, float).reshape(batch, -1, 7).copy()
    quat = x[:, :, 3:]
    flips = np.cumsum(np.r_[np.zeros((1, quat.shape[1])), (quat[1:] * quat[:-1]).sum(-1) < 0], axis=0) % 2
    quat *= np.where(flips == 1, -1.0, 1.0)[..., None]  # q and -q are one rotation; the derivative needs one path
    vel, acc = (d.reshape(x.shape) for d in differentiate(t, x.reshape(batch, -1)))
    conj = quat * np.array([1.0, -1.0, -1.0, -1.0])
    out = []
    for d in (vel, acc):
        omega = 2.0 * _quat_mul(conj, d[:, :, 3:])[..., 1:]
        out.append(np.concatenate([d[:, :, :3], omega], -1).reshape(batch, -1))
    return out[0], out[1]
