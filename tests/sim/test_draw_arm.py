"""tools/draw_arm.py draws a config's robot (issue 27: drawings of the MyoSuite bodies): the robot is the one the data
module builds, the drawing plane is perpendicular to the chosen hinge, and ``--frame moving`` shows every body the
free joints move and not the held rest of a whole-body model."""
import importlib.util
import os

import mujoco
import numpy as np
import pytest
import yaml

from lightning_bodyschema.plots.arm import draw_arm, view_plane
from lightning_bodyschema.sim import MusculoskeletalModel

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def _tool():
    spec = importlib.util.spec_from_file_location("draw_arm_tool", os.path.join(REPO, "tools", "draw_arm.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_config_draws_the_data_modules_robot_and_options_add_to_it():
    pytest.importorskip("myo_sim")
    from lightning_bodyschema.data import EquilibriumDataModule

    tool, path = _tool(), os.path.join(REPO, "configs", "myolegs_osl.yaml")
    with open(path) as fh:
        data = yaml.safe_load(fh)["data"]
    expected = EquilibriumDataModule(**data, cache_dir=None).robot_model
    drawn = MusculoskeletalModel(**tool.robot_options(tool.parse_args(["--config", path])))
    assert drawn.xml == expected.xml and drawn.muscle_names == expected.muscle_names  # pelvis held, OSL locked
    options = tool.robot_options(tool.parse_args(["--config", path, "--lock", "mtp_angle_l=0.1", "--model", "x.xml"]))
    assert options["locked_joints"] == {**data["locked_joints"], "mtp_angle_l": 0.1} and options["source"] == "x.xml"


def test_the_drawing_plane_is_perpendicular_to_the_view_joint():
    pytest.importorskip("myo_sim")
    model = MusculoskeletalModel("myo:myofinger")
    m, d = model.mj_model, mujoco.MjData(model.mj_model)
    mujoco.mj_kinematics(m, d)
    for name in ("IFadb", "IFmcp"):
        j = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, name)
        plane = view_plane(m, d, j)
        axis = d.xaxis[j] / np.linalg.norm(d.xaxis[j])
        assert abs(abs(plane.normal @ axis) - 1.0) < 1e-12
        assert abs(plane.right @ plane.up) < 1e-12 and plane.up @ -m.opt.gravity >= 0  # orthonormal, up against g


def _ancestors(m, b: int) -> list[int]:
    return [b] + (_ancestors(m, int(m.body_parentid[b])) if b > 0 else [])


def test_frame_moving_shows_the_legs_and_not_the_held_torso(tmp_path):
    pytest.importorskip("myo_sim")
    model = MusculoskeletalModel("myo:myolegs", fixed_base=True)
    qs = np.zeros((2, model.n_joints))
    qs[1, [0, 3, 7, 10]] = 1.5  # seated: both hips and knees flexed
    fig = draw_arm(model, qs, zoom=False, frame="moving")
    (x0, x1), (y0, y1) = fig.axes[0].get_xlim(), fig.axes[0].get_ylim()
    m, d = model.mj_model, mujoco.MjData(model.mj_model)
    mujoco.mj_kinematics(m, d)
    plane = view_plane(m, d)
    feet, neck = (mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, n) for n in ("toes_l", "neck"))
    for q in qs:
        d.qpos[:] = model.joint_map.full_q(q[None])[0]
        mujoco.mj_kinematics(m, d)
        moving = [b for b in range(1, m.nbody) if set(_ancestors(m, b)) & set(m.jnt_bodyid[model.joint_map.free])]
        xy = plane.xy(d.xpos[moving])
        assert (xy[:, 0] > x0).all() and (xy[:, 0] < x1).all() and (xy[:, 1] > y0).all() and (xy[:, 1] < y1).all()
        assert plane.xy(d.xpos[neck])[1] > y1 > plane.xy(d.xpos[feet])[1]  # the torso's neck is out of the frame


def test_cli_refuses_a_view_joint_that_is_no_hinge_in_one_line(capsys):
    assert _tool().main(["--model", "paper_arm", "--view-joint", "knee", "--out", os.devnull]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "'knee' is not a hinge" in err and "shoulder" in err
