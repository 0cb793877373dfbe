"""``MusculoskeletalModel``: batched muscle kinematics and gravity torques of any MJCF with tendons.

MuJoCo is the single source of truth. For a batch of postures ``q (B, N)`` it gives
``l_geo (B, M)`` geometric muscle lengths [m], ``G (B, M, N) = d l_geo / d q`` [m/rad] and
``tau_bias (B, N)`` the gravity torque at zero velocity [N m] (MuJoCo ``qfrc_bias``).
Tensions act on the joints as ``-G^T f``; static equilibrium is ``-G^T f = tau_bias``.
"""
from __future__ import annotations

import hashlib
from concurrent.futures import ThreadPoolExecutor
from typing import Mapping, Sequence

import mujoco
import numpy as np

from ..errors import BodySchemaInputError, did_you_mean
from ..notes import note
from .joints import JointMap
from .mjcf import (compile_spec, load_spec, packaged_model_names, packaged_model_xml, quiet_attach_warnings,
                   self_contained_xml)

FIXED_BASE_HINT = "hold the base with fixed_base=True (data.fixed_base: true in a config)"
UNLOADED_TAU_NM = 1e-9  # below this gravity torque at every probed posture, gravity does not load the joints


def paper_arm_xml() -> str:
    """The MJCF text of the paper's two-joint, six-muscle arm shipped with the package."""
    return packaged_model_xml("paper_arm")


def _muscle_forces(spec: mujoco.MjSpec) -> dict[str, float]:
    """Peak force [N] of each tendon driven by a muscle actuator (``<muscle force=...>``), by tendon name.

    A force of -1 asks MuJoCo to derive it at compile time (scale / acc0): then the spec is compiled
    with its actuators once; NaN if that fails (e.g. a length range that does not converge).
    """
    muscles = [a for a in spec.actuators
               if a.trntype == mujoco.mjtTrn.mjTRN_TENDON and a.gaintype == mujoco.mjtGain.mjGAIN_MUSCLE]
    forces = {a.target: float(a.gainprm[2]) for a in muscles}
    if any(f <= 0 for f in forces.values()):
        try:
            with quiet_attach_warnings():
                compiled = spec.copy().compile()
            for a in muscles:
                i = mujoco.mj_name2id(compiled, mujoco.mjtObj.mjOBJ_ACTUATOR, a.name) if a.name else -1
                if i >= 0 and forces[a.target] <= 0:
                    forces[a.target] = float(compiled.actuator_gainprm[i, 2])
        except Exception:  # MuJoCo raises plain ValueError; a force stays unknown
            pass
    return {name: (f if f > 0 else float("nan")) for name, f in forces.items()}


def _check_same_lock(eq, joint: str, offset: float):
    """A joint already constrained may be "locked" again only at the value it is locked at."""
    if eq.name2:
        raise BodySchemaInputError(f"joint {joint!r} follows {eq.name2!r} through an <equality joint> coupling; "
                                   f"lock {eq.name2!r} instead")
    if abs(float(eq.data[0]) - offset) > 1e-12 or np.any(np.asarray(eq.data[1:5]) != 0):
        raise BodySchemaInputError(f"joint {joint!r} is already locked at {float(eq.data[0]):.6g} (from its reference) "
                                   f"by equality {eq.name!r}; it cannot be locked at another value")


def _add_locks(spec: mujoco.MjSpec, locked: Mapping[str, float]):
    """Lock joints at absolute values [rad or m] as ``<equality joint>`` constraints without joint2."""
    joints = {j.name: j for j in spec.joints}
    constrained = {e.name1: e for e in spec.equalities if e.type == mujoco.mjtEq.mjEQ_JOINT}
    for name, value in locked.items():
        if name in constrained:  # a model rebuilt from its stored XML already holds its locks
            _check_same_lock(constrained[name], name, float(value) - float(joints[name].ref) if name in joints else 0.0)
            continue
        if name not in joints:
            raise BodySchemaInputError(f"locked joint {name!r} is not a joint of the model"
                                       f"{did_you_mean(name, joints)}; joints are {sorted(joints)}")
        joint, value = joints[name], float(value)
        lo, hi = joint.range
        if not np.isfinite(value) or (lo < hi and not lo <= value <= hi):
            raise BodySchemaInputError(f"locked joint {name!r} at {value!r} is outside its range [{lo:.6g}, {hi:.6g}]")
        eq = spec.add_equality(name=f"lock_{name}", type=mujoco.mjtEq.mjEQ_JOINT, name1=name,
                               objtype=mujoco.mjtObj.mjOBJ_JOINT)
        eq.data[:5] = [value - float(joint.ref), 0.0, 0.0, 0.0, 0.0]


def _weld_free_joints(spec: mujoco.MjSpec):
    """Delete every free joint: its body stays where the MJCF puts it (``fixed_base``). Keyframes, whose qpos had
    the free joints' 7 numbers, go too (the stored XML drops them anyway)."""
    free = [j for j in spec.joints if j.type == mujoco.mjtJoint.mjJNT_FREE]
    for element in free + (list(spec.keys) if free else []):
        spec.delete(element)


UNCROSSED_ARM_M = 1e-9  # [m/rad]: a tendon Jacobian entry at most this large is rounding (real arms are mm)

def check_threads(threads) -> int:
    """``threads`` as an int, or the ``BodySchemaInputError`` naming it (an integer >= 1 is allowed)."""
    if isinstance(threads, bool) or not isinstance(threads, (int, np.integer)) or threads < 1:
        raise BodySchemaInputError(f"threads={threads!r}; give an integer >= 1")
    return int(threads)


def _thread_count(threads, batch: int) -> int:
    """The threads worth starting for ``batch`` postures (at least ``MIN_POSTURES_PER_THREAD`` each)."""
    return max(1, min(check_threads(threads), batch // MIN_POSTURES_PER_THREAD))


MIN_POSTURES_PER_THREAD = 32  # below this a thread's start costs more than its share of MuJoCo's work


class MusculoskeletalModel:
    """A MuJoCo model whose spatial tendons are the robot's muscles.

    Args:
        source: a packaged model name (``"paper_arm"``, ``"arm3_8"``, ``"opensim_like_arm"``; see
            ``packaged_model_names()``), ``myo:<name>`` for a MyoSuite model (``myo:myoelbow_2dof``,
            ``myo:myoarm``, ...; needs ``myo-sim``, see ``sim.install``), a path to an MJCF file, or MJCF text.
        muscles: names of the tendons that are muscles; default: the tendons that the model's muscle
            actuators drive when it has any (ligaments and other passive tendons are not muscles), of
            those only the ones crossing a free joint; else every spatial tendon (fixed tendons never).
        gravity: optional override of the model's gravity vector [m/s^2].
        allow_unloaded: accept a model whose gravity loads no joint (zero gravity, or gravity along
            every hinge axis). Refused by default: the static equilibrium ``-G^T f = tau_bias`` is
            then ``-G^T f = 0`` everywhere, i.e. pure co-contraction, which is almost always a
            wrong gravity vector or a wrongly oriented model rather than the robot one meant.
        locked_joints: ``{joint: value}`` [rad or m] joints held fixed (written into the model as
            ``<equality joint>`` locks, so the stored XML carries them).
        lock_uncrossed: lock free joints that no muscle crosses at their reference position (clipped
            into their range), printing one summary line: nothing could hold them against gravity.
        fixed_base: hold a floating base: every ``<freejoint>`` (a root body's 6-DOF joint, e.g.
            MyoSuite's legs' pelvis) is deleted before compiling, so its body is welded to the world
            at the pose the MJCF places it in (the model's reference pose, ``qpos0``; for MyoSuite's
            legs the standing pelvis). The stored XML has no free joint, so rebuilding from it needs
            no option. Without it a free joint is refused, naming this option. Ball joints are refused
            in any case: replace each by up to three hinge joints in the MJCF.

    Postures ``q (B, N)`` are the *free* joints (``joint_names``): those neither locked nor following
    another through an ``<equality joint>`` coupling (see ``sim/joints.py``); without couplings and
    locks these are all the model's joints. MuJoCo actuators are removed before compiling (their
    muscle peak forces are kept in ``actuator_f_max_n``): the pipeline needs only tendons, and a
    ``<muscle>`` actuator whose length-range computation fails must not stop the model loading.
    ``xml`` is self-contained (``sim/mjcf.py``) and the model is compiled from it, so a checkpoint
    holding ``xml`` rebuilds exactly this model anywhere.
    """

    def __init__(self, source: str = "paper_arm", muscles: Sequence[str] | None = None,
                 gravity: Sequence[float] | None = None, allow_unloaded: bool = False,
                 locked_joints: Mapping[str, float] | None = None, lock_uncrossed: bool = True,
                 fixed_base: bool = False):
        spec = load_spec(source)
        if fixed_base:
            _weld_free_joints(spec)
        self._actuator_forces = _muscle_forces(spec)
        for actuator in list(spec.actuators):
            spec.delete(actuator)
        if gravity is not None:
            spec.option.gravity = np.asarray(gravity, dtype=float)
        _add_locks(spec, dict(locked_joints or {}))
        self._build(spec)
        self.muscle_ids = self._select_muscles(muscles)
        if lock_uncrossed:
            self._lock_uncrossed(muscles)
        if muscles is None and self._actuator_forces:
            self._drop_muscles_crossing_nothing()
        if not allow_unloaded:
            self._check_gravity_loads()

    def _build(self, spec: mujoco.MjSpec):
        """Compile the self-contained XML of ``spec``: the model used here is exactly the one stored."""
        self.xml = self_contained_xml(spec)
        self.mj_model = compile_spec(mujoco.MjSpec.from_string(self.xml))
        self._check_joints()
        self.joint_map = JointMap.from_model(self.mj_model)
        self._q_range = self.joint_map.free_range(self.mj_model.jnt_range[: self.mj_model.njnt])
        m = self.mj_model
        self._passive = bool(m.jnt_stiffness.any() or m.tendon_stiffness.any() or m.body_gravcomp.any())
        self._data = mujoco.MjData(m)
        self._dense_index = self._tendon_jacobian_index()

    def _lock_uncrossed(self, muscles):
        """Lock the free joints no muscle moves (|G| = 0 at probed postures), then rebuild."""
        q = np.vstack([self.q_range.mean(axis=1), self.sample_q(np.random.default_rng(0), 8)])
        crossed = np.abs(self.kinematics(q)[1]).max(axis=(0, 1)) > 1e-12
        if crossed.all() or not crossed.any():  # none crossed: a kinematic rig, not a robot to hold up
            return
        lo, hi = self.q_range.T
        names = self.joint_names
        ref = np.clip(self.joint_map.qpos0[self.joint_map.free], lo, hi)
        locks = {names[c]: float(ref[c]) for c in np.flatnonzero(~crossed)}
        # from the stored XML, not ``spec``: making a MyoSuite model self-contained stripped ``spec``'s materials
        # and meshes in place, and only the stored XML also dropped every reference to them
        spec = mujoco.MjSpec.from_string(self.xml)
        _add_locks(spec, locks)
        self._build(spec)
        self.muscle_ids = self._select_muscles(muscles)
        note(f"locked {len(locks)} joint(s) that no muscle crosses at their reference position: "
             + ", ".join(f"{k}={v:.4g}" for k, v in locks.items()) + f"; free joints: {self.joint_names}")

    def _drop_muscles_crossing_nothing(self):
        """Default muscles that cross no free joint (e.g. finger muscles of a locked hand) are left out."""
        q = np.vstack([self.q_range.mean(axis=1), self.sample_q(np.random.default_rng(0), 8)])
        moves = np.abs(self.kinematics(q)[1]).max(axis=(0, 2)) > 1e-12
        if not moves.all():
            dropped = [n for n, keep in zip(self.muscle_names, moves) if not keep]
            self.muscle_ids = self.muscle_ids[moves]
            note(f"left out {len(dropped)} muscle(s) that cross no free joint: {dropped}")

    # ------------------------------------------------------------------ structure
    def _check_joints(self):
        m = self.mj_model
        if m.njnt == 0:
            raise BodySchemaInputError("model has no joint: need at least one hinge or slide joint")
        names = [self._name(mujoco.mjtObj.mjOBJ_JOINT, j) for j in range(m.njnt)]
        bad = {kind: [n for n, t in zip(names, m.jnt_type) if int(t) == int(code)]
               for kind, code in (("free", mujoco.mjtJoint.mjJNT_FREE), ("ball", mujoco.mjtJoint.mjJNT_BALL))}
        if bad["free"]:
            raise BodySchemaInputError(f"joint(s) {bad['free']} are free joints (a floating base); only hinge and "
                                       f"slide joints are supported: {FIXED_BASE_HINT}, welding the base at the "
                                       "model's reference pose")
        if bad["ball"]:
            raise BodySchemaInputError(f"joint(s) {bad['ball']} are ball joints; only hinge and slide joints are "
                                       "supported: replace each by up to three hinge joints in the MJCF")
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
        names = {self._name(mujoco.mjtObj.mjOBJ_TENDON, i): i for i in spatial}
        if muscles is None:
            if self._actuator_forces:  # the tendons muscle actuators drive; ligaments are not muscles
                return np.array([i for n, i in names.items() if n in self._actuator_forces], dtype=int)
            return np.array(spatial, dtype=int)
        unknown = [name for name in muscles if name not in names]
        if unknown:
            raise BodySchemaInputError(f"unknown muscle {unknown}{did_you_mean(unknown[0], names)}; the model's "
                                       f"spatial tendons are {sorted(names)}")
        return np.array([names[name] for name in muscles], dtype=int)

    def _tendon_jacobian_index(self):
        """Row/column indices that scatter MuJoCo's sparse ``ten_J`` into a dense (ntendon, nv) array."""
        m = self.mj_model
        rows = np.repeat(np.arange(m.ntendon), m.ten_J_rownnz)
        entries = np.concatenate([np.arange(a, a + n) for a, n in zip(m.ten_J_rowadr, m.ten_J_rownnz)]
                                 + [np.zeros(0, int)])
        return rows, m.ten_J_colind[entries], entries

    def _name(self, kind, i):
        return mujoco.mj_id2name(self.mj_model, kind, int(i)) or f"#{int(i)}"

    @property
    def n_joints(self) -> int:
        """Number of free joints N (all the model's joints when none is locked or coupled)."""
        return len(self.joint_map.free)

    @property
    def n_muscles(self) -> int:
        return len(self.muscle_ids)

    @property
    def joint_names(self) -> list[str]:
        """Names of the free joints, the columns of q."""
        return self.joint_map.free_names

    @property
    def all_joint_names(self) -> list[str]:
        """Every joint of the model (free, locked and coupled), the columns of ``full_q``."""
        return list(self.joint_map.names)

    @property
    def locked_joints(self) -> dict[str, float]:
        """Locked joints and their values [rad or m]."""
        return {self.joint_map.names[j]: v for j, v in self.joint_map.locked.items()}

    @property
    def actuator_f_max_n(self) -> np.ndarray:
        """(M,) peak force [N] of each muscle's actuator in the source model (NaN: none or unknown)."""
        return np.array([self._actuator_forces.get(n, np.nan) for n in self.muscle_names])

    def full_q(self, q) -> np.ndarray:
        """Every joint of the model (B, nq) at free-joint postures q (B, N): exactly on couplings and locks."""
        return self.joint_map.full_q(self.check_q(q))

    @property
    def muscle_names(self) -> list[str]:
        ids = np.asarray(self.muscle_ids).tobytes()  # muscle_ids may be reassigned: names cached per selection
        if getattr(self, "_muscle_names_of", (None,))[0] != ids:
            self._muscle_names_of = (ids, [self._name(mujoco.mjtObj.mjOBJ_TENDON, i) for i in self.muscle_ids])
        return list(self._muscle_names_of[1])

    @property
    def q_range(self) -> np.ndarray:
        """Free joints' limits (N, 2) [rad or m], from the model (narrowed so coupled followers stay in range)."""
        return self._q_range.copy()

    has_physics = True  # sim.robot.RobotModel: a compiled model (kinematics, feasibility, settle)

    @property
    def xml_hash(self) -> str:
        """sha256 of the compiled model's canonical XML: identifies the robot in caches and checkpoints."""
        return hashlib.sha256(self.xml.encode()).hexdigest()

    # ------------------------------------------------------------------ physics
    def check_q(self, q, within_range: bool = False) -> np.ndarray:
        """Return q as a (B, N) float64 array, refusing non-finite values and wrong widths.

        A model with locked or coupled joints also takes every joint (B, nq), checked against the
        couplings and locks (``joints.COUPLING_TOL_RAD``) and reduced to the free joints.
        within_range: also refuse postures outside the joint ranges (``q_range``), naming the first one.
        """
        q = np.atleast_2d(np.asarray(q, dtype=np.float64))
        n_all = len(self.joint_map.names)
        if q.ndim != 2 or q.shape[1] not in (self.n_joints, n_all):
            every = "" if n_all == self.n_joints else f" (free joints {self.joint_names}) or (B, {n_all}) (every joint)"
            raise BodySchemaInputError(f"q has shape {q.shape}; expected (B, {self.n_joints}){every}")
        if not np.all(np.isfinite(q)):
            raise BodySchemaInputError("q contains NaN or inf")
        if q.shape[1] != self.n_joints:
            q = self.joint_map.reduce(q)
        if within_range:
            lo, hi = self.q_range.T
            rows, joints = np.nonzero((q < lo) | (q > hi))
            if rows.size:
                b, j = int(rows[0]), int(joints[0])
                raise BodySchemaInputError(
                    f"q[{b}] of joint {self.joint_names[j]!r} is {q[b, j]:.6g}, outside its range "
                    f"[{lo[j]:.6g}, {hi[j]:.6g}] ({np.unique(rows).size} posture(s) out of range)")
        return q

    def _fill_kinematics(self, full, rows, d, out) -> None:
        """MuJoCo's tendon lengths, tendon Jacobian and bias forces of postures ``full[rows]`` into ``out``."""
        m, (lengths, jac, bias) = self.mj_model, out
        tendon_rows, cols, entries = self._dense_index
        d.qvel[:] = 0.0
        for b in rows:  # MuJoCo evaluates one posture per call
            d.qpos[:] = full[b]
            mujoco.mj_kinematics(m, d)
            mujoco.mj_comPos(m, d)
            mujoco.mj_tendon(m, d)
            mujoco.mj_rne(m, d, 0, bias[b])
            if self._passive:
                mujoco.mj_passive(m, d)
                bias[b] -= d.qfrc_passive
            lengths[b] = d.ten_length
            jac[b, tendon_rows, cols] = d.ten_J[entries]

    def _thread_data(self, threads: int) -> list:
        """One ``MjData`` per thread, made once (the first is the model's own)."""
        pool = self.__dict__.setdefault("_datas", [self._data])
        pool.extend(mujoco.MjData(self.mj_model) for _ in range(threads - len(pool)))
        return pool[:threads]

    def kinematics(self, q, threads: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Batched ``l_geo (B, M)``, ``G (B, M, N)`` and ``tau_bias (B, N)`` at postures ``q (B, N)``.

        With couplings or locks, G and tau_bias are in the free joints: ``G = J_ten E``,
        ``tau_bias = E^T (qfrc_bias - qfrc_passive)`` with ``E = d q_full / d q`` (sim/joints.py).
        Passive forces (joint and tendon springs, gravity compensation) are part of tau_bias when the
        model has any: a non-muscle tendon with stiffness pulls as MuJoCo says, in the equilibrium
        and in the settle simulation alike. ``threads``: MuJoCo's per-posture calls on that many threads (each
        with its own ``MjData``; the same numbers whatever the count).
        """
        q = self.check_q(q)
        full = self.joint_map.full_q(q)
        m = self.mj_model
        batch = q.shape[0]
        out = (np.empty((batch, m.ntendon)), np.zeros((batch, m.ntendon, m.nv)), np.empty((batch, m.nv)))
        threads = _thread_count(threads, batch)
        if threads == 1:
            self._fill_kinematics(full, range(batch), self._data, out)
        else:  # MuJoCo releases the GIL inside its calls
            chunks = np.array_split(np.arange(batch), threads)
            with ThreadPoolExecutor(threads) as pool:
                list(pool.map(self._fill_kinematics, [full] * threads, chunks, self._thread_data(threads),
                              [out] * threads))
        lengths, jac, bias = out
        idx = self.muscle_ids
        if self.joint_map.identity:
            return lengths[:, idx], jac[:, idx, :], bias
        tangent = self.joint_map.tangent(q, full)  # (B, nq, N)
        return lengths[:, idx], jac[:, idx, :] @ tangent, np.einsum("bjn,bj->bn", tangent, bias)

    def crossing(self, n_postures: int = 64, seed: int = 0) -> np.ndarray:
        """``(M, N)`` bool: the free joints each muscle crosses, the nonzero pattern of MuJoCo's tendon Jacobian
        (through the couplings) at the range midpoint and ``n_postures`` seeded uniform postures, above
        ``UNCROSSED_ARM_M`` (a joint moving both ends of a path alike leaves rounding there, not an arm)."""
        q = np.vstack([self.q_range.mean(axis=1), self.sample_q(np.random.default_rng(seed), n_postures)])
        return np.abs(self.kinematics(q)[1]).max(axis=0) > UNCROSSED_ARM_M

    def site_position(self, q, site: str) -> np.ndarray:
        """World position (B, 3) [m] of a named site, e.g. the hand."""
        q = self.full_q(q)
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
        """n postures of the free joints drawn uniformly inside their ranges (on the coupled manifold)."""
        lo, hi = self.q_range.T
        return lo + (hi - lo) * rng.random((n, self.n_joints))

    def __repr__(self):
        return (f"MusculoskeletalModel({self.n_joints} joints {self.joint_names}, "
                f"{self.n_muscles} muscles {self.muscle_names})")
