"""MuJoCo's inverse dynamics per frame, doing only what the muscles' problem needs.

Profiled on the myoArm reach (one thread): ``mj_inverse`` was ~60 % of ``inverse_dynamics``, and ~80 % of it the
tendons' wrapping (``mj_tendon``). Two things are cut, neither changing a number the muscles' problem uses:

* ``lean_model``: the tendons that are neither muscles nor exert a force (no stiffness, damping or armature) are left
  out of the inverse model (myoArm: 17 of 67 tendons, 79 of 463 wrap points: ligament-like paths and the muscles that
  cross no free joint). With constraints off (``statics.dynamics``) such a tendon plays no part in the dynamics. So
  are the sites no kept tendon passes or wraps by (myoArm: 801 of 1169, myoLegs: 736 of 1060; markers and the idle
  tendons' points), which ``mj_kinematics`` would place at every frame: a site has no mass, and in the stored body
  only tendons refer to sites (it has no actuators or sensors, and its equalities join joints).
* ``lean_inverse``: instead of ``mj_inverse`` (which also builds and factors the mass matrix, the transmission and
  a velocity-only RNE for ``qfrc_bias``), ``mj_kinematics, mj_comPos, mj_tendon, mj_comVel, mj_passive`` and one RNE
  with the acceleration, ``qfrc_inverse = rne(qacc) + armature qacc - qfrc_passive``. It agrees with ``mj_inverse``
  to rounding (~1e-15 of the force's scale, the sums taken in another order), and is used only where the model has
  nothing it leaves out (no tendon damping or armature, no flex, no discrete-time inverse): ``uses_lean`` says which.
numpy and MuJoCo; never imports Lightning.
"""
from __future__ import annotations

import mujoco
import numpy as np

from ..sim.mjcf import compile_spec


def _exerts_force(m: mujoco.MjModel) -> np.ndarray:
    """(ntendon,) True where a tendon pushes on the joints by itself (a spring, a damper, armature)."""
    parts = [m.tendon_stiffness, m.tendon_damping, m.tendon_armature]
    parts += [getattr(m, name) for name in ("tendon_stiffnesspoly", "tendon_dampingpoly") if hasattr(m, name)]
    return np.any([np.abs(np.asarray(p).reshape(m.ntendon, -1)).max(1, initial=0.0) > 0 for p in parts], axis=0)


def lean_model(spec: mujoco.MjSpec, muscles) -> mujoco.MjModel:
    """``spec`` compiled without the tendons that are neither in ``muscles`` (names) nor exert a force, and without
    the sites that no tendon left refers to."""
    full = compile_spec(spec.copy())
    keep = set(muscles)
    idle = [mujoco.mj_id2name(full, mujoco.mjtObj.mjOBJ_TENDON, i) for i in np.flatnonzero(~_exerts_force(full))]
    for tendon in list(spec.tendons):
        if tendon.name in idle and tendon.name not in keep:
            spec.delete(tendon)
    used = _tendon_sites(compile_spec(spec))
    for site in list(spec.sites):
        if site.name not in used:
            spec.delete(site)
    return compile_spec(spec)


def _tendon_sites(m: mujoco.MjModel) -> set:
    """Names of the sites the tendons of ``m`` pass (site wraps) or keep a side with (a sphere or cylinder wrap's
    side site, in ``wrap_prm``; -1 where it has none)."""
    kinds = {int(mujoco.mjtWrap.mjWRAP_SPHERE), int(mujoco.mjtWrap.mjWRAP_CYLINDER)}
    ids = {int(obj) for kind, obj in zip(m.wrap_type, m.wrap_objid) if int(kind) == int(mujoco.mjtWrap.mjWRAP_SITE)}
    ids |= {int(side) for kind, side in zip(m.wrap_type, m.wrap_prm) if int(kind) in kinds and side >= 0}
    return {mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_SITE, i) for i in ids}


def uses_lean(m: mujoco.MjModel) -> bool:
    """True where ``lean_inverse`` computes what ``mj_inverse`` does (module docstring)."""
    discrete = m.opt.enableflags & int(mujoco.mjtEnableBit.mjENBL_INVDISCRETE)
    return not (discrete or m.nflex or m.tendon_damping.any() or m.tendon_armature.any()
                or (hasattr(m, "tendon_dampingpoly") and np.any(m.tendon_dampingpoly)))


def lean_inverse(m: mujoco.MjModel, d: mujoco.MjData, rne: np.ndarray) -> None:
    """The lean sequence on ``d``'s state (module docstring; constraints must be off): ``d``'s tendon lengths and
    Jacobian and ``qfrc_passive``, and the RNE with the acceleration into ``rne`` (nv,); ``qfrc_inverse`` is then
    ``assemble``'s (kept apart so that frames are assembled together)."""
    mujoco.mj_kinematics(m, d)
    mujoco.mj_comPos(m, d)
    mujoco.mj_tendon(m, d)
    mujoco.mj_comVel(m, d)
    mujoco.mj_passive(m, d)
    mujoco.mj_rne(m, d, 1, rne)


def assemble(m: mujoco.MjModel, rne: np.ndarray, qacc: np.ndarray, passive: np.ndarray) -> np.ndarray:
    """``qfrc_inverse`` (B, nv) of frames from ``lean_inverse``'s RNE and passive forces at accelerations ``qacc``."""
    return rne + m.dof_armature * qacc - passive
