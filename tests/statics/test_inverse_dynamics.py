"""Inverse dynamics on the true body: MuJoCo's force-velocity curve and activation dynamics, the forward check in MuJoCo
(its acceleration is the requested one), an independent reference written with MuJoCo alone and scipy's SLSQP on the
user's own MyoSuite model, residual actuators, the torque form, the excitations MuJoCo integrates, bad input."""
from __future__ import annotations

import mujoco
import numpy as np
import pytest
from physics_checks import rounding_tol

from lightning_bodyschema.errors import BodySchemaInputError
from lightning_bodyschema.status import Status

pytest.importorskip("myo_sim")
from lightning_bodyschema.statics import StaticBody, actuated_model, inverse_dynamics, muscles_for_torque  # noqa: E402
from lightning_bodyschema.statics.activation import activation_rate, excitation  # noqa: E402
from lightning_bodyschema.statics.check import mujoco_motion_error  # noqa: E402

ELBOW = "myo:myoelbow_2dof"
# MuJoCo's forward acceleration against the requested one [rad/s^2]: the target. The accelerations here are
# ~10-60 rad/s^2 and M^-1 of the arm ~1e2 /(kg m^2): rounding in the torques (~1e-13 N m) leaves ~1e-10.
QACC_TOL = 1e-6


def sine_motion(body, seconds=1.0, step=0.002, speed=1.0):
    """Both joints swinging around mid-range (a quarter of the range each way), 0.7 and 1.1 Hz times ``speed``."""
    t = np.arange(0.0, seconds, step)
    lo, hi = body.model.q_range.T
    mid, amp, w = (lo + hi) / 2, (hi - lo) / 4, 2 * np.pi * speed * np.array([0.7, 1.1])
    phase = w * t[:, None]
    return t, mid + amp * np.sin(phase), amp * w * np.cos(phase), -amp * w ** 2 * np.sin(phase)


@pytest.fixture(scope="module")
def elbow():
    return StaticBody(ELBOW)


@pytest.fixture(scope="module")
def motion(elbow):
    return sine_motion(elbow)


def test_velocity_curve_is_mujocos(elbow):
    """FV s equals -gear mju_muscleGain at the tendon velocity, on every branch of the curve (shortening past vmax,
    shortening, lengthening, past fvmax)."""
    c, rng = elbow.curves, np.random.default_rng(2)
    lr = c.lengthrange_m
    length = (lr[:, 0] + (lr[:, 1] - lr[:, 0]) * rng.uniform(0.2, 0.8, (400, len(lr)))) / c.gear
    l0 = (lr[:, 1] - lr[:, 0]) / (c.gainprm[:, 1] - c.gainprm[:, 0])
    velocity = rng.uniform(-1.5, 1.0, (400, len(lr))) * l0 * c.gainprm[:, 6] / c.gear  # V in [-1.5, 1]
    s = c.affine(length)[0] * c.velocity_factor(velocity)
    gain = np.array([[mujoco.mju_muscleGain(x * c.gear[k], v * c.gear[k], lr[k], 1.0, c.gainprm[k])
                      for k, (x, v) in enumerate(zip(row, vrow))] for row, vrow in zip(length, velocity)])
    factor = c.velocity_factor(velocity)
    assert (factor == 0).any() and (factor == c.gainprm[0, 8]).any() and ((factor > 0) & (factor < 1)).any()
    np.testing.assert_allclose(s, -c.gear * gain, rtol=1e-12, atol=1e-9)


@pytest.mark.parametrize("tausmooth", [0.0, 0.2])
def test_activation_dynamics_is_mujocos(tausmooth):
    """act_dot equals mju_muscleDynamics (hard and smooth switch), and the excitation is its inverse over one step
    and over five steps (exactly where the next activation is reachable, flagged where it is not)."""
    rng = np.random.default_rng(3)
    prm = np.tile([0.01, 0.04, tausmooth], (6, 1))
    ctrl, act = rng.uniform(-0.2, 1.2, (300, 6)), rng.uniform(0.0, 1.0, (300, 6))
    reference = np.array([[mujoco.mju_muscleDynamics(c, a, prm[k]) for k, (c, a) in enumerate(zip(cr, ar))]
                          for cr, ar in zip(ctrl, act)])
    rate = activation_rate(ctrl, act, prm)
    # MuJoCo's formula written again (a difference, a division by the time constant, the smooth switch's few terms):
    # a few tens of roundings at the rates' scale (~1e-12 /s at 200 /s); the two time constants swapped are O(10 /s)
    np.testing.assert_allclose(rate, reference, rtol=0, atol=rounding_tol(32, reference))
    for steps in (1, 5):
        target = act.copy()
        for _ in range(steps):
            target = target + 0.002 * activation_rate(ctrl, target, prm)
        control, clipped = excitation(act, target, prm, np.full(300, 0.002 * steps), 0.002)
        assert not clipped.any()
        np.testing.assert_allclose(control, np.clip(ctrl, 0, 1), atol=1e-9)
        _, clipped = excitation(act, np.clip(target + 0.3, 0, 1.3), prm, np.full(300, 0.002 * steps), 0.002)
        assert clipped.any()  # a jump no excitation reaches in that time


def test_zero_motion_is_static_optimization(elbow):
    q = elbow.model.sample_q(np.random.default_rng(0), 40)
    static, motion = elbow.solve(q), inverse_dynamics(elbow, q, None, None)
    np.testing.assert_array_equal(static.status, motion.status)
    np.testing.assert_array_equal(static.activation, motion.activation)


def test_threads_give_the_same_numbers(elbow, motion):
    """MuJoCo's per-frame calls on 2 threads (each its own MjData) answer bit for bit as on one."""
    t, q, qvel, qacc = motion
    one = inverse_dynamics(elbow, q, qvel, qacc, t=t)
    two = inverse_dynamics(StaticBody(ELBOW, threads=2), q, qvel, qacc, t=t)
    np.testing.assert_array_equal(one.activation, two.activation)
    np.testing.assert_array_equal(one.tau_nm, two.tau_nm)


@pytest.mark.parametrize("faults", [None, {"cut": ["BRA_tendon"]}])
def test_mujoco_follows_the_motion(elbow, motion, faults):
    """MuJoCo's forward acceleration with the activations is the requested one where ok; activations computed
    without MuJoCo's force-velocity factor miss it by far (the check can fail)."""
    t, q, qvel, qacc = motion
    result = inverse_dynamics(elbow, q, qvel, qacc, faults=faults, t=t)
    ok = result.ok
    assert ok.sum() >= 100
    assert np.abs(mujoco_motion_error(elbow, result)[ok]).max() <= QACC_TOL
    static_curves = result.take(ok)
    static_curves.activation = inverse_dynamics(elbow, q[ok], np.zeros_like(qvel[ok]), qacc[ok]).activation
    assert np.abs(mujoco_motion_error(elbow, static_curves)).max() > 1e3 * QACC_TOL


def _slsqp_reference(q, qvel, qacc):
    """Per frame, MuJoCo alone on MyoSuite's own elbow model and scipy's SLSQP: the generalized force by mj_inverse,
    the actuators' generalized force affine in the activations (probed by mj_forward one activation at a time),
    ``min sum a^2`` with ``0 <= a <= 1``. Returns the actuators' names, activations and MuJoCo's tensions (B, nu),
    NaN where SLSQP fails."""
    import myo_sim
    from scipy.optimize import minimize

    m = myo_sim.load_spec("myoelbow_2dof").compile()
    m.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_CONTACT) | int(mujoco.mjtDisableBit.mjDSBL_CONSTRAINT)
    d, nu = mujoco.MjData(m), m.nu
    activation, tension = np.full((len(q), nu), np.nan), np.full((len(q), nu), np.nan)
    for b in range(len(q)):
        d.qpos[:], d.qvel[:], d.qacc[:] = q[b], qvel[b], qacc[b]
        mujoco.mj_inverse(m, d)
        need = d.qfrc_inverse.copy()

        def actuator_force(a):
            d.act[:] = a
            mujoco.mj_forward(m, d)
            return d.qfrc_actuator.copy(), d.actuator_force.copy()

        base = actuator_force(np.zeros(nu))[0]
        A = np.stack([actuator_force(np.eye(nu)[k])[0] - base for k in range(nu)], axis=1)
        solution = minimize(lambda a: a @ a, np.full(nu, 0.5), jac=lambda a: 2 * a, method="SLSQP",
                            bounds=[(0, 1)] * nu, options={"ftol": 1e-15, "maxiter": 500},
                            constraints={"type": "eq", "fun": lambda a: base + A @ a - need, "jac": lambda a: A})
        if solution.success:
            activation[b] = solution.x
            tension[b] = -m.actuator_gear[:, 0] * actuator_force(solution.x)[1]
    return [m.actuator(k).name for k in range(nu)], activation, tension


def test_answers_equal_an_independent_slsqp_reference(elbow, motion):
    """On MyoSuite's own model (not our stored copy), healthy: activations within 1e-6, tensions within 1e-4 N."""
    t, q, qvel, qacc = (x[::10] for x in motion)
    result = inverse_dynamics(elbow, q, qvel, qacc, t=t)
    actuators, activation, tension = _slsqp_reference(q, qvel, qacc)
    both = result.ok & np.isfinite(activation).all(1)
    assert both.sum() >= 15
    order = [elbow.curves.actuators.index(a) for a in actuators]  # MyoSuite's actuator order
    assert np.abs(result.activation[both][:, order] - activation[both]).max() <= 1e-6
    assert np.abs(result.tension_n[both][:, order] - tension[both]).max() <= 1e-4


def test_excitations_drive_mujocos_activations(elbow, motion):
    """MuJoCo's step with each frame's control takes its activations to the next frame's (where not clipped)."""
    t, q, qvel, qacc = motion
    result = inverse_dynamics(elbow, q[:200], qvel[:200], qacc[:200], t=t[:200])
    m = actuated_model(elbow.model, elbow.curves)
    d = mujoco.MjData(m)
    rows = np.flatnonzero(np.isfinite(result.activation[:-1]).all(1) & np.isfinite(result.activation[1:]).all(1))
    reached = []
    for b in rows:
        d.qpos[:], d.qvel[:], d.act[:], d.ctrl[:] = q[b], qvel[b], result.activation[b], result.control[b]
        mujoco.mj_step(m, d)
        reached.append(d.act.copy())
    miss = np.abs(np.array(reached) - result.activation[rows + 1])
    free = ~result.control_clipped[rows]
    assert free.mean() > 0.5 and miss[free].max() <= 1e-12
    assert miss[~free].max() > 1e-6  # clipped excitations do not reach it: the flag means something


def test_residual_actuators_carry_what_the_muscles_cannot(elbow, motion):
    """Every elbow flexor cut: no frame can be driven; with residual actuators on both joints every frame is ok and
    MuJoCo with the residual torques applied follows the motion. Healthy: the residual takes over only what lies
    beyond full activation; elsewhere it shrinks as 1 / weight."""
    t, q, qvel, qacc = motion
    cut, joints = {"cut": ["BIClong_tendon", "BICshort_tendon", "BRA_tendon"]}, ["r_shoulder_elev", "r_elbow_flex"]
    assert not inverse_dynamics(elbow, q, qvel, qacc, faults=cut, t=t).ok.any()
    helped = inverse_dynamics(elbow, q, qvel, qacc, faults=cut, t=t, residual_dofs=joints)
    assert helped.ok.all() and np.abs(helped.residual_nm).max() > 1.0
    assert np.abs(mujoco_motion_error(elbow, helped)).max() <= QACC_TOL
    healthy = inverse_dynamics(elbow, q, qvel, qacc, t=t)
    light, heavy = (inverse_dynamics(elbow, q, qvel, qacc, t=t, residual_dofs=joints, residual_weight=w)
                    for w in (1e2, 1e4))
    assert light.ok.all() and np.median(np.abs(light.residual_nm[~healthy.ok]).max(1)) > 1.0
    assert (light.activation[~healthy.ok].max(1) >= 1.0 - 1e-9).all()  # the muscles first, then the residual
    ratio = np.abs(light.residual_nm[healthy.ok]).max() / np.abs(heavy.residual_nm[healthy.ok]).max()
    assert 90 < ratio < 110


def test_muscles_for_torque_make_that_torque(elbow, motion):
    """The activations' MuJoCo actuator force, E^T qfrc_actuator, is the torque asked for (myosuite #337)."""
    _, q, qvel, qacc = (x[::25] for x in motion)
    tau = inverse_dynamics(elbow, q, qvel, qacc).tau_nm
    result = muscles_for_torque(elbow, q, tau, qvel=qvel)
    m = actuated_model(elbow.model, elbow.curves)
    d = mujoco.MjData(m)
    made = []
    for b in np.flatnonzero(result.ok):
        d.qpos[:], d.qvel[:], d.act[:] = q[b], qvel[b], result.activation[b]
        mujoco.mj_forward(m, d)
        made.append(d.qfrc_actuator.copy())
    assert result.ok.sum() >= 5
    assert np.abs(np.array(made) - tau[result.ok]).max() <= 1e-8


@pytest.mark.parametrize("call, match", [
    (lambda b, m: inverse_dynamics(b, m[1], m[2][:, :1], m[3]), r"qvel has shape \(500, 1\)"),
    (lambda b, m: inverse_dynamics(b, m[1], m[2], m[3] * np.nan), "qacc contains NaN"),
    (lambda b, m: inverse_dynamics(b, m[1], m[2], m[3], residual_dofs=["pelvis_tx"]), "residual_dofs .*pelvis_tx"),
    (lambda b, m: inverse_dynamics(b, m[1], m[2], m[3], t=m[0][::-1]), "strictly increasing"),
    (lambda b, m: inverse_dynamics(b, m[1], m[2], m[3], residual_weight=0.0), "residual_weight=0.0"),
    (lambda b, m: muscles_for_torque(b, m[1], m[2][:3]), r"tau_nm has shape \(3, 2\)"),
    (lambda b, m: inverse_dynamics(b, m[1], m[2], m[3], device="tpu:9"), "device='tpu:9'"),
])
def test_bad_input_is_one_clear_error(elbow, motion, call, match):
    with pytest.raises(BodySchemaInputError, match=match):
        call(elbow, motion)


def test_top_level_export():
    import lightning_bodyschema as package

    assert package.inverse_dynamics is inverse_dynamics and package.muscles_for_torque is muscles_for_torque
    assert Status.OK.name == "OK"


@pytest.mark.slow
def test_readme_example(readme_block):
    """README "Muscles for a motion": the Python block runs from the repository root and its answers are physical:
    the cut muscle carries nothing, most frames are ok, and the torque form returns the first frame's activations."""
    namespace = readme_block("inverse_dynamics(arm")
    motion, held = namespace["motion"], namespace["held"]
    assert motion.activation.shape == (1001, 50) and motion.ok.mean() > 0.9
    assert (motion.tension_n[:, motion.muscles.index("BIClong_tendon")] == 0).all()
    np.testing.assert_allclose(held.activation[0], motion.activation[0], atol=1e-9)
