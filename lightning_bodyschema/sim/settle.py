"""Physical settle check: drop each command into a MuJoCo simulation and let the arm come to rest.

The forward solver (``forward_solver.solve_posture``) finds the posture a command *should* realize by
optimisation. This module asks the physics instead: start at ``q_ref`` with zero velocity, let every
muscle pull as its command says, and simulate until the arm is at rest. The rest posture
``q_settle`` and ``E_q_phys = ||q_settle - q_ref||`` [rad] are the physical counterpart of E_q.

Force model (one case = one MuJoCo rollout), muscle i with tendon length ``l_geo_i(q)``:

* ``mode="length"`` (default; a length-controlled motor, the paper's robot): the motor holds its
  winch at the commanded ``l_motor_i`` and the muscle is the exponential spring
  ``f_i = k (exp(alpha * max(0, l_geo_i - l_motor_i)) - 1)``. The command's ``f`` is *not* applied:
  it is only what the schema expects the spring to produce. ``f`` is checked for NaN and otherwise unused.
* ``mode="tension"``: a force-controlled motor; a healthy muscle pulls with the constant commanded
  ``max(f_i, 0)`` whatever its length (the winch takes up any slack). Constant forces add no
  stiffness, so only gravity restores the arm: small tension errors move it far and slowly.
* cut muscles: absent (no force) in both modes.
* jammed motors (default ``jam="one_sided"``): the paper's constraint ``l_motor_j <= l_fixed_j`` read
  as a ratchet: the wire can be taken in but not paid out past l_fixed, so the rest length is
  ``min(l_motor_j, l_fixed_j)``. This is the reading of the adaptation loss and of
  ``evaluation.feasibility.check_feasible`` (``jam_model="one_sided"``): its oracle commands settle exactly at
  q_ref. ``jam="immobile"``: the winch cannot move at all, rest length ``l_fixed_j`` whatever the command
  says (then only ``jam_model="immobile"`` oracle commands settle at q_ref).
* weakened muscles (``FaultCases.f_max``): the tension saturates at f_max' (the motor slips, both modes).
* banded motors (``FaultCases.l_band``, length mode): the winch stops at its band, rest length
  ``clip(l_motor, lo, hi)`` (after the jam's ``min``); in tension mode the band is not modelled.

Tensions act on the joints as ``-J_ten^T f`` with MuJoCo's own ``ten_length`` / ``ten_J`` (sparse in MuJoCo 4,
scattered into a dense (M, nv) buffer) of the current state: each step is ``mj_step1`` (positions, tendons, mass
matrix, gravity and passive forces), the step below in numpy, ``mj_step2`` (joint-limit constraints, integration).
No global MuJoCo callback is installed.

Integration (``_Simulator._reduced_step``), in the free joints q of ``sim/joints.py`` (``E = d q_full / dq``):

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

Stopping: every ``check_every_steps`` steps, SETTLED when ``max|qvel| < qvel_tol_rad_s`` and
``max|qacc| < qacc_tol_rad_s2`` over the free joints (followers and locked joints are not coordinates of
q) (the acceleration test rejects the turning point of an oscillation, where the velocity is momentarily zero; with
the defaults the torque left unbalanced at rest is about ``M_r qacc_tol + a M_r qvel_tol``: the rest posture is within
~3e-5 rad of the true equilibrium on the paper arm, further on soft bodies, that torque over the softest stiffness); UNSTABLE when a joint force exceeds ``max_torque_nm`` or is NaN (checked every step,
before MuJoCo integrates it, so MuJoCo never prints its own blow-up warning), the state is non-finite,
or ``max|qvel| > max_qvel_rad_s``; NOT_SETTLED when ``max_time_s`` runs out. A case at rest more than
``limit_tol_rad`` outside the joint range is BEYOND_LIMIT: tensions far above f_max (a wire stretched by
centimetres) overpower MuJoCo's soft limit, and that rest posture is not physical. An exact but
unstable equilibrium at q_ref is reported as settled: the simulation starts without a perturbation.

Couplings and locks (``<equality joint>``, sim/joints.py): q_ref and q_settle are the free joints; the
simulation runs on every joint, held exactly on the couplings and locks: MuJoCo's equality constraints are off
(``_hold_exactly``), the step gives each follower the acceleration its polynomial prescribes and a locked joint none,
and after MuJoCo integrates, followers and locked joints are put back from the free joints' positions and velocities
(``_onto_couplings``). Measured on myoLegs (knees: patella and tibia translations and rotations coupled to the knee
angle), why: MuJoCo's constraints are soft by construction (the previous near-hard ones left followers 0.2-0.3 mm off
their polynomials at a 2 ms step, shrinking as dt^2), and the legs' softest directions (0.7 N m/rad) turned that
into 0.01-0.02 rad: exact equilibria did not rest where they are.

Batching: MuJoCo steps one MjData at a time and the tension law needs a per-step computation that
``mujoco.rollout`` cannot express (it would need a global Python callback). So the cases of a chunk
(``chunk_size``, one MjData each, reused across chunks) advance in lockstep: ``mj_step1`` per case,
tensions and joint forces for the whole chunk in numpy, ``mj_step2`` per case; a case leaves the
chunk when it stops (costs: BENCHMARKS.md, settle check). On models with
``THREADS_MIN_DOF`` or more joints the chunks run on threads (MuJoCo releases the GIL while it steps), each
with its own model copy and MjData.
A case's result never depends on the chunk it ran in (its checks fall on the same steps wherever it runs,
and a case blowing up records only itself), so chunking and threads change no byte of the result.

numpy and MuJoCo only; never imports Lightning or torch.
"""
from __future__ import annotations

import copy
import enum
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import NamedTuple

import mujoco
import numpy as np

from ..errors import BodySchemaInputError
from .model import MusculoskeletalModel
from .settle_inputs import _Laws, _check_inputs, _force_laws, _is_cases
from .spring import SpringParams

MODES = ("length", "tension")
# statics.check's MuJoCo check holds locks and couplings with MuJoCo (_hold_couplings_and_locks); settle holds them
# exactly (_hold_exactly) and keeps these only for that check:
LOCK_ARMATURE = 1e6  # [kg m^2] added to a locked joint: it does not accelerate (see _hold_couplings_and_locks)
COUPLING_IMPEDANCE = 0.9999  # MuJoCo solimp d of a coupling: near-hard (MuJoCo's largest d)
SOLVER_TOLERANCE = 1e-12  # MuJoCo opt.tolerance: constraint (limit) forces solved to convergence
JAM_MODES = ("one_sided", "immobile")  # the same names as evaluation.feasibility.JAM_MODELS


class SettleStatus(enum.IntEnum):
    """How the simulation of one case ended (stored as ints in ``SettleResult.status``)."""

    SETTLED = 0  # came to rest: |qvel| and |qacc| below their tolerances
    NOT_SETTLED = 1  # still moving when max_time_s ran out
    UNSTABLE = 2  # the state blew up (non-finite, MuJoCo bad qacc, or |qvel| > max_qvel_rad_s)
    BEYOND_LIMIT = 3  # came to rest, but more than limit_tol_rad outside the joint range: not physical
    NONFINITE_COMMAND = 4  # l_motor or f has NaN/inf: not simulated, q_settle is NaN


@dataclass(frozen=True)
class SettleParams:
    """Simulation settings; see the module docstring for why these defaults."""

    mode: str = "length"  # "length": motors hold l_motor (spring); "tension": constant commanded f
    jam: str = "one_sided"  # "one_sided": jammed rest length min(l_motor, l_fixed) (paper); "immobile": l_fixed
    max_time_s: float = 3.0  # simulated time limit per case [s]
    timestep_s: float | None = None  # None: the model's timestep [s]
    mass_damping_per_s: float = 8.0  # a in -a M qdot [1/s]
    muscle_damping_s: float = 0.01  # beta in beta * dphi/ddelta * dl/dt [s]
    qvel_tol_rad_s: float = 1e-4  # at rest when max|qvel| is below this [rad/s] ...
    qacc_tol_rad_s2: float = 1e-3  # ... and max|qacc| below this [rad/s^2]
    max_qvel_rad_s: float = 100.0  # faster than this counts as UNSTABLE [rad/s]
    max_torque_nm: float = 1e6  # a larger muscle/damping joint force counts as UNSTABLE [N m]
    check_every_steps: int = 10  # test for rest / blow-up every this many steps
    limit_tol_rad: float = 0.02  # a rest posture further outside the joint range is BEYOND_LIMIT [rad]
    chunk_size: int = 128  # cases stepped in lockstep (one MjData, ~0.5 MB, each)
    n_threads: int | None = None  # threads stepping chunks side by side (None: see THREADS_MIN_DOF)

    def __post_init__(self):
        if self.mode not in MODES:
            raise BodySchemaInputError(f"SettleParams.mode={self.mode!r}; use one of {list(MODES)}")
        if self.jam not in JAM_MODES:
            raise BodySchemaInputError(f"SettleParams.jam={self.jam!r}; use one of {list(JAM_MODES)}")
        positive = ["max_time_s", "qvel_tol_rad_s", "qacc_tol_rad_s2", "max_qvel_rad_s", "max_torque_nm",
                    "check_every_steps", "limit_tol_rad", "chunk_size"]
        positive += [] if self.timestep_s is None else ["timestep_s"]
        for name in positive:
            value = getattr(self, name)
            if not np.isfinite(value) or value <= 0:
                raise BodySchemaInputError(f"SettleParams.{name}={value!r} must be finite and > 0")
        for name in ("mass_damping_per_s", "muscle_damping_s"):
            value = getattr(self, name)
            if not np.isfinite(value) or value < 0:
                raise BodySchemaInputError(f"SettleParams.{name}={value!r} must be finite and >= 0")
        for name in ("check_every_steps", "chunk_size"):
            if int(getattr(self, name)) != getattr(self, name):
                raise BodySchemaInputError(f"SettleParams.{name}={getattr(self, name)!r} must be an integer")
        if self.n_threads is not None and (isinstance(self.n_threads, bool) or not isinstance(self.n_threads, int)
                                           or self.n_threads < 1):
            raise BodySchemaInputError(f"SettleParams.n_threads={self.n_threads!r} must be an integer >= 1 or None")


@dataclass
class SettleResult:
    """Batched settle output; prints nothing, like mujoco's ``minimize``.

    q_settle (B, N) rest posture [rad]; E_q_phys (B,) ``||q_settle - q_ref||`` [rad]; status (B,)
    ``SettleStatus`` ints; time_s (B,) simulated time when the case stopped [s]; qvel_rad_s (B, N)
    final joint velocity; f_settle_n (B, M) muscle tensions in the final state [N] (0 for cut muscles).
    Rows of NONFINITE_COMMAND cases are NaN (time_s 0). UNSTABLE rows hold the last state that passed a
    check (q_ref at rest, f NaN, if the case blew up before its first check) for diagnosis, and E_q_phys +inf.
    A NOT_SETTLED row holds the state at max_time_s, a body still moving: no rest posture (``unsettled``,
    ``E_q_rest``).
    """

    q_settle: np.ndarray
    E_q_phys: np.ndarray
    status: np.ndarray
    time_s: np.ndarray
    qvel_rad_s: np.ndarray
    f_settle_n: np.ndarray

    @property
    def settled(self) -> np.ndarray:
        """(B,) bool: the case came to rest."""
        return self.status == SettleStatus.SETTLED

    @property
    def unsettled(self) -> np.ndarray:
        """(B,) bool: simulated but never at rest (NOT_SETTLED: still moving at max_time_s; UNSTABLE: blew up). Its
        q_settle is no rest posture: a score counts these apart (``E_q_rest``), never as an E_q_phys."""
        return np.isin(self.status, (SettleStatus.NOT_SETTLED, SettleStatus.UNSTABLE))

    @property
    def E_q_rest(self) -> np.ndarray:
        """(B,) E_q_phys [rad] of the cases that came to rest (SETTLED, BEYOND_LIMIT), NaN elsewhere (``unsettled``
        and NONFINITE_COMMAND): what medians of rest postures take, with ``unsettled.sum()`` reported beside."""
        return np.where(self.unsettled, np.nan, self.E_q_phys)

    @property
    def status_names(self) -> list[str]:
        return [SettleStatus(int(s)).name for s in self.status]


# ---------------------------------------------------------------------------- simulation
class _Final(NamedTuple):
    """Per-case outcome of one lockstep run (arrays over the cases of the run)."""

    q: np.ndarray  # (B, N) last finite posture seen at a check [rad]
    qvel: np.ndarray  # (B, N) [rad/s]
    f: np.ndarray  # (B, M) tensions of that state [N]
    status: np.ndarray  # (B,) SettleStatus ints
    time_s: np.ndarray  # (B,) simulated time at the stop [s]


class _Simulator:
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
        polynomials prescribe, ``_project`` puts positions and velocities back on it after MuJoCo integrates)."""
        m, jm = self.m, self.joint_map
        self._locked = np.array(sorted(jm.locked), dtype=int)
        self._locked_values = np.array([jm.locked[j] for j in self._locked])
        for e in range(m.neq):
            if int(m.eq_type[e]) == int(mujoco.mjtEq.mjEQ_JOINT):
                m.eq_active0[e] = 0
        # a follower's range is its leader's (JointMap.free_range narrows the free joints' ranges to keep followers
        # inside theirs); its own limit would only push where that narrowing rounds (0.2 mrad on myoLegs' knee)
        m.jnt_limited[[j for j, _, _ in jm.deps]] = 0

    def _hold_couplings_and_locks(self):
        """(``statics.check``'s MuJoCo check; the settle simulation holds them exactly, ``_hold_exactly``.)
        Locks: the equality is switched off and the joint gets a huge armature, so it does not accelerate while
        the rest of the arm moves exactly as if it were welded (M_jj -> inf), then is reset each step. Couplings:
        MuJoCo's equality constraint made stiff (time constant 2 steps, impedance COUPLING_IMPEDANCE): at rest a
        follower misses its polynomial by ~(1 - d) a / (d k), and its constraint force is the one the arm needs."""
        m, jm = self.m, self.joint_map
        self._locked = np.array(sorted(jm.locked), dtype=int)
        self._locked_values = np.array([jm.locked[j] for j in self._locked])
        m.dof_armature[self._locked] += LOCK_ARMATURE
        for e in range(m.neq):
            if int(m.eq_type[e]) != int(mujoco.mjtEq.mjEQ_JOINT):
                continue
            if m.eq_obj2id[e] < 0:
                m.eq_active0[e] = 0
            else:
                m.eq_solref[e] = [2.0 * m.opt.timestep, 1.0]
                m.eq_solimp[e, :2] = COUPLING_IMPEDANCE

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
        m, p, jm, dt = self.m, self.params, self.joint_map, self.m.opt.timestep
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
        qddot = _solve_or_nan(mass_r + dt * damp_r + dt * dt * stiff_r, rhs) / dt
        accel = (e @ qddot)[..., 0] + drift
        return (mass @ accel[..., None])[..., 0] - smooth

    def _project(self, datas):
        """Locked joints back at their value and at rest (``statics.check``'s MuJoCo check, with
        ``_hold_couplings_and_locks``)."""
        for d in datas:
            d.qpos[self._locked], d.qvel[self._locked] = self._locked_values, 0.0

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

    def _start(self, q_ref) -> list:
        """One MjData per case (reused across chunks: a fresh MjData is costly), reset to q_ref at rest."""
        while len(self.pool) < len(q_ref):
            self.pool.append(mujoco.MjData(self.m))
        for d, q in zip(self.pool, self.joint_map.full_q(q_ref)):
            mujoco.mj_resetData(self.m, d)
            d.qpos[:] = q
        return self.pool[:len(q_ref)]

    def run(self, q_ref, laws: _Laws) -> _Final:
        """Simulate the cases (rows of q_ref and laws) in lockstep, dropping each one when it stops."""
        datas = self._start(q_ref)
        out = _Final(q_ref.copy(), np.zeros_like(q_ref), np.full(laws.rest_m.shape, np.nan),
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
    def _drop(datas, active, blown, out: _Final) -> np.ndarray:
        """Between checks: only the blown-up cases stop (UNSTABLE, last checked state kept); the others are not
        looked at, so where a case runs (with or without a blow-up beside it) never changes its result."""
        gone = np.flatnonzero(blown)
        out.status[active[gone]] = SettleStatus.UNSTABLE
        out.time_s[active[gone]] = [datas[b].time for b in gone]
        return active[~blown]

    def _record(self, datas, active, f, blown, out: _Final) -> np.ndarray:
        """Store the state of the running cases (``datas`` = rows ``active``); returns those still running."""
        status, qpos, qvel = self.verdict(datas)
        status[blown] = SettleStatus.UNSTABLE
        ok = status != SettleStatus.UNSTABLE  # an unstable case keeps its last finite state
        out.q[active[ok]], out.qvel[active[ok]], out.f[active[ok]] = qpos[ok], qvel[ok], f[ok]
        out.time_s[active] = [d.time for d in datas]
        done = status >= 0
        out.status[active[done]] = status[done]
        return active[~done]


def _solve_or_nan(a: np.ndarray, b: np.ndarray) -> np.ndarray:
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


def _mark_beyond_limits(out: SettleResult, q_range, tol_rad: float):
    """SETTLED cases resting more than tol_rad outside the joint range become BEYOND_LIMIT."""
    lo, hi = q_range[:, 0], q_range[:, 1]
    with np.errstate(invalid="ignore"):
        beyond = np.max(np.maximum(lo - out.q_settle, out.q_settle - hi), axis=1) > tol_rad
    out.status[beyond & out.settled] = SettleStatus.BEYOND_LIMIT


# n_threads=None: threads only for models with at least this many degrees of freedom: a small arm's step is too
# short to hand between threads, a large model's is not (BENCHMARKS.md "Settle check on threads").
THREADS_MIN_DOF = 10


def _usable_cpus() -> int:
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def _run_chunks(model, spring, params: SettleParams, q_ref, laws: _Laws, idx: np.ndarray):
    """(rows, _Final) of every chunk of the cases ``idx``: chunks of at most ``chunk_size``, at least one per
    thread, each thread with its own simulator."""
    if idx.size == 0:
        return []
    threads = params.n_threads or (_usable_cpus() if model.mj_model.nv >= THREADS_MIN_DOF else 1)
    threads = max(1, min(threads, idx.size))
    size = min(int(params.chunk_size), -(-idx.size // threads))
    chunks = [idx[start:start + size] for start in range(0, idx.size, size)]
    threads = min(threads, len(chunks))
    sims = [_Simulator(model, spring, params) for _ in range(threads)]

    def run(k):  # chunk k on simulator k % threads: no two running chunks share MjData
        return chunks[k], sims[k % threads].run(q_ref[chunks[k]], laws.take(chunks[k]))
    if threads == 1:
        return [run(k) for k in range(len(chunks))]
    with ThreadPoolExecutor(threads) as pool:
        return [res for wave in range(0, len(chunks), threads)
                for res in pool.map(run, range(wave, min(wave + threads, len(chunks))))]


# ---------------------------------------------------------------------------- public API
def settle(model: MusculoskeletalModel, l_motor, f, cases_or_q_ref, cut=None, fix=None, l_fixed=None,
           spring: SpringParams = SpringParams(), params: SettleParams = SettleParams()) -> SettleResult:
    """Simulate each command (l_motor [m], f [N]) (B, M) from q_ref at rest until the arm stops.

    ``cases_or_q_ref`` is a case batch (``evaluation.FaultCases`` or any object with those arrays) (its cut / fix / l_fixed, and f_max / l_band, are used) or q_ref (B, N) [rad]
    with optional ``cut``, ``fix`` (B, M) bool and ``l_fixed`` (B, M) [m] (NaN where not jammed);
    without them every muscle is healthy. Cases with a non-finite command are not simulated
    (status NONFINITE_COMMAND, NaN rows). The others run in lockstep chunks of ``params.chunk_size``.
    """
    q_ref, l_motor, f, cut, fix, l_fixed, finite = _check_inputs(model, l_motor, f, cases_or_q_ref,
                                                                  cut, fix, l_fixed)
    batch, n_j, n_m = q_ref.shape[0], model.n_joints, model.n_muscles
    out = SettleResult(np.full((batch, n_j), np.nan), np.full(batch, np.nan),
                       np.full(batch, int(SettleStatus.NONFINITE_COMMAND), np.int8), np.zeros(batch),
                       np.full((batch, n_j), np.nan), np.full((batch, n_m), np.nan))
    new_faults = ({"f_max": cases_or_q_ref.f_max, "l_band": cases_or_q_ref.l_band}
                  if _is_cases(cases_or_q_ref) else {})  # weakened / banded: only through FaultCases
    laws = _force_laws(l_motor, f, cut, fix, l_fixed, params, **new_faults)
    for rows, res in _run_chunks(model, spring, params, q_ref, laws, np.flatnonzero(finite)):
        out.q_settle[rows], out.qvel_rad_s[rows], out.f_settle_n[rows] = res.q, res.qvel, res.f
        out.status[rows], out.time_s[rows] = res.status, res.time_s
    out.E_q_phys = np.linalg.norm(out.q_settle - q_ref, axis=1)
    # a blown-up case rests nowhere: its last checked state (possibly q_ref itself) must not read as a small
    # error, so its E_q_phys is +inf (medians then count it as the worst case; JSON writes null)
    out.E_q_phys[out.status == SettleStatus.UNSTABLE] = np.inf
    _mark_beyond_limits(out, model.q_range, params.limit_tol_rad)
    return out
