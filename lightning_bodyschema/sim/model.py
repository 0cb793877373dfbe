"""``MusculoskeletalModel``: batched muscle kinematics and gravity torques of any MJCF with tendons.

MuJoCo is the single source of truth. For a batch of postures ``q (B, N)`` it gives
``l_geo (B, M)`` geometric muscle lengths [m], ``G (B, M, N) = d l_geo / d q`` [m/rad] and
``tau_bias (B, N)`` the gravity torque at zero velocity [N m] (MuJoCo ``qfrc_bias``).
Tensions act on the joints as ``-G^T f``; static equilibrium is ``-G^T f = tau_bias``.
"""
from __future__ import annotations

import hashlib
import os
from importlib import resources
from typing import Sequence

import mujoco
import numpy as np

from ..errors import BodySchemaInputError

_SUPPORTED_JOINTS = (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE))
UNLOADED_TAU_NM = 1e-9  # below this gravity torque at every probed posture, gravity does not load the joints


def packaged_model_names() -> list[str]:
    """Names of the MJCF models shipped in ``lightning_bodyschema/assets`` (e.g. ``paper_arm``)."""
    files = resources.files("lightning_bodyschema.assets").iterdir()
    return sorted(f.name[:-4] for f in files if f.name.endswith(".xml"))


def packaged_model_xml(name: str) -> str:
    """The MJCF text of a packaged model: ``paper_arm``, ``arm3_8``, ``opensim_like_arm``, ..."""
    names = packaged_model_names()
    if name not in names:
        raise BodySchemaInputError(f"unknown packaged model {name!r}; packaged models are {names}")
    return resources.files("lightning_bodyschema.assets").joinpath(f"{name}.xml").read_text()


def paper_arm_xml() -> str:
    """The MJCF text of the paper's two-joint, six-muscle arm shipped with the package."""
    return packaged_model_xml("paper_arm")


def _load_spec(source: str) -> mujoco.MjSpec:
    """Parse an MJCF given as a packaged model name, a file path, or XML text."""
    if source in packaged_model_names():
        return mujoco.MjSpec.from_string(packaged_model_xml(source))
    if source.lstrip().startswith("<"):
        try:
            return mujoco.MjSpec.from_string(source)
        except Exception as err:  # MuJoCo raises plain ValueError with its parser message
            raise BodySchemaInputError(f"model XML does not parse: {str(err).strip()}") from None
    if not os.path.isfile(source):
        raise BodySchemaInputError(
            f"model {source!r} does not exist: it is neither a packaged model {packaged_model_names()} "
            "nor an MJCF file (give a packaged name, an MJCF path, or MJCF text)")
    try:
        return mujoco.MjSpec.from_file(source)
    except Exception as err:
        raise BodySchemaInputError(f"model file {source!r} does not parse: {str(err).strip()}") from None


class MusculoskeletalModel:
    """A MuJoCo model whose spatial tendons are the robot's muscles.

    Args:
        source: a packaged model name (``"paper_arm"``, ``"arm3_8"``, ``"opensim_like_arm"``; see
            ``packaged_model_names()``), a path to an MJCF file, or MJCF text.
        muscles: names of the tendons that are muscles; default: every spatial tendon
            (fixed, i.e. joint, tendons are never muscles).
        gravity: optional override of the model's gravity vector [m/s^2].
        allow_unloaded: accept a model whose gravity loads no joint (zero gravity, or gravity along
            every hinge axis). Refused by default: the static equilibrium ``-G^T f = tau_bias`` is
            then ``-G^T f = 0`` everywhere, i.e. pure co-contraction, which is almost always a
            wrong gravity vector or a wrongly oriented model rather than the robot one meant.

    MuJoCo actuators are removed before compiling: the pipeline needs only tendons, and a
    ``<muscle>`` actuator whose length-range computation fails must not stop the model loading.
    Joint count, ranges and muscle names all come from the model.
    """

    def __init__(self, source: str = "paper_arm", muscles: Sequence[str] | None = None,
                 gravity: Sequence[float] | None = None, allow_unloaded: bool = False):
        spec = _load_spec(source)
        for actuator in list(spec.actuators):
            spec.delete(actuator)
        if gravity is not None:
            spec.option.gravity = np.asarray(gravity, dtype=float)
        try:
            self.mj_model = spec.compile()
        except Exception as err:
            raise BodySchemaInputError(f"model does not compile: {str(err).strip()}") from None
        self.xml = spec.to_xml()
        self._check_joints()
        self.muscle_ids = self._select_muscles(muscles)
        self._data = mujoco.MjData(self.mj_model)
        self._dense_index = self._tendon_jacobian_index()
        if not allow_unloaded:
            self._check_gravity_loads()

    # ------------------------------------------------------------------ structure
    def _check_joints(self):
        m = self.mj_model
        if m.njnt == 0 or m.nq != m.nv:
            raise BodySchemaInputError(
                f"model has {m.njnt} joints with nq={m.nq}, nv={m.nv}: need at least one joint, "
                "and only hinge or slide joints are supported")
        bad = [self._name(mujoco.mjtObj.mjOBJ_JOINT, j) for j in range(m.njnt)
               if int(m.jnt_type[j]) not in _SUPPORTED_JOINTS]
        if bad:
            raise BodySchemaInputError(f"joints {bad} are not hinge or slide joints; only those are supported")
        unlimited = [self._name(mujoco.mjtObj.mjOBJ_JOINT, j) for j in range(m.njnt) if not m.jnt_limited[j]]
        if unlimited:
            raise BodySchemaInputError(f"joints {unlimited} have no range; every joint needs range=\"lo hi\"")

    def _check_gravity_loads(self, n_postures: int = 8):
        """Refuse a model whose gravity torque vanishes at a few postures spread over the joint range.

        Probes the range midpoint and ``n_postures`` seeded uniform postures; if every joint torque
        is below ``UNLOADED_TAU_NM`` at all of them, gravity does not load the joints. A model where
        only some joints are unloaded (e.g. a vertical-axis joint) is accepted.
        """
        q = np.vstack([self.q_range.mean(axis=1), self.sample_q(np.random.default_rng(0), n_postures)])
        tau_max_nm = float(np.abs(self.kinematics(q)[2]).max())
        if tau_max_nm < UNLOADED_TAU_NM:
            gravity = np.round(self.mj_model.opt.gravity, 6).tolist()
            raise BodySchemaInputError(
                f"gravity {gravity} m/s^2 does not load the joints: max |tau_bias| = {tau_max_nm:.3g} N m over "
                f"{len(q)} postures (gravity is zero, or along every hinge axis), so equilibrium would be pure "
                "co-contraction; give gravity with a component in the joints' plane of motion "
                "(e.g. '0 -9.81 0' for hinges about z), or pass allow_unloaded=True if this is intended")

    def _select_muscles(self, muscles):
        m = self.mj_model
        spatial = [i for i in range(m.ntendon) if int(m.wrap_type[m.tendon_adr[i]]) != int(mujoco.mjtWrap.mjWRAP_JOINT)]
        if not spatial:
            raise BodySchemaInputError(
                "model has no spatial tendons: muscles must be <spatial> tendons in the <tendon> section")
        if muscles is None:
            return np.array(spatial, dtype=int)
        names = {self._name(mujoco.mjtObj.mjOBJ_TENDON, i): i for i in spatial}
        unknown = [name for name in muscles if name not in names]
        if unknown:
            raise BodySchemaInputError(f"unknown muscle {unknown}; the model's spatial tendons are {sorted(names)}")
        return np.array([names[name] for name in muscles], dtype=int)

    def _tendon_jacobian_index(self):
        """Row/column indices that scatter MuJoCo's sparse ``ten_J`` into a dense (ntendon, nv) array."""
        m = self.mj_model
        rows = np.repeat(np.arange(m.ntendon), m.ten_J_rownnz)
        entries = np.concatenate([np.arange(a, a + n) for a, n in zip(m.ten_J_rowadr, m.ten_J_rownnz)])
        return rows, m.ten_J_colind[entries], entries

    def _name(self, kind, i):
        return mujoco.mj_id2name(self.mj_model, kind, int(i)) or f"#{int(i)}"

    @property
    def n_joints(self) -> int:
        return int(self.mj_model.nq)

    @property
    def n_muscles(self) -> int:
        return len(self.muscle_ids)

    @property
    def joint_names(self) -> list[str]:
        return [self._name(mujoco.mjtObj.mjOBJ_JOINT, j) for j in range(self.mj_model.njnt)]

    @property
    def muscle_names(self) -> list[str]:
        return [self._name(mujoco.mjtObj.mjOBJ_TENDON, i) for i in self.muscle_ids]

    @property
    def q_range(self) -> np.ndarray:
        """Joint limits (N, 2) [rad or m], from the model."""
        return self.mj_model.jnt_range[: self.n_joints].copy()

    @property
    def xml_hash(self) -> str:
        """sha256 of the compiled model's canonical XML: identifies the robot in caches and checkpoints."""
        return hashlib.sha256(self.xml.encode()).hexdigest()

    # ------------------------------------------------------------------ physics
    def check_q(self, q, within_range: bool = False) -> np.ndarray:
        """Return q as a (B, N) float64 array, refusing non-finite values and wrong widths.

        within_range: also refuse postures outside the joint ranges (``q_range``), naming the first one.
        """
        q = np.atleast_2d(np.asarray(q, dtype=np.float64))
        if q.ndim != 2 or q.shape[1] != self.n_joints:
            raise BodySchemaInputError(f"q has shape {q.shape}; expected (B, {self.n_joints})")
        if not np.all(np.isfinite(q)):
            raise BodySchemaInputError("q contains NaN or inf")
        if within_range:
            lo, hi = self.q_range.T
            rows, joints = np.nonzero((q < lo) | (q > hi))
            if rows.size:
                b, j = int(rows[0]), int(joints[0])
                raise BodySchemaInputError(
                    f"q[{b}] of joint {self.joint_names[j]!r} is {q[b, j]:.6g}, outside its range "
                    f"[{lo[j]:.6g}, {hi[j]:.6g}] ({np.unique(rows).size} posture(s) out of range)")
        return q

    def kinematics(self, q) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Batched ``l_geo (B, M)``, ``G (B, M, N)`` and ``tau_bias (B, N)`` at postures ``q (B, N)``."""
        q = self.check_q(q)
        m, d = self.mj_model, self._data
        rows, cols, entries = self._dense_index
        batch = q.shape[0]
        lengths = np.empty((batch, m.ntendon))
        jac = np.zeros((batch, m.ntendon, m.nv))
        bias = np.empty((batch, m.nv))
        d.qvel[:] = 0.0
        for b in range(batch):  # MuJoCo evaluates one posture per call
            d.qpos[:] = q[b]
            mujoco.mj_kinematics(m, d)
            mujoco.mj_comPos(m, d)
            mujoco.mj_tendon(m, d)
            mujoco.mj_rne(m, d, 0, bias[b])
            lengths[b] = d.ten_length
            jac[b, rows, cols] = d.ten_J[entries]
        idx = self.muscle_ids
        return lengths[:, idx], jac[:, idx, :], bias

    def site_position(self, q, site: str) -> np.ndarray:
        """World position (B, 3) [m] of a named site, e.g. the hand."""
        q = self.check_q(q)
        sid = mujoco.mj_name2id(self.mj_model, mujoco.mjtObj.mjOBJ_SITE, site)
        if sid < 0:
            raise BodySchemaInputError(f"unknown site {site!r}")
        out = np.empty((q.shape[0], 3))
        for b in range(q.shape[0]):
            self._data.qpos[:] = q[b]
            mujoco.mj_kinematics(self.mj_model, self._data)
            out[b] = self._data.site_xpos[sid]
        return out

    def sample_q(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """n postures drawn uniformly inside the joint ranges."""
        lo, hi = self.q_range.T
        return lo + (hi - lo) * rng.random((n, self.n_joints))

    def __repr__(self):
        return (f"MusculoskeletalModel({self.mj_model.nq} joints {self.joint_names}, "
                f"{self.n_muscles} muscles {self.muscle_names})")
