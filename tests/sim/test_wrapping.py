"""Wrapping states (sim/wrapping.py) on a body whose switches are known in closed form: a strap from a fixed site
around a fixed post (a cylinder of radius R at the origin) to a site a distance D out on an arm turning about the
post's axis. With no side site the path wraps the shorter way: over the top (y > 0) for an angle theta > 0, under it
for theta < 0 (the side flips at 0), and straight once the segment clears the post, |theta| >= 2 asin(R / D). The
same strap with a side site below the post ("sided") goes under it from -2 asin(R / D) (where the segment starts to
cut it) to pi / 2 (where the side site stops lying behind the post, opposite the wedge between the two sites)."""
import numpy as np
import pytest

from physics_checks import rounding_tol

from lightning_bodyschema.errors import BodySchemaInputError
from lightning_bodyschema.sim import MusculoskeletalModel
from lightning_bodyschema.sim.wrapping import MARGINS, states_from_margins, wrap_geoms, wrap_margins, wrap_states

# MuJoCo's path through the sites (a rotation's sin/cos, the tangent points' sqrt and atan2, an arc) and the closed
# form each take a dozen or so roundings at the post's scale; another CPU's libm may differ by an ulp in each
# (measured here: 2.5 roundings at most)
PATH_ROUNDINGS = 16

R, D = 0.03, 0.1
POST_XML = f"""
<mujoco>
  <compiler angle="radian"/>
  <default>
    <joint type="hinge" axis="0 0 1" range="-2.5 2.5"/>
    <geom contype="0" conaffinity="0"/>
  </default>
  <worldbody>
    <geom name="post" type="cylinder" size="{R} 0.05"/>
    <site name="s0" pos="-{D} 0 0"/>
    <body name="arm">
      <joint name="turn"/>
      <geom type="capsule" fromto="0 0 0  {3 * D} 0 0" size="0.005" mass="1"/>
      <geom name="knob" type="cylinder" pos="{2 * D} 0 0" size="{R} 0.05" mass="0"/>
      <site name="s1" pos="{D} 0 0"/>
      <site name="s2" pos="{3 * D} 0.01 0"/>
    </body>
    <site name="below" pos="0 -{2 * R} 0"/>
  </worldbody>
  <tendon>
    <spatial name="strap"><site site="s0"/><geom geom="post"/><site site="s1"/></spatial>
    <spatial name="double"><site site="s0"/><geom geom="post"/><site site="s1"/><geom geom="knob"/><site site="s2"/></spatial>
    <spatial name="sided"><site site="s0"/><geom geom="post" sidesite="below"/><site site="s1"/></spatial>
  </tendon>
</mujoco>"""


def expected_strap_code(theta: np.ndarray) -> np.ndarray:
    """0 straight; wrapped with the incoming tangent's ``p0 x t1`` about +z positive (1: under the post, theta < 0)
    or negative (2: over it, theta > 0)."""
    wrapped = np.abs(theta) < 2 * np.arcsin(R / D)
    return np.where(wrapped, np.where(theta > 0, 2, 1), 0)


def test_the_side_flips_at_zero_and_the_wrap_lets_go_at_the_tangent_angle():
    body = MusculoskeletalModel(POST_XML, allow_unloaded=True)
    release = 2 * np.arcsin(R / D)
    theta = np.linspace(-2.4, 2.4, 4801)
    theta = theta[(np.abs(theta) > 1e-6) & (np.abs(np.abs(theta) - release) > 1e-6)]  # off the switches themselves
    codes = wrap_states(body, theta[:, None])
    strap = expected_strap_code(theta)
    np.testing.assert_array_equal(codes[:, 0], strap)
    # the knob rides on the arm with both its sites: always wrapped, over its top (code 2, weight 3) whatever the post
    np.testing.assert_array_equal(codes[:, 1], strap + 3 * 2)
    # inside each state MuJoCo's length is the closed form of that state: the labels are the path's own pieces
    length = body.kinematics(theta[:, None])[0][:, 0]
    straight = 2 * D * np.abs(np.cos(theta / 2))
    wrapped = 2 * np.sqrt(D ** 2 - R ** 2) + R * (np.pi - np.abs(theta) - 2 * np.arccos(R / D))
    truth = np.where(strap == 0, straight, wrapped)
    np.testing.assert_allclose(length, truth, rtol=0, atol=rounding_tol(PATH_ROUNDINGS, truth))


def test_the_geoms_are_listed_in_path_order_and_a_body_without_a_wrap_codes_zero():
    body = MusculoskeletalModel(POST_XML, allow_unloaded=True)
    post, knob = (int(body.mj_model.geom(name).id) for name in ("post", "knob"))
    assert wrap_geoms(body) == [[(post, 1, False)], [(post, 1, False), (knob, 2, False)], [(post, 1, False)]]
    assert np.all(wrap_states(MusculoskeletalModel("paper_arm"), np.zeros((3, 2)))[:, 0] > 0)  # paper arm: wraps
    with pytest.raises(BodySchemaInputError, match="q has shape"):
        wrap_states(body, np.zeros((2, 3)))


def test_the_margins_give_the_states_and_cross_zero_where_they_switch():
    body = MusculoskeletalModel(POST_XML, allow_unloaded=True)
    release = 2 * np.arcsin(R / D)
    theta = np.linspace(-2.4, 2.4, 4801)
    theta = theta[np.min(np.abs(theta[:, None] - np.array([0.0, -release, release, np.pi / 2])), 1) > 1e-6]
    margins, codes = wrap_margins(body, theta[:, None]), wrap_states(body, theta[:, None])
    np.testing.assert_array_equal(states_from_margins(margins), codes)
    np.testing.assert_array_equal(codes[:, 2], np.where((theta > -release) & (theta < np.pi / 2), 1, 0))
    strap = dict(zip(MARGINS, margins[:, 0, 0].T))
    # the line from (-D, 0) to D (cos, sin) theta passes D sin(theta / 2) from the post's axis, on the side of -theta
    np.testing.assert_allclose(strap["upper"], R + D * np.sin(theta / 2), rtol=0, atol=rounding_tol(PATH_ROUNDINGS, D))
    np.testing.assert_allclose(strap["lower"], R - D * np.sin(theta / 2), rtol=0, atol=rounding_tol(PATH_ROUNDINGS, D))
    assert np.all(strap["foot0"] > 0) and np.all(strap["foot1"] > 0)  # the foot: between the sites, for |theta| < pi
    assert np.all(np.isnan(strap["before"])) and np.all(np.isnan(margins[:, 0, 1])) and np.isnan(margins[:, 2, 1]).all()
    # the sided strap's switch at pi / 2 (a jump: straight to under the post) is the zero of its "after" margin,
    # r u x d1 / |d1| = -R cos(theta) with u = +y (away from the side site), d1 along theta
    after = margins[:, 2, 0, MARGINS.index("after")]
    np.testing.assert_allclose(after, -R * np.cos(theta), rtol=0, atol=rounding_tol(PATH_ROUNDINGS, D))
    length = body.kinematics(np.array([[np.pi / 2 - 1e-4], [np.pi / 2 + 1e-4]]))[0][:, 2]
    assert length[0] - length[1] > R  # the path under the post is longer by an arc: the state is the jump


def test_margins_refuse_a_posture_of_the_wrong_width():
    body = MusculoskeletalModel(POST_XML, allow_unloaded=True)
    with pytest.raises(BodySchemaInputError, match="q has shape"):
        wrap_margins(body, np.zeros((2, 3)))


def test_on_myoarm_the_margins_give_mujocos_own_states_at_every_muscle():
    """Side sites that force a wrap, side sites inside the geom, spheres and cylinders: all of myoArm's 85 wrapping
    geoms, at seeded random postures."""
    pytest.importorskip("myo_sim")
    import yaml

    locks = yaml.safe_load(open("configs/myoarm.yaml"))["data"]["locked_joints"]
    arm = MusculoskeletalModel("myo:myoarm", locked_joints=locks)
    q = arm.sample_q(np.random.default_rng(3), 300)
    codes = wrap_states(arm, q)
    assert len(np.unique(codes)) > 5  # the draw sees several states
    np.testing.assert_array_equal(states_from_margins(wrap_margins(arm, q)), codes)
