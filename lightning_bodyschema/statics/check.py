"""Static optimization checked by MuJoCo itself: the activations go into ``mjData`` of the body with its muscle
actuators put back (``statics.muscles.actuated_model``), and MuJoCo's own forces must balance, and keep, the posture.

Contacts are off (the equilibrium has none, as in ``sim.settle``); a cut muscle's actuator is held at zero force
(``forcerange [0, 0]``: a ruptured muscle pulls neither actively nor passively); locked joints and couplings are held
by MuJoCo's own constraints made near-hard (``_hold_couplings_and_locks``: this check steps MuJoCo's muscle
actuators, while ``sim.settle`` holds them exactly in its own step). MuJoCo steps one posture at a time: these are
checks, not a hot path.
"""
from __future__ import annotations

import mujoco
import numpy as np

from ..errors import BodySchemaInputError
from ..sim.settle import SOLVER_TOLERANCE
from .muscles import actuated_model
from .optimize import StaticBody, StaticResult


LOCK_ARMATURE = 1e6  # [kg m^2] added to a locked joint: it does not accelerate
COUPLING_IMPEDANCE = 0.9999  # MuJoCo solimp d of a coupling: near-hard (MuJoCo's largest d)


def _hold_couplings_and_locks(m: mujoco.MjModel, joint_map) -> tuple[np.ndarray, np.ndarray]:
    """Hold ``m``'s locks and couplings with MuJoCo itself; returns the locked joints and their values. Locks: the
    equality is switched off and the joint gets a huge armature, so it does not accelerate while the rest of the body
    moves as if it were welded (M_jj -> inf), and the caller puts it back each step. Couplings: MuJoCo's equality
    constraint made stiff (time constant 2 steps, impedance COUPLING_IMPEDANCE): at rest a follower misses its
    polynomial by ~(1 - d) a / (d k), and its constraint force is the one the body needs. (``sim.settle`` holds both
    exactly in its own step; this check steps MuJoCo's own muscle actuators, so MuJoCo must hold them.)"""
    locked = np.array(sorted(joint_map.locked), dtype=int)
    m.dof_armature[locked] += LOCK_ARMATURE
    for e in range(m.neq):
        if int(m.eq_type[e]) != int(mujoco.mjtEq.mjEQ_JOINT):
            continue
        if m.eq_obj2id[e] < 0:
            m.eq_active0[e] = 0
        else:
            m.eq_solref[e] = [2.0 * m.opt.timestep, 1.0]
            m.eq_solimp[e, :2] = COUPLING_IMPEDANCE
    return locked, np.array([joint_map.locked[j] for j in locked])


class MuJoCoBody:
    """A private copy of the actuated model with locks and couplings held, and one MjData."""

    def __init__(self, body: StaticBody):
        if body.curves is None:
            raise BodySchemaInputError("the MuJoCo check needs MuJoCo <muscle> actuators on every muscle")
        m = actuated_model(body.model, body.curves)
        m.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_CONTACT)
        m.opt.tolerance = min(m.opt.tolerance, SOLVER_TOLERANCE)
        self.locked, self.locked_values = _hold_couplings_and_locks(m, body.model.joint_map)
        self.m, self.d, self.model = m, mujoco.MjData(m), body.model

    def start(self, q_free, activation, cut):
        """Rest at ``q_free`` with activations (and controls) ``activation``; cut muscles at zero force."""
        m, d = self.m, self.d
        mujoco.mj_resetData(m, d)
        m.actuator_forcelimited[:] = cut
        m.actuator_forcerange[:] = 0.0
        d.qpos[:] = self.model.full_q(q_free[None])[0]
        d.act[:], d.ctrl[:] = activation, activation
        mujoco.mj_forward(m, d)

    def hold_locks(self):
        """Locked joints back at their value and at rest (after each MuJoCo step)."""
        self.d.qpos[self.locked], self.d.qvel[self.locked] = self.locked_values, 0.0

    def free_q(self) -> np.ndarray:
        return self.d.qpos[self.model.joint_map.free].copy()


def _rows(result: StaticResult) -> np.ndarray:
    if result.activation is None:
        raise BodySchemaInputError("the MuJoCo check needs activations (a body with MuJoCo muscle actuators)")
    return np.flatnonzero(np.isfinite(result.activation).all(1))


def mujoco_residual_nm(body: StaticBody, result: StaticResult) -> tuple[np.ndarray, np.ndarray]:
    """``(residual (B,) [N m], tension_miss (B,) [N])`` by MuJoCo at rest: the largest free-joint torque of
    ``qfrc_actuator + qfrc_passive - qfrc_bias`` (through couplings), and the largest difference between MuJoCo's
    tendon tension ``-gear * actuator_force`` and ``result.tension_n``. NaN on rows without activations."""
    sim = MuJoCoBody(body)
    residual, miss = np.full(len(result.q), np.nan), np.full(len(result.q), np.nan)
    gear = body.curves.gear
    for b in _rows(result):
        sim.start(result.q[b], result.activation[b], result.faults.cut[b])
        d = sim.d
        tangent = body.model.joint_map.tangent(result.q[b:b + 1])[0]  # (nq, N)
        residual[b] = np.abs(tangent.T @ (d.qfrc_actuator + d.qfrc_passive - d.qfrc_bias)).max()
        miss[b] = np.abs(-gear * d.actuator_force - result.tension_n[b]).max()
    return residual, miss


def mujoco_drift_rad(body: StaticBody, result: StaticResult, duration_s: float = 0.5) -> np.ndarray:
    """(B,) largest ``|q(t) - q|`` [rad] over the free joints while MuJoCo simulates ``duration_s`` from rest at
    each posture with the result's activations held (the settle check's question: does the body stay?). NaN on
    rows without activations."""
    sim = MuJoCoBody(body)
    drift = np.full(len(result.q), np.nan)
    steps = max(1, int(round(duration_s / sim.m.opt.timestep)))
    for b in _rows(result):
        sim.start(result.q[b], result.activation[b], result.faults.cut[b])
        worst = 0.0
        for _ in range(steps):
            mujoco.mj_step(sim.m, sim.d)
            sim.hold_locks()
            worst = max(worst, float(np.abs(sim.free_q() - result.q[b]).max()))
        drift[b] = worst
    return drift


def mujoco_motion_error(body: StaticBody, result) -> np.ndarray:
    """(B, N) MuJoCo's free-joint acceleration minus the requested ``result.qacc`` [rad/s^2 or m/s^2] per frame of a
    ``statics.dynamics.MotionResult``: ``mj_forward`` of the body with its muscle actuators at the frame's state
    (positions and velocities of every joint through the couplings, ``act`` = the activations, ``ctrl`` = the
    controls, cut muscles at zero force, residual torques as ``qfrc_applied`` on their joints), its constraints off
    and the locks and couplings held exactly instead: the free joints' acceleration is
    ``(E^T M E)^-1 E^T M (qacc - (dE/dt) qvel)`` of MuJoCo's unconstrained ``qacc`` (that very ``qacc`` where every
    joint is free). On a floating root (``result.root_qpos``) MuJoCo runs the body with its root free, the root's
    residual forces applied, and the root's 6K accelerations minus ``result.root_qacc`` follow as columns N.. of
    (B, N + 6K). NaN on rows without activations."""
    from .dynamics import _inverse_body
    from .root import FrameLayout, floating_spec

    floating = result.root_qpos is not None
    m = actuated_model(body.model, body.curves, floating_spec(body) if floating else None)
    layout = FrameLayout.of(body, floating, m)
    m.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_CONSTRAINT)
    d, error = mujoco.MjData(m), np.full((len(result.q), result.q.shape[1] + len(layout.root_dof)), np.nan)
    full, qvel_full, _, tangent = _inverse_body(body).full_state(result.q, result.qvel, result.qacc)
    rate = body.model.joint_map.tangent_rate(result.q, result.qvel, full)
    root = (result.root_qpos, result.root_qvel, result.root_qacc) if floating else None
    qpos, qvel, _ = layout.state(full, qvel_full, qvel_full, root)
    mass, free_dofs = np.zeros((m.nv, m.nv)), layout.rest_dof[body.model.joint_map.free]
    wanted = result.qacc if not floating else np.hstack([result.qacc, result.root_qacc])
    m.actuator_forcerange[:] = 0.0
    for b in _rows(result):
        m.actuator_forcelimited[:] = result.faults.cut[b]
        d.qpos[:], d.qvel[:], d.act[:], d.ctrl[:] = qpos[b], qvel[b], result.activation[b], result.control[b]
        d.qfrc_applied[:] = 0.0
        if result.residual_nm is not None:
            d.qfrc_applied[free_dofs[[body.model.joint_names.index(n) for n in result.residual_dofs]]] = \
                result.residual_nm[b]
        if floating:
            d.qfrc_applied[layout.root_dof] = result.root_residual[b]
        mujoco.mj_forward(m, d)
        mujoco.mj_fullM(m, d, mass)
        E = _tangent_of(layout, tangent[b], m.nv)
        qacc = d.qacc.copy()
        qacc[layout.rest_dof] -= rate[b]
        error[b] = np.linalg.solve(E.T @ mass @ E, E.T @ mass @ qacc) - wanted[b]
    return error


def _tangent_of(layout, tangent, nv: int) -> np.ndarray:
    """``d state / d (free joints, roots)`` (nv, N + 6K): the joint map's ``E`` on the welded body's dofs, the
    identity on the roots'."""
    n, k = tangent.shape[1], len(layout.root_dof)
    E = np.zeros((nv, n + k))
    E[layout.rest_dof, :n] = tangent
    E[layout.root_dof, n + np.arange(k)] = 1.0
    return E
