"""The settle simulation's step: one MuJoCo model copy, many cases in lockstep (``sim.settle`` runs it).

Tensions act on the joints as ``-J_ten^T f`` with MuJoCo's own ``ten_length`` / ``ten_J`` (sparse in MuJoCo 4,
scattered into a dense (M, nv) buffer) of the current state: each step is ``mj_step1`` (positions, tendons, mass
matrix, gravity and passive forces), the step below in numpy, ``mj_step2`` (joint-limit constraints, integration).
No global MuJoCo callback is installed.

Integration (``SettleSimulator._reduced_step``), in the free joints q of ``sim/joints.py`` (``E = d q_full / dq``):

* linearly implicit Euler: ``(M_r + dt D_r + dt^2 K_r) dqdot = dt (F_r - dt K_r qdot)``, ``M_r = E^T M E``,
  ``F_r = E^T F`` every force of the current state, ``K_r = G^T diag(dphi/ddelta) G`` the taut springs' stiffness
  (``G = J_ten E``), ``D_r`` the dampers below; the model's timestep (1 ms paper arm, 2 ms MyoSuite). MuJoCo
  integrates it: ``qfrc_applied`` is the force that gives every joint ``E qddot + dE/dt qdot``.
  The rest posture is where ``F_r = 0``, the balance the data and the oracle solve, exactly (to float rounding).
  Why implicit: the springs are stiff (``alpha (f + k)``) on light segments (myoLegs' toes: modes near 1000 rad/s);
  the explicit spring and muscle damping rang there at a 2 ms step (a limit cycle, never at rest). A command
  stretching a muscle by tens of centimetres now rests where its antagonists balance it (MN tensions) instead of
  blowing up; joint forces above ``max_torque_nm`` are UNSTABLE.
* damping (the rest posture does not depend on it; only how fast it is reached): mass-proportional ``a M_r qdot``,
  ``a = mass_damping_per_s`` (default 8 1/s, critical for the hanging paper arm's 4 rad/s pendulum mode);
  stiffness-proportional muscle damping (Kelvin-Voigt muscle) ``beta * dphi/ddelta * dl_geo/dt``,
  ``beta = muscle_damping_s`` (default 0.01 s); the model's joint damping. All three implicitly.
  The total tension is clipped at 0: a wire never pushes.
* no contacts: the static equilibrium the data and the schemas use has no contact forces, so the
  simulation has none either (on myoArm the upper arm would otherwise push against the torso at
  postures the data holds as equilibria, and exact commands would settle elsewhere).
* joint limits: MuJoCo's soft limit constraints of the model on the free joints (so a posture pressed into a limit
  may sit slightly beyond it: a few mrad at ordinary tensions, 0.05 rad at 1500 N). A follower's own limit is off:
  its range is its leader's (``JointMap.free_range``), which otherwise pushed where that narrowing rounds.

Couplings and locks (``<equality joint>``, sim/joints.py): q_ref and q_settle are the free joints; the
simulation runs on every joint, held exactly on the couplings and locks: MuJoCo's equality constraints are off
(``_hold_exactly``), the step gives each follower the acceleration its polynomial prescribes and a locked joint none,
and after MuJoCo integrates, followers and locked joints are put back from the free joints' positions and velocities
(``_onto_couplings``). Measured on myoLegs (knees: patella and tibia translations and rotations coupled to the knee
angle), why: MuJoCo's constraints are soft by construction (the previous near-hard ones left followers 0.2-0.3 mm off
their polynomials at a 2 ms step, shrinking as dt^2), and the legs' softest directions (0.7 N m/rad) turned that
into 0.01-0.02 rad: exact equilibria did not rest where they are.

numpy and MuJoCo only.
"""
from __future__ import annotations

import copy
from typing import NamedTuple

import mujoco
import numpy as np

from .model import MusculoskeletalModel
from .settle_inputs import _Laws
from .settle_params import SettleParams, SettleStatus
from .spring import SpringParams

SOLVER_TOLERANCE = 1e-12  # MuJoCo opt.tolerance: constraint (limit) forces solved to convergence


class SettleRun(NamedTuple):
    """Per-case outcome of one lockstep run (arrays over the cases of the run)."""

    q: np.ndarray  # (B, N) last finite posture seen at a check [rad]
    qvel: np.ndarray  # (B, N) [rad/s]
    f: np.ndarray  # (B, M) tensions of that state [N]
    status: np.ndarray  # (B,) SettleStatus ints
    time_s: np.ndarray  # (B,) simulated time at the stop [s]


class SettleSimulator:
    """A private copy of the model and the index arrays a step needs; runs cases in lockstep."""

    def __init__(self, model: MusculoskeletalModel, spring: SpringParams, params: SettleParams):
        self.m = copy.copy(model.mj_model)  # private: integrator, timestep and flags are ours to set
        self.m.opt.integrator = mujoco.mjtIntegrator.mjINT_EULER
        self.m.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_AUTORESET)  # blow-ups stay visible
        self.m.opt.tolerance = min(self.m.opt.tolerance, SOLVER_TOLERANCE)  # limit forces solved to convergence
        self.m.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_CONTACT)  # the equilibrium has no contacts
        if params.timestep_s is not None:
            self.m.opt.timestep = params.timestep_s
        self.ids = np.asarray(model.muscle_ids)
        self.k = np.broadcast_to(np.asarray(spring.k_n, float), (len(self.ids),)).copy()
        self.alpha = np.broadcast_to(np.asarray(spring.alpha_per_m, float), (len(self.ids),)).copy()
        self.params = params
        self.joint_map = model.joint_map
        self.joint_damping = self.m.dof_damping.copy()  # [N m s/rad]: integrated implicitly in _reduced_step
        self.m.dof_damping[:] = 0.0
        self._hold_exactly()
        self.pool: list[mujoco.MjData] = []
        self._jacobian_index()

    def _hold_exactly(self):
        """Couplings and locks are not MuJoCo constraints here: every <equality joint> is switched off and the
        step itself keeps the state on the manifold (``_reduced_step`` gives the followers the acceleration the
        polynomials prescribe, ``_onto_couplings`` puts positions and velocities back on it after MuJoCo integrates)."""
        m, jm = self.m, self.joint_map
        self._locked = np.array(sorted(jm.locked), dtype=int)
        self._locked_values = np.array([jm.locked[j] for j in self._locked])
        for e in range(m.neq):
            if int(m.eq_type[e]) == int(mujoco.mjtEq.mjEQ_JOINT):
                m.eq_active0[e] = 0
        # a follower's range is its leader's (JointMap.free_range narrows the free joints' ranges to keep followers
        # inside theirs); its own limit would only push where that narrowing rounds (0.2 mrad on myoLegs' knee)
        m.jnt_limited[[j for j, _, _ in jm.deps]] = 0

    def _jacobian_index(self):
        """Scatter indices from MuJoCo's sparse ``ten_J`` rows of the muscles into a dense (M, nv) block."""
        m = self.m
        rows = [np.full(m.ten_J_rownnz[t], i) for i, t in enumerate(self.ids)]
        entries = [np.arange(m.ten_J_rowadr[t], m.ten_J_rowadr[t] + m.ten_J_rownnz[t]) for t in self.ids]
        self.j_rows, self.j_entries = np.concatenate(rows), np.concatenate(entries)
        self.j_cols = m.ten_J_colind[self.j_entries]

    def tension(self, length, velocity, laws: _Laws) -> np.ndarray:
        """Muscle tensions (B, M) [N] from tendon lengths [m] and velocities [m/s] (B, M)."""
        delta = length - laws.rest_m
        taut = delta > 0.0
        with np.errstate(over="ignore", invalid="ignore"):  # a blow-up is reported as UNSTABLE, not warned
            grow = np.exp(self.alpha * np.where(taut, delta, 0.0))
            spring = self.k * (grow - 1.0)
            if self.params.muscle_damping_s > 0:  # beta * dphi/ddelta * dl/dt while taut
                spring += (self.params.muscle_damping_s * self.alpha * self.k) * (taut * grow) * velocity
            return np.minimum(np.maximum(np.where(laws.spring, spring, laws.f_const_n), 0.0), laws.f_cap_n)

    def stiffness(self, length, laws: _Laws) -> np.ndarray:
        """d tension / d length (B, M) [N/m] of the springs as ``tension`` pulls them (0 where slack, where the tension
        is a constant or clipped at 0 or at its cap): the stiffness the step integrates implicitly."""
        delta = length - laws.rest_m
        with np.errstate(over="ignore", invalid="ignore"):
            slope = self.alpha * self.k * np.exp(self.alpha * np.where(delta > 0.0, delta, 0.0))
        return np.where(laws.spring & (delta > 0.0), slope, 0.0)

    @np.errstate(invalid="ignore", over="ignore")
    def step(self, datas, laws: _Laws) -> tuple[np.ndarray, np.ndarray]:
        """One lockstep step: state -> tensions -> qfrc_applied -> integrate -> back on the couplings.

        Returns the tensions (B, M) and a (B,) mask of blown-up cases (a muscle/damping joint force above
        ``max_torque_nm``, or NaN), which are left unstepped so MuJoCo never sees (and prints) the blow-up.
        """
        m = self.m
        mass = np.zeros((len(datas), m.nv, m.nv))
        for d, mb in zip(datas, mass):
            mujoco.mj_step1(m, d)  # positions, tendons, mass matrix, bias and passive forces of the current state
            mujoco.mj_fullM(m, d, mb)
        length = np.array([d.ten_length for d in datas])[:, self.ids]
        f = self.tension(length, np.array([d.ten_velocity for d in datas])[:, self.ids], laws)
        jac = np.zeros((len(f), len(self.ids), m.nv))
        jac[:, self.j_rows, self.j_cols] = np.array([d.ten_J for d in datas])[:, self.j_entries]
        qvel = np.array([d.qvel for d in datas])
        pull = -(jac.transpose(0, 2, 1) @ f[..., None])[..., 0] - self.params.mass_damping_per_s * (
            mass @ qvel[..., None])[..., 0]
        applied = self._reduced_step(datas, mass, jac, pull, self.stiffness(length, laws))
        blown = ~(np.all(np.abs(pull) <= self.params.max_torque_nm, axis=1) & np.all(np.isfinite(applied), axis=1))
        for d, tau, skip in zip(datas, applied, blown):
            if not skip:
                d.qfrc_applied[:] = tau
                mujoco.mj_step2(m, d)  # limit constraints, Euler integration
        self._onto_couplings([d for d, skip in zip(datas, blown) if not skip])
        return f, blown

    @np.errstate(invalid="ignore", over="ignore")  # a blow-up is reported as UNSTABLE, not warned
    def _reduced_step(self, datas, mass, jac, pull, stiffness) -> np.ndarray:
        """qfrc_applied (B, nv) that gives every joint the acceleration of the free joints' linearly implicit Euler
        step, followers exactly on their couplings (so MuJoCo's integration of it is that step).

        In the free joints q (``E = dq_full/dq``): ``(M_r + dt D_r + dt^2 K_r) dqdot = dt (F_r - dt K_r qdot)`` with
        ``M_r = E^T M E``, the muscles' stiffness ``K_r = G^T diag(dtension/dlength) G`` (``G = J_ten E``), the damping
        ``D_r = muscle_damping_s K_r + mass_damping_per_s M_r + E^T diag(joint damping) E`` and ``F_r`` every force at
        the current state through E. The rest posture is where ``F_r = 0``: the oracle's equilibrium, exactly."""
        p, jm, dt = self.params, self.joint_map, self.m.opt.timestep
        qpos, qvel = np.array([d.qpos for d in datas]), np.array([d.qvel for d in datas])
        q, qdot = qpos[:, jm.free], qvel[:, jm.free]
        e = jm.tangent(q, qpos)  # (B, nv, N)
        drift = jm.tangent_rate(q, qdot, qpos)  # (B, nv): followers' acceleration at zero free acceleration
        smooth = np.array([d.qfrc_passive for d in datas]) - np.array([d.qfrc_bias for d in datas])  # gravity, springs
        force = pull + smooth - self.joint_damping * qvel - (mass @ drift[..., None])[..., 0]
        e_t = e.transpose(0, 2, 1)
        mass_r = e_t @ mass @ e
        g = jac @ e
        stiff_r = (g.transpose(0, 2, 1) * stiffness[:, None, :]) @ g
        damp_r = (p.muscle_damping_s * stiff_r + p.mass_damping_per_s * mass_r
                  + e_t @ (self.joint_damping[:, None] * e))
        rhs = dt * (e_t @ force[..., None] - dt * stiff_r @ qdot[..., None])
        qddot = solve_or_nan(mass_r + dt * damp_r + dt * dt * stiff_r, rhs) / dt
        accel = (e @ qddot)[..., 0] + drift
        return (mass @ accel[..., None])[..., 0] - smooth

    def _onto_couplings(self, datas):
        """Every joint back on the couplings and locks: followers and locked joints from the free joints' positions
        and velocities (MuJoCo's Euler step leaves them off by the limit constraints' share and by rounding)."""
        if self.joint_map.identity or not datas:
            return
        jm = self.joint_map
        qpos, qvel = np.array([d.qpos for d in datas]), np.array([d.qvel for d in datas])
        full = jm.full_q(qpos[:, jm.free])
        speed = np.einsum("bin,bn->bi", jm.tangent(qpos[:, jm.free], full), qvel[:, jm.free])
        for d, pos, vel in zip(datas, full, speed):
            d.qpos[:], d.qvel[:] = pos, vel

    def verdict(self, datas) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(status (B,) with -1 = keep going, qpos (B, N), qvel (B, N)) of the current states."""
        p, bad = self.params, int(mujoco.mjtWarning.mjWARN_BADQACC)
        qpos, qvel = np.array([d.qpos for d in datas]), np.array([d.qvel for d in datas])
        free = self.joint_map.free
        qacc = np.array([d.qacc for d in datas])[:, free]  # followers chatter on their stiff constraint
        flagged = np.array([d.warning[bad].number > 0 for d in datas])
        finite = np.all(np.isfinite(qpos) & np.isfinite(qvel), axis=1)
        with np.errstate(invalid="ignore"):
            speed, accel = np.max(np.abs(qvel[:, free]), axis=1), np.max(np.abs(qacc), axis=1)
            rest = (speed < p.qvel_tol_rad_s) & (accel < p.qacc_tol_rad_s2)
            unstable = flagged | ~finite | ~(speed <= p.max_qvel_rad_s)
        status = np.where(rest, int(SettleStatus.SETTLED), -1)
        return np.where(unstable, int(SettleStatus.UNSTABLE), status), qpos[:, free], qvel[:, free]

    def start(self, q_ref) -> list:
        """One MjData per case (reused across chunks: a fresh MjData is costly), reset to q_ref at rest."""
        while len(self.pool) < len(q_ref):
            self.pool.append(mujoco.MjData(self.m))
        for d, q in zip(self.pool, self.joint_map.full_q(q_ref)):
            mujoco.mj_resetData(self.m, d)
            d.qpos[:] = q
        return self.pool[:len(q_ref)]

    def run(self, q_ref, laws: _Laws) -> SettleRun:
        """Simulate the cases (rows of q_ref and laws) in lockstep, dropping each one when it stops."""
        datas = self.start(q_ref)
        out = SettleRun(q_ref.copy(), np.zeros_like(q_ref), np.full(laws.rest_m.shape, np.nan),
                     np.full(len(q_ref), int(SettleStatus.NOT_SETTLED), np.int8), np.zeros(len(q_ref)))
        active = np.arange(len(q_ref))
        n_steps = max(1, int(round(self.params.max_time_s / self.m.opt.timestep)))
        every, running = int(self.params.check_every_steps), (datas, laws)
        for i in range(n_steps):
            f, blown = self.step(*running)
            check = (i + 1) % every == 0 or i + 1 == n_steps
            if check or blown.any():
                active = self._record(running[0], active, f, blown, out) if check else self._drop(
                    running[0], active, blown, out)
                if active.size == 0:
                    break
                running = ([datas[b] for b in active], laws.take(active))
        return out

    @staticmethod
    def _drop(datas, active, blown, out: SettleRun) -> np.ndarray:
        """Between checks: only the blown-up cases stop (UNSTABLE, last checked state kept); the others are not
        looked at, so where a case runs (with or without a blow-up beside it) never changes its result."""
        gone = np.flatnonzero(blown)
        out.status[active[gone]] = SettleStatus.UNSTABLE
        out.time_s[active[gone]] = [datas[b].time for b in gone]
        return active[~blown]

    def _record(self, datas, active, f, blown, out: SettleRun) -> np.ndarray:
        """Store the state of the running cases (``datas`` = rows ``active``); returns those still running."""
        status, qpos, qvel = self.verdict(datas)
        status[blown] = SettleStatus.UNSTABLE
        ok = status != SettleStatus.UNSTABLE  # an unstable case keeps its last finite state
        out.q[active[ok]], out.qvel[active[ok]], out.f[active[ok]] = qpos[ok], qvel[ok], f[ok]
        out.time_s[active] = [d.time for d in datas]
        done = status >= 0
        out.status[active[done]] = status[done]
        return active[~done]


def solve_or_nan(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``solve(a, b)`` per case (B, N, N) x (B, N, 1); NaN rows where a case's system is not finite or singular (a
    spring stretched far past its range overflows): the step reports that case as blown up, the others go on."""
    bad = ~(np.isfinite(a).all(axis=(1, 2)) & np.isfinite(b).all(axis=(1, 2)))
    a, b = np.where(bad[:, None, None], np.eye(a.shape[1]), a), np.where(bad[:, None, None], 0.0, b)
    try:
        out = np.linalg.solve(a, b)
    except np.linalg.LinAlgError:  # an overflowed but finite system: find it case by case (rare)
        out = np.stack([_solve_one(ai, bi) for ai, bi in zip(a, b)])
    out[bad] = np.nan
    return out


def _solve_one(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    try:
        return np.linalg.solve(a, b)
    except np.linalg.LinAlgError:
        return np.full_like(b, np.nan)
