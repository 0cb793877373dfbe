"""The fault drill: a robot holds a posture in MuJoCo on its schema's healthy command, a fault strikes, the monitor
reads the simulated sensors, and on a declared diagnosis the adapter re-commands.

The physics is ``sim.settle``'s (length-controlled motors and exponential springs, every fault kind, its damping and
joint handling), stepped in time instead of to rest. The sensors follow ``diagnosis.sensors``' model with Gaussian
noise, read every ``tick_s``. numpy and MuJoCo (and the schema handed in); never imports Lightning.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from ..faults import Faults
from ..sim.settle import SettleParams, SettleSimulator, settle
from ..sim.settle_inputs import _force_laws
from ..status import Status
from .noise import SensorNoise
from .result import HEALTHY
from .sensors import sensor_model


REST_S = 10.0  # the rest comparison's simulated time: a learned command drifts slowly along an arm's soft directions


@dataclass
class DrillSettings:
    """at_s: when the fault strikes [s]; seconds: the drill's length [s]; tick_s: the controller's period [s] (the
    monitor reads the sensors once a tick); window, confirm: the monitor's (``schema.monitor``)."""

    at_s: float = 1.0
    seconds: float = 4.0
    tick_s: float = 0.01
    window: int = 5
    confirm: int = 3


@dataclass
class DrillResult:
    """The trace (one row per tick) and what happened: ``detected_s`` (NaN: never), ``diagnosis`` (the declared
    one that the adapter re-commanded for, or None), ``adapted_status`` (that command's status, or None), posture
    errors [rad]."""

    t_s: np.ndarray
    q_rad: np.ndarray  # (T, N) joint readings
    l_m: np.ndarray  # (T, M) encoder readings
    f_n: np.ndarray  # (T, M) load-cell readings (NaN without a load cell)
    l_cmd_m: np.ndarray
    f_cmd_n: np.ndarray
    error_rad: np.ndarray  # (T,) |q_true - q_ref|
    detected_s: float
    diagnosis: object = None
    adapted_status: Optional[str] = None
    summary: dict = field(default_factory=dict)


def run_drill(schema, q_ref, faults: Faults, rng, noise: Optional[SensorNoise] = None,
              settings: DrillSettings = DrillSettings(), load_cells=None) -> DrillResult:
    """One drill at posture ``q_ref (N,)`` with ``faults`` (one row) striking at ``settings.at_s``."""
    noise = noise or SensorNoise()
    model, spring = schema.robot_model, schema.spring
    params = SettleParams()
    sim = SettleSimulator(model, spring, params)
    data = sim.start(np.asarray(q_ref, float)[None])
    l_cmd, f_cmd = (a[0] for a in schema.infer(np.asarray(q_ref, float)[None]))
    monitor = schema.monitor(noise, window=settings.window, confirm=settings.confirm, load_cells=load_cells)
    has_f = np.ones(model.n_muscles, bool) if load_cells is None else np.asarray(load_cells, bool)
    healthy = Faults.none(1, model.n_muscles)
    dt, rows, detected, adapted = sim.m.opt.timestep, [], np.nan, None
    per_tick = max(1, int(round(settings.tick_s / dt)))
    for step in range(int(round(settings.seconds / dt))):
        t = step * dt
        active = faults if t >= settings.at_s else healthy
        sim.step(data, _laws(l_cmd, f_cmd, active, params))
        if step % per_tick:
            continue
        q_true = data[0].qpos[sim.joint_map.free].copy()
        length = data[0].ten_length[sim.ids]
        motor, f = sensor_model(length[None], l_cmd[None], active, spring)
        reading = _noisy(q_true, motor[0], f[0], has_f, spring, noise, rng)
        diagnosis = monitor.update((l_cmd, f_cmd), reading)
        rows.append((t, *reading, l_cmd.copy(), f_cmd.copy(), float(np.linalg.norm(q_true - q_ref))))
        if np.isnan(detected) and monitor.declared_diagnosis is not None:
            detected = t
            # an ambiguous diagnosis: a command that holds under every candidate explanation
            adapted = schema.adapt(np.asarray(q_ref, float)[None], diagnosis.union_faults(0), check_physics=False)
            if adapted.status[0] == Status.OK:
                l_cmd, f_cmd = adapted.l_motor_m[0], adapted.f_n[0]
    cols = list(zip(*rows))
    return DrillResult(np.array(cols[0]), np.array(cols[1]), np.array(cols[2]), np.array(cols[3]), np.array(cols[4]),
                       np.array(cols[5]), np.array(cols[6]), detected,
                       monitor.declarations[0][1] if monitor.declarations else None,
                       None if adapted is None else str(adapted.status[0]))


def _laws(l_cmd, f_cmd, faults: Faults, params):
    return _force_laws(l_cmd[None], f_cmd[None], faults.cut, faults.fix, faults.l_fixed_m, params,
                       f_max=faults.f_max_n, l_band=faults.l_band_m)


def _noisy(q, motor, f, has_f, spring, noise: SensorNoise, rng):
    sigma_f = noise.f_frac * np.broadcast_to(np.asarray(spring.f_max_n, float), f.shape)
    return (q + noise.q_rad * rng.standard_normal(q.shape), motor + noise.l_m * rng.standard_normal(motor.shape),
            np.where(has_f, f + sigma_f * rng.standard_normal(f.shape), np.nan))


def rest_errors(schema, q_ref, faults: Faults, diagnosed: Optional[Faults]) -> dict:
    """Posture errors at rest [rad] (MuJoCo settle from q_ref under the true faults) of the healthy command, of the
    command adapted to the true faults, and of the one adapted to the diagnosed faults."""
    q = np.asarray(q_ref, float)[None]
    from ..evaluation.cases import FaultCases, condition_of

    cases = FaultCases(q, faults.cut, faults.fix, faults.l_fixed_m,
                       condition_of(faults.cut, faults.fix, faults.weak, faults.band), faults.f_max_n, faults.l_band_m)
    commands = {"healthy": schema.infer(q)}
    for name, given in (("true_faults", faults), ("diagnosed", diagnosed)):  # diagnosed: what the drill adapted to
        if given is not None:
            result = schema.adapt(q, given, check_physics=False)
            commands[name] = (result.l_motor_m, result.f_n) if result.status[0] == Status.OK else None
    out = {}
    for name, command in commands.items():
        if command is None:
            out[name] = None
            continue
        res = settle(schema.robot_model, command[0], command[1], cases, spring=schema.spring,
                     params=SettleParams(max_time_s=REST_S))
        out[name] = float(res.E_q_phys[0]) if res.settled[0] else None
    return out


def faulted_names(kinds: np.ndarray, muscles) -> dict:
    from .result import KINDS

    return {muscles[m]: KINDS[k] for m, k in enumerate(kinds) if k != HEALTHY}
