"""A motion simulated in MuJoCo: computed muscle control (closed loop) and the inverse dynamics' controls played open
loop, each against the reference.

MuJoCo runs the body with its muscle actuators (``statics.muscles.actuated_model``), contacts off, locks and couplings
held as ``statics.check`` holds them; a cut muscle's actuator is held at zero force, a weakened one's within its
``f_max_n``. Jams and bands bound a motor through the robot's spring, which MuJoCo's muscles do not have: refused here.

Computed muscle control, each control step ``h`` (a multiple of the model's timestep): from the state ``(q, qvel)``
and MuJoCo's acceleration the state one step ahead is predicted (MuJoCo's semi-implicit Euler), the acceleration
wanted there is the reference's plus PD feedback ``kp (q_ref - q) + kd (qvel_ref - qvel)``, ``statics.dynamics``
gives the activations that make it, and the control is the excitation that MuJoCo's activation dynamics turn the
current activations into them over the step (a muscle's force follows its activation, MuJoCo's state, one step late:
hence the prediction). A frame without a solution holds the activations. The reference between the motion's frames
is interpolated linearly (positions, velocities, accelerations alike). numpy and MuJoCo; never imports Lightning.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import mujoco
import numpy as np

from ..errors import BodySchemaInputError
from .activation import excitation
from .check import MuJoCoBody
from .dynamics import inverse_dynamics, solve_motion
from .optimize import StaticBody

KP_PER_S2, KD_PER_S = 400.0, 40.0  # PD gains of computed muscle control: critically damped, 20 rad/s bandwidth


@dataclass
class TrackingReport:
    """``t`` (K,) [s] control steps; ``q_ref``, ``q_tracked``, ``q_open_loop`` (K, N) the reference, computed muscle
    control's and the open-loop rollout's free joints; ``solve_s`` (K,) each step's solve; ``failed`` (K,) steps whose
    solve had no answer (activations held); ``clipped`` (K,) steps with some excitation clipped to [0, 1]."""

    t: np.ndarray
    q_ref: np.ndarray
    q_tracked: np.ndarray
    q_open_loop: np.ndarray
    solve_s: np.ndarray
    failed: np.ndarray
    clipped: np.ndarray

    @staticmethod
    def _rms(q, ref):
        return float(np.sqrt(np.mean((q - ref) ** 2)))

    @property
    def rms_rad(self) -> float:
        """RMS over every step and free joint of computed muscle control's error [rad]."""
        return self._rms(self.q_tracked, self.q_ref)

    @property
    def open_loop_rms_rad(self) -> float:
        return self._rms(self.q_open_loop, self.q_ref)

    def summary(self) -> str:
        step = float(np.median(np.diff(self.t)))
        return (f"tracking over {self.t[-1] - self.t[0]:.3g} s at a {1e3 * step:.3g} ms control step: RMS "
                f"{self.rms_rad:.2e} rad, max {np.abs(self.q_tracked - self.q_ref).max():.2e} rad; open loop drift "
                f"RMS {self.open_loop_rms_rad:.2e} rad, max {np.abs(self.q_open_loop - self.q_ref).max():.2e} rad; "
                f"solve per step median {1e3 * np.median(self.solve_s):.3g} ms (p95 "
                f"{1e3 * np.quantile(self.solve_s, 0.95):.3g}); {int(self.failed.sum())} steps without a solution, "
                f"{int(self.clipped.sum())} with an excitation clipped")


def resample(t, *arrays, step_s: float):
    """The control steps ``t0, t0 + step, ...`` up to the last frame, and each (B, N) array linearly interpolated."""
    grid = t[0] + step_s * np.arange(int(np.floor((t[-1] - t[0]) / step_s + 1e-9)) + 1)
    return grid, [np.stack([np.interp(grid, t, a[:, j]) for j in range(a.shape[1])], axis=1) for a in arrays]


class _Simulation(MuJoCoBody):
    """The MuJoCo body of ``statics.check`` with the faults of one case held by the actuators' force ranges."""

    def __init__(self, body: StaticBody, faults, control_step_s: float):
        super().__init__(body)
        if faults.fix.any() or faults.band.any():
            raise BodySchemaInputError("tracking simulates cut and weakened muscles; a jammed motor or a length "
                                       "band bounds the robot's spring, which MuJoCo's muscles do not have")
        self.substeps = int(round(control_step_s / self.m.opt.timestep))
        if self.substeps < 1 or abs(self.substeps * self.m.opt.timestep - control_step_s) > 1e-12:
            raise BodySchemaInputError(f"control step {control_step_s} s: give a multiple of the model's timestep "
                                       f"{self.m.opt.timestep} s")
        self.weak = faults.weak[0]
        self.f_max = np.where(self.weak, faults.f_max_n[0] if faults.f_max_n is not None else 0.0, 0.0)
        self.cut, self.gear = faults.cut[0], body.curves.gear

    def reset(self, q, qvel, activation):
        """Start at free-joint ``q``, ``qvel`` with activations ``activation``."""
        self.start(q, activation, self.cut)
        weak = self.weak & ~self.cut
        self.m.actuator_forcelimited[:] = self.cut | weak
        self.m.actuator_forcerange[:, 0] = np.where(weak, -self.f_max / self.gear, 0.0)
        jm = self.model.joint_map
        self.d.qvel[:] = jm.tangent(q[None])[0] @ qvel
        mujoco.mj_forward(self.m, self.d)

    def state(self):
        free = self.model.joint_map.free
        return self.d.qpos[free].copy(), self.d.qvel[free].copy(), self.d.qacc[free].copy(), self.d.act.copy()

    def step(self, control):
        self.d.ctrl[:] = control
        for _ in range(self.substeps):
            mujoco.mj_step(self.m, self.d)
            self.hold_locks()
        mujoco.mj_forward(self.m, self.d)


def _closed_loop(body, sim, grid, ref, faults, h, options):
    """Computed muscle control along the reference; returns the tracked q, the solve times, failed, clipped."""
    q_ref, qvel_ref, qacc_ref = ref
    lo, hi = body.model.q_range.T
    tracked, solve_s = np.empty_like(q_ref), np.empty(len(grid))
    failed, clipped = np.zeros(len(grid), bool), np.zeros(len(grid), bool)
    for k in range(len(grid)):
        q, qvel, qacc, act = sim.state()
        tracked[k] = q
        nxt = min(k + 1, len(grid) - 1)
        start = time.perf_counter()
        qvel_next = qvel + h * qacc
        q_next = np.clip(q + h * qvel_next, lo, hi)
        wanted = qacc_ref[nxt] + options["kp"] * (q_ref[nxt] - q_next) + options["kd"] * (qvel_ref[nxt] - qvel_next)
        result = solve_motion(body, q_next[None], qvel_next[None], wanted[None], faults,
                              residual_dofs=options.get("residual_dofs"))
        target = result.activation
        failed[k] = not np.isfinite(target).all()
        control, clip = excitation(act[None], act[None] if failed[k] else target, body.curves.dynprm,
                                   np.array([h]), sim.m.opt.timestep)
        solve_s[k], clipped[k] = time.perf_counter() - start, clip.any()
        sim.step(control[0])
    return tracked, solve_s, failed, clipped


def _open_loop(body, sim, grid, ref, faults, options):
    """The inverse dynamics' controls of the whole reference played from its first state; returns q per step."""
    result = inverse_dynamics(body, *ref, faults=faults, residual_dofs=options.get("residual_dofs"), t=grid)
    control = result.control.copy()
    for k in range(1, len(control)):  # a step without an answer holds the previous control
        control[k] = np.where(np.isnan(control[k]), control[k - 1], control[k])
    first = np.nan_to_num(result.activation[0])
    sim.reset(ref[0][0], ref[1][0], first)
    out = np.empty_like(ref[0])
    for k in range(len(grid)):
        out[k] = sim.state()[0]
        sim.step(np.nan_to_num(control[k], nan=0.0))
    return out


def track_motion(body: StaticBody, t, q, qvel, qacc, faults=None, control_step_s=None, kp: float = KP_PER_S2,
                 kd: float = KD_PER_S, residual_dofs=None) -> TrackingReport:
    """Simulate the motion (frames ``t`` (B,) [s], ``q``, ``qvel``, ``qacc`` (B, N)) in MuJoCo by computed muscle
    control and open loop (module docstring); ``control_step_s`` default the model's timestep. Residual actuators
    are solved for but not simulated (MuJoCo has none): give ``residual_dofs`` only to see where they would act."""
    if body.curves is None:
        raise BodySchemaInputError("tracking needs MuJoCo <muscle> actuators on every muscle")
    faults = body.fault_batch(faults, 1)
    h = float(control_step_s or body.model.mj_model.opt.timestep)
    grid, ref = resample(np.asarray(t, float), q, qvel, qacc, step_s=h)
    sim = _Simulation(body, faults, h)
    options = {"kp": kp, "kd": kd, "residual_dofs": residual_dofs}
    start = inverse_dynamics(body, ref[0][:1], ref[1][:1], ref[2][:1], faults=faults)
    sim.reset(ref[0][0], ref[1][0], np.nan_to_num(start.activation[0]))
    tracked, solve_s, failed, clipped = _closed_loop(body, sim, grid, ref, faults, h, options)
    open_loop = _open_loop(body, sim, grid, ref, faults, options)
    return TrackingReport(grid, ref[0], tracked, open_loop, solve_s, failed, clipped)
