"""OpenSim's pelvis coordinates in a .mot file onto myoLegs' floating root (apps.motion_pelvis): a pure tilt turns the
root about the pelvis's right axis by that angle; any tilt, list, rotation and translation comes back from MuJoCo's
own kinematics of the mapped root (decomposed independently, Z-X-Y about OpenSim's ground axes); ``--motion`` on a
.mot with pelvis columns runs with the root free and its residual forces carry the body's weight."""
from __future__ import annotations

import mujoco
import numpy as np
import pytest
from physics_checks import rounding_tol

pytest.importorskip("myo_sim")
from scipy.spatial.transform import Rotation  # noqa: E402

from lightning_bodyschema.apps.motion_pelvis import PELVIS_COLUMNS, rest_frames, root_qpos  # noqa: E402
from lightning_bodyschema.apps.static_opt import static_opt_main  # noqa: E402
from lightning_bodyschema.sim.mjcf import compile_spec, load_spec  # noqa: E402

LEGS = "myo:myolegs"
ROOT_BODY = "Full Body"  # the body of myo:myolegs's free joint


@pytest.fixture(scope="module")
def legs():
    """``(model, data, pelvis body id, rest frames, P0)``: myoLegs as MyoSuite ships it (its free joint in place)."""
    m = compile_spec(load_spec(LEGS))
    frames = rest_frames(LEGS, ROOT_BODY)
    return m, mujoco.MjData(m), mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "pelvis"), frames, \
        Rotation.from_quat(frames[0], scalar_first=True).as_matrix()


def pelvis_pose(legs, qpos):
    """(B, 3, 3), (B, 3): the pelvis's orientation and origin in the world from MuJoCo's kinematics at root ``qpos``."""
    m, d, pelvis = legs[:3]
    rotations, origins = [], []
    for row in qpos:
        d.qpos[:7] = row
        mujoco.mj_kinematics(m, d)
        rotations.append(d.xmat[pelvis].reshape(3, 3).copy())
        origins.append(d.xpos[pelvis].copy())
    return np.array(rotations), np.array(origins)


def columns_of(tilt=0.0, list_=0.0, rotation=0.0, tx=0.0, ty=0.0, tz=0.0):
    values = (tilt, list_, rotation, tx, ty, tz)
    return {name: np.atleast_1d(np.asarray(v, float)) for name, v in zip(PELVIS_COLUMNS, values)}


def test_the_rest_pose_is_opensims_ground_frame(legs):
    """MyoSuite's legs put OpenSim's ground axes at forward -Y, up +Z, right -X (to the pelvis's 1e-3 rad at rest)."""
    P0 = legs[4]
    assert np.abs(P0 - np.array([[0, 0, -1], [-1, 0, 0], [0, 1, 0]])).max() < 2e-3


def test_a_pure_tilt_turns_the_root_about_the_pelvis_right_axis(legs):
    """pelvis_tilt 30 deg: the root's quaternion is the 30 deg turn about the pelvis's right axis (P0's Z) times its
    rest orientation, and in MuJoCo the pelvis's forward axis rises by 30 deg toward up."""
    P0, q_root0 = legs[4], legs[3][2]
    qpos = root_qpos(columns_of(tilt=30.0, ty=0.95), True, legs[3])
    half = np.deg2rad(15.0)
    turn = np.r_[np.cos(half), np.sin(half) * P0[:, 2]]
    expected = (Rotation.from_quat(turn, scalar_first=True)
                * Rotation.from_quat(q_root0, scalar_first=True)).as_quat(scalar_first=True)
    assert np.abs(qpos[0, 3:] - expected).max() <= rounding_tol(16, 1.0)
    rotation = pelvis_pose(legs, qpos)[0][0]
    forward, up = rotation[:, 0], P0[:, 1]
    assert np.isclose(np.degrees(np.arccos(np.clip(forward @ P0[:, 0], -1, 1))), 30.0, atol=1e-9)
    assert forward @ up > 0.49  # sin 30 deg: the front of the pelvis rose


def test_round_trip_through_mujocos_kinematics(legs):
    """Tilt, list, rotation and translations mapped onto the root, then read back from MuJoCo's pelvis frame in
    OpenSim's ground axes (scipy's intrinsic Z-X-Y decomposition): the same coordinates."""
    rng = np.random.default_rng(0)
    angles = rng.uniform(-40.0, 40.0, (20, 3))
    shift = rng.uniform([-1.0, 0.8, -0.5], [1.0, 1.1, 0.5], (20, 3))
    qpos = root_qpos(columns_of(*angles.T, *shift.T), True, legs[3])
    assert np.abs(np.linalg.norm(qpos[:, 3:], axis=1) - 1.0).max() <= rounding_tol(16, 1.0)
    rotations, origins = pelvis_pose(legs, qpos)
    P0 = legs[4]
    back = Rotation.from_matrix(P0.T @ rotations).as_euler("ZXY", degrees=True)
    assert np.abs(back - angles).max() <= 1e-9
    assert np.abs(origins @ P0 - shift).max() <= rounding_tol(64, shift)


def test_cli_mot_with_pelvis_columns_frees_the_root(tmp_path):
    """A 1 s .mot (degrees) whose pelvis sinks 1 cm and tilts 2 deg while the hips and knees flex: the root moves as
    mapped, and its residual actuators carry the body's weight: the vertical force within 3 % of m g away from the
    differentiator's edges (the pelvis's acceleration peaks at 0.5 % of g, the legs' segments' at a few %)."""
    t = np.arange(0.0, 1.0, 0.002)
    s = 0.5 - 0.5 * np.cos(np.pi * t)
    m = compile_spec(load_spec(LEGS))
    joints = {f"{j}_{side}": 0.0 * t for j in ("hip_flexion", "hip_adduction", "hip_rotation", "knee_angle",
                                                "ankle_angle", "subtalar_angle", "mtp_angle") for side in "rl"}
    for side in "rl":
        joints[f"hip_flexion_{side}"], joints[f"knee_angle_{side}"] = 10.0 * s, 20.0 * s
    pelvis = columns_of(2.0 * s, 0.0 * t, 0.0 * t, 0.0 * t, 0.95 - 0.01 * s, 0.0 * t)
    names = ["time", *pelvis, *joints]
    rows = np.column_stack([t, *pelvis.values(), *joints.values()])
    mot = tmp_path / "squat.mot"
    mot.write_text(f"squat\nversion=1\nnRows={len(t)}\nnColumns={len(names)}\ninDegrees=yes\nendheader\n"
                   + "\t".join(names) + "\n" + "".join("\t".join(repr(float(v)) for v in row) + "\n" for row in rows))
    out = tmp_path / "out.npz"
    static_opt_main(["--model", LEGS, "--motion", str(mot), "--out", str(out), "--no-progress"])
    with np.load(out) as saved:
        assert list(saved["root_dofs"])[:3] == ["root_tx", "root_ty", "root_tz"]
        np.testing.assert_allclose(saved["root_qpos"], root_qpos(pelvis, True, rest_frames(LEGS, ROOT_BODY)),
                                   atol=rounding_tol(16, 1.0))
        weight = m.body_mass.sum() * 9.81
        assert np.abs(saved["root_residual"][25:-25, 2] / weight - 1.0).max() < 0.03


def test_some_pelvis_columns_on_a_floating_root_are_one_clear_line(tmp_path, capsys):
    t = np.arange(0.0, 0.1, 0.002)
    mot = tmp_path / "partial.mot"
    mot.write_text("partial\ninDegrees=yes\nendheader\ntime\tpelvis_tilt\tpelvis_ty\n"
                   + "".join(f"{float(x)!r}\t0.0\t0.95\n" for x in t))
    with pytest.raises(SystemExit) as exit_info:
        static_opt_main(["--model", LEGS, "--motion", str(mot), "--out", str(tmp_path / "x.npz"), "--no-progress"])
    err = capsys.readouterr().err.strip()
    assert exit_info.value.code == 2 and len(err.splitlines()) == 1 and "the pelvis columns miss" in err
