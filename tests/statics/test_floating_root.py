"""Inverse dynamics on a floating root (statics.root): a body whose root is a MuJoCo free joint, the root's 6
generalized forces carried by residual actuators, the muscles on the rest; MuJoCo's forward dynamics with the
controls and those forces reproduces every acceleration, the root's included; the CLI on a motion file with root
columns; bad input."""
from __future__ import annotations

import re
from dataclasses import replace

import numpy as np
import pytest

from lightning_bodyschema.apps.static_opt import static_opt_main
from lightning_bodyschema.errors import BodySchemaInputError
from lightning_bodyschema.statics import StaticBody, inverse_dynamics
from lightning_bodyschema.statics.check import mujoco_motion_error
from lightning_bodyschema.statics.differentiate import differentiate
from lightning_bodyschema.statics.root import root_derivatives

# a torso floating on a free joint, a two-joint arm, four muscles with MuJoCo muscle actuators, an idle tendon
# (a path without force: left out of the inverse model), a spring tendon (kept: it pulls) and a marker site (no
# tendon passes it: left out)
FLOATING_ARM = """
<mujoco model="floating_arm">
  <compiler angle="radian"/>
  <option timestep="0.002" gravity="0 0 -9.81"/>
  <worldbody>
    <body name="torso" pos="0 0 1">
      <freejoint name="root"/>
      <geom type="box" size="0.1 0.08 0.2" mass="8"/>
      <site name="s_shoulder_front" pos="0.06 0 0.1"/>
      <site name="s_shoulder_back" pos="-0.06 0 0.1"/>
      <site name="marker" pos="0 0 0.2"/>
      <body name="upper" pos="0 0.12 0.15">
        <joint name="shoulder" type="hinge" axis="0 1 0" range="-1.5 1.5" damping="0.5"/>
        <geom type="capsule" fromto="0 0 0 0 0 -0.3" size="0.03" mass="1.5"/>
        <site name="s_upper_front" pos="0.03 0 -0.1"/>
        <site name="s_upper_back" pos="-0.03 0 -0.1"/>
        <site name="s_upper_low_f" pos="0.03 0 -0.25"/>
        <site name="s_upper_low_b" pos="-0.03 0 -0.25"/>
        <body name="fore" pos="0 0 -0.3">
          <joint name="elbow" type="hinge" axis="0 1 0" range="0 2.0" armature="0.01"/>
          <geom type="capsule" fromto="0 0 0 0.25 0 0" size="0.025" mass="1.0"/>
          <site name="s_fore_top" pos="0.05 0 0.02"/>
          <site name="s_fore_bottom" pos="0.05 0 -0.02"/>
        </body>
      </body>
    </body>
  </worldbody>
  <tendon>
    <spatial name="flexor_s"><site site="s_shoulder_front"/><site site="s_upper_front"/></spatial>
    <spatial name="extensor_s"><site site="s_shoulder_back"/><site site="s_upper_back"/></spatial>
    <spatial name="flexor_e"><site site="s_upper_low_f"/><site site="s_fore_top"/></spatial>
    <spatial name="extensor_e"><site site="s_upper_low_b"/><site site="s_fore_bottom"/></spatial>
    <spatial name="ligament"><site site="s_shoulder_front"/><site site="s_fore_top"/></spatial>
    <spatial name="spring" stiffness="40" springlength="0.3"><site site="s_shoulder_back"/><site site="s_fore_bottom"/></spatial>
  </tendon>
  <actuator>
    <muscle name="m_flexor_s" tendon="flexor_s" force="400"/>
    <muscle name="m_extensor_s" tendon="extensor_s" force="400"/>
    <muscle name="m_flexor_e" tendon="flexor_e" force="300"/>
    <muscle name="m_extensor_e" tendon="extensor_e" force="300"/>
  </actuator>
</mujoco>
"""
GRAVITY = np.array([0.0, 0.0, -9.81])
# MuJoCo's acceleration against the requested one [rad/s^2, m/s^2]: the target. Accelerations here are
# ~1-30, M^-1 ~1e2 per kg m^2, force rounding ~1e-13: ~1e-11 is left.
QACC_TOL = 1e-6


@pytest.fixture(scope="module")
def body():
    return StaticBody(FLOATING_ARM, fixed_base=True)


def turning_root(t, axis=(0.3, -0.4, 0.866)):
    """The root rising and sliding by a raised cosine while it turns about a fixed tilted axis, 0.4 sin(2 pi t / T)
    rad: positions and quaternions, and the exact qvel, qacc in MuJoCo's convention (about a fixed axis the angular
    velocity is the same in the world and the root's frame)."""
    axis = np.asarray(axis) / np.linalg.norm(axis)
    w = 2 * np.pi / 1.0
    shift = np.array([0.05, 0.02, -0.1])
    angle, rate, accel = 0.4 * np.sin(w * t), 0.4 * w * np.cos(w * t), -0.4 * w ** 2 * np.sin(w * t)
    s, sd, sdd = 0.5 * (1 - np.cos(w * t)), 0.5 * w * np.sin(w * t), 0.5 * w ** 2 * np.cos(w * t)
    qpos = np.hstack([[0, 0, 1] + shift * s[:, None], np.cos(angle / 2)[:, None], np.sin(angle / 2)[:, None] * axis])
    qvel = np.hstack([shift * sd[:, None], rate[:, None] * axis])
    qacc = np.hstack([shift * sdd[:, None], accel[:, None] * axis])
    return qpos, qvel, qacc


def arm_motion(t):
    w = 2 * np.pi * np.array([0.7, 1.1])
    mid, amp = np.array([0.2, 1.0]), np.array([0.3, 0.4])
    return mid + amp * np.sin(w * t[:, None]), amp * w * np.cos(w * t[:, None]), -amp * w ** 2 * np.sin(w * t[:, None])


def test_statics_still_refuses_the_free_root():
    with pytest.raises(BodySchemaInputError, match="fixed_base"):
        StaticBody(FLOATING_ARM)


def test_a_rigid_body_accelerating_needs_total_mass_times_a_minus_g(body):
    """Joints at rest, the root translating at a constant acceleration without turning: the root's force is
    m_total (a - g), exactly, and the muscles hold the arm against the accelerating frame."""
    t = np.arange(0.0, 0.2, 0.002)
    acc = np.array([1.5, -0.5, 2.0])
    qpos = np.zeros((len(t), 7))
    qpos[:, :3], qpos[:, 3] = [0, 0, 1] + 0.5 * acc * t[:, None] ** 2, 1.0
    qvel, qacc = np.zeros((len(t), 6)), np.zeros((len(t), 6))
    qvel[:, :3], qacc[:, :3] = acc * t[:, None], acc
    q = np.tile([0.2, 0.8], (len(t), 1))
    result = inverse_dynamics(FLOATING_ARM, q, 0 * q, 0 * q, t=t, root_qpos=qpos, root_qvel=qvel, root_qacc=qacc)
    mass = body.model.mj_model.body_mass.sum()
    force = mass * (acc - GRAVITY)  # ~120 N: rounding ~1e-13 N
    assert result.ok.all() and result.root_dofs == [f"root_{d}" for d in ("tx", "ty", "tz", "rx", "ry", "rz")]
    np.testing.assert_allclose(result.root_residual[:, :3], np.broadcast_to(force, (len(t), 3)), rtol=0, atol=1e-9)
    welded = inverse_dynamics(body, q, 0 * q, 0 * q, t=t)
    assert np.abs(result.tau_nm - welded.tau_nm).max() > 0.1  # the frame's acceleration loads the joints


def test_forward_check_reproduces_every_acceleration_root_included(body):
    """MuJoCo's mj_forward with the computed activations and controls, the root's residual forces applied,
    reproduces the requested acceleration on every dof (2 joints + the root's 6) of a motion whose root turns and
    accelerates; without the root's forces it falls."""
    t = np.arange(0.0, 1.0, 0.01)
    q, qvel, qacc = arm_motion(t)
    root = turning_root(t)
    result = inverse_dynamics(body, q, qvel, qacc, t=t, root_qpos=root[0], root_qvel=root[1], root_qacc=root[2])
    ok = result.ok
    assert ok.mean() >= 0.8  # the rest need activations above 1 (held with the cap lifted)
    error = mujoco_motion_error(body, result)
    assert error.shape == (len(t), 8) and np.abs(error[ok]).max() <= QACC_TOL
    sample = result.take(np.flatnonzero(ok)[:5])
    unheld = mujoco_motion_error(body, replace(sample, root_residual=np.zeros_like(sample.root_residual)))
    assert np.abs(unheld[:, 2:]).max() > 1.0  # the root's forces matter: without them it falls


def test_root_derivatives_of_a_turning_root():
    """The differentiator on the root: angular velocity 2 conj(q) qdot and acceleration 2 conj(q) qddot against a
    turn's exact ones, within the Savitzky-Golay accuracy (statics.differentiate: ~0.2 % of the peak), interior
    frames; a sign flip of the quaternions in the file changes nothing."""
    t = np.arange(0.0, 2.0, 0.002)
    qpos, qvel, qacc = turning_root(t)
    flipped = qpos.copy()
    flipped[::7, 3:] *= -1
    vel, acc = root_derivatives(t, flipped, differentiate)
    inner = slice(30, -30)
    peak_vel, peak_acc = np.abs(qvel).max(), np.abs(qacc).max()
    assert np.abs(vel - qvel)[inner].max() <= 2e-3 * peak_vel
    assert np.abs(acc - qacc)[inner].max() <= 2e-3 * peak_acc


def test_bad_root_input_is_one_clear_line(body):
    q = np.array([[0.2, 0.8]])
    with pytest.raises(BodySchemaInputError, match="quaternion has norm"):
        inverse_dynamics(body, q, 0 * q, 0 * q, root_qpos=[[0, 0, 1, 1, 1, 0, 0]])
    with pytest.raises(BodySchemaInputError, match=r"root_qvel has shape \(1, 5\)"):
        inverse_dynamics(body, q, 0 * q, 0 * q, root_qpos=[[0, 0, 1, 1, 0, 0, 0]], root_qvel=[[0] * 5])
    with pytest.raises(BodySchemaInputError, match="no floating root"):
        inverse_dynamics(StaticBody("paper_arm"), [[0.1, 0.2]], [[0, 0]], [[0, 0]], root_qpos=[[0, 0, 1, 1, 0, 0, 0]])


def test_cli_motion_with_root_columns(tmp_path, body):
    """``--motion`` on a file with the root's position and quaternion columns (derivatives by the differentiator):
    the root's residual columns per frame, and the model built without --fixed-base."""
    t = np.arange(0.0, 1.0, 0.002)
    q = arm_motion(t)[0]
    qpos, qvel, qacc = turning_root(t)
    columns = {"t": t, "shoulder": q[:, 0], "elbow": q[:, 1]}
    columns.update({f"root_{p}": qpos[:, k] for k, p in enumerate(("px", "py", "pz", "qw", "qx", "qy", "qz"))})
    model, motion, out = tmp_path / "arm.xml", tmp_path / "motion.npz", tmp_path / "out.npz"
    model.write_text(FLOATING_ARM)
    np.savez(motion, **columns)
    static_opt_main(["--model", str(model), "--motion", str(motion), "--out", str(out), "--no-progress",
                     "--residual", "root"])  # naming the root: it has its residuals anyway
    with np.load(out) as saved:
        assert list(saved["root_dofs"]) == [f"root_{d}" for d in ("tx", "ty", "tz", "rx", "ry", "rz")]
        exact = inverse_dynamics(body, q, *arm_motion(t)[1:], t=t, root_qpos=qpos, root_qvel=qvel, root_qacc=qacc)
        inner = slice(30, -30)
        # the differentiator's miss (~0.2 % of the peak accelerations) is all that separates them
        scale = np.abs(exact.root_residual[inner]).max(0)
        assert (np.abs(saved["root_residual"] - exact.root_residual)[inner].max(0) <= 1e-2 * scale).all()


@pytest.mark.parametrize("floating", [False, True])
def test_lean_inverse_is_mj_inverse(body, floating):
    """The inverse model leaves out the idle tendon and the sites no tendon left passes only, and its lean sequence
    gives mj_inverse's generalized force on the whole model (idle tendon and sites included) to 1e-12 of the force's
    scale, frame by frame."""
    import mujoco

    from lightning_bodyschema.statics.dynamics import InverseBody
    from lightning_bodyschema.statics.root import FrameLayout, floating_spec

    inverse = InverseBody(body, floating)
    names = [mujoco.mj_id2name(inverse.m, mujoco.mjtObj.mjOBJ_TENDON, i) for i in range(inverse.m.ntendon)]
    # floating: the muscles' paths are the welded body's, the forces need only the tendon that pulls
    assert inverse.lean and sorted(names) == (["spring"] if floating else sorted(body.model.muscle_names + ["spring"]))
    sites = {mujoco.mj_id2name(inverse.m, mujoco.mjtObj.mjOBJ_SITE, i) for i in range(inverse.m.nsite)}
    assert sites == ({"s_shoulder_back", "s_fore_bottom"} if floating else
                     {"s_shoulder_front", "s_shoulder_back", "s_upper_front", "s_upper_back", "s_upper_low_f",
                      "s_upper_low_b", "s_fore_top", "s_fore_bottom"})
    whole = FrameLayout.of(body, floating)
    whole.m.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_CONSTRAINT)
    assert whole.m.ntendon == 6
    t = np.arange(0.0, 1.0, 0.05)
    q, qvel, qacc = arm_motion(t)
    root = turning_root(t) if floating else None
    _, G, tau, G_root, tau_root = inverse.inverse(q, qvel, qacc, root)
    assert G_root is None  # no muscle spans the root: its moment arms there are zero
    state = whole.state(*inverse.full_state(q, qvel, qacc)[:3], root)
    d = mujoco.MjData(whole.m)
    expected = np.empty((len(t), whole.m.nv))
    for b in range(len(t)):
        d.qpos[:], d.qvel[:], d.qacc[:] = state[0][b], state[1][b], state[2][b]
        mujoco.mj_inverse(whole.m, d)
        expected[b] = d.qfrc_inverse
    got = np.zeros_like(expected)
    got[:, whole.rest_dof] = tau  # every joint free here: E = I
    if floating:
        got[:, whole.root_dof] = tau_root
    scale = np.abs(expected).max()
    assert scale > 1.0 and np.abs(got - expected).max() <= 1e-12 * scale


def test_a_muscle_anchored_to_the_world_is_refused_on_a_floating_root():
    """A muscle from the world to the arm spans the root: the root cannot be left to residuals alone."""
    anchored = FLOATING_ARM.replace('<worldbody>', '<worldbody>\n    <site name="s_ground" pos="0 0 0"/>').replace(
        '<spatial name="ligament">', '<spatial name="tether"><site site="s_ground"/><site site="s_upper_front"/>'
        '</spatial>\n    <spatial name="ligament">').replace(
        '</actuator>', '  <muscle name="m_tether" tendon="tether" force="100"/>\n  </actuator>')
    q = np.array([[0.2, 0.8]])
    with pytest.raises(BodySchemaInputError, match="spans the floating root"):
        inverse_dynamics(anchored, q, 0 * q, 0 * q, root_qpos=[[0, 0, 1, 1, 0, 0, 0]])


def test_cli_root_columns_in_csv_and_refusals(tmp_path, capsys):
    """CSV out: the root's residual columns named with their units; root columns given in part, and --track on a
    floating root, refused in one line (exit 2)."""
    t = np.arange(0.0, 0.2, 0.002)
    q = arm_motion(t)[0]
    qpos = turning_root(t)[0]
    columns = {"t": t, "shoulder": q[:, 0], "elbow": q[:, 1]}
    columns.update({f"root_{p}": qpos[:, k] for k, p in enumerate(("px", "py", "pz", "qw", "qx", "qy", "qz"))})
    model, motion, out = tmp_path / "arm.xml", tmp_path / "motion.npz", tmp_path / "out.csv"
    model.write_text(FLOATING_ARM)
    np.savez(motion, **columns)
    static_opt_main(["--model", str(model), "--motion", str(motion), "--out", str(out), "--no-progress"])
    header = out.read_text().splitlines()[0].split(",")
    assert header[-6:] == ["root_tx.residual_n", "root_ty.residual_n", "root_tz.residual_n", "root_rx.residual_nm",
                           "root_ry.residual_nm", "root_rz.residual_nm"]
    partial = {k: v for k, v in columns.items() if k != "root_qz"}
    np.savez(tmp_path / "partial.npz", **partial)
    for argv, match in ((["--motion", str(tmp_path / "partial.npz")], re.escape("miss ['root_qz']")),
                        (["--motion", str(motion), "--track"], "--track simulates a welded body")):
        with pytest.raises(SystemExit) as exit_info:
            static_opt_main(["--model", str(model), "--out", str(tmp_path / "x.csv"), "--no-progress", *argv])
        err = capsys.readouterr().err.strip()
        assert exit_info.value.code == 2 and len(err.splitlines()) == 1
        assert re.search(match, err), err
