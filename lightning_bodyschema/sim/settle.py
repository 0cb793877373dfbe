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

Batching: MuJoCo steps one MjData at a time and the tension law needs a per-step computation that
``mujoco.rollout`` cannot express (it would need a global Python callback). So the cases of a chunk
(``chunk_size``, one MjData each, reused across chunks) advance in lockstep: ``mj_step1`` per case,
tensions and joint forces for the whole chunk in numpy, ``mj_step2`` per case; a case leaves the
chunk when it stops (costs: BENCHMARKS.md, settle check). On models with
``THREADS_MIN_DOF`` or more joints the chunks run on threads (MuJoCo releases the GIL while it steps), each
with its own model copy and MjData.
A case's result never depends on the chunk it ran in (its checks fall on the same steps wherever it runs,
and a case blowing up records only itself), so chunking and threads change no byte of the result.

The step, its integration and how couplings and locks are held: ``sim/settle_step.py``. numpy and MuJoCo only;
never imports Lightning or torch.
"""
from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from .model import MusculoskeletalModel
from .settle_inputs import _Laws, _check_inputs, _force_laws, _is_cases
from .settle_params import JAM_MODES, MODES, SettleParams, SettleResult, SettleStatus
from .settle_step import SOLVER_TOLERANCE, SettleSimulator, SettleRun, solve_or_nan
from .spring import SpringParams

__all__ = ["JAM_MODES", "MODES", "SOLVER_TOLERANCE", "SettleParams", "SettleResult", "SettleRun", "SettleSimulator",
           "SettleStatus", "settle", "solve_or_nan", "_force_laws"]


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
    """(rows, SettleRun) of every chunk of the cases ``idx``: chunks of at most ``chunk_size``, at least one per
    thread, each thread with its own simulator."""
    if idx.size == 0:
        return []
    threads = params.n_threads or (_usable_cpus() if model.mj_model.nv >= THREADS_MIN_DOF else 1)
    threads = max(1, min(threads, idx.size))
    size = min(int(params.chunk_size), -(-idx.size // threads))
    chunks = [idx[start:start + size] for start in range(0, idx.size, size)]
    threads = min(threads, len(chunks))
    sims = [SettleSimulator(model, spring, params) for _ in range(threads)]

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
