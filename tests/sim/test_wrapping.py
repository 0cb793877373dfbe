"""Wrapping states (sim/wrapping.py) on a body whose switches are known in closed form: a strap from a fixed site
around a fixed post (a cylinder of radius R at the origin) to a site a distance D out on an arm turning about the
post's axis. With no side site the path wraps the shorter way: over the top (y > 0) for an angle theta > 0, under it
for theta < 0 (the side flips at 0), and straight once the segment clears the post, |theta| >= 2 asin(R / D)."""
import numpy as np
import pytest

from lightning_bodyschema.errors import BodySchemaInputError
from lightning_bodyschema.sim import MusculoskeletalModel
from lightning_bodyschema.sim.wrapping import wrap_geoms, wrap_states

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
  </worldbody>
  <tendon>
    <spatial name="strap"><site site="s0"/><geom geom="post"/><site site="s1"/></spatial>
    <spatial name="double"><site site="s0"/><geom geom="post"/><site site="s1"/><geom geom="knob"/><site site="s2"/></spatial>
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
    np.testing.assert_allclose(length, truth, rtol=0, atol=1e-12 * D)  # lengths of ~0.2 m: rounding ~1e-16 m


def test_the_geoms_are_listed_in_path_order_and_a_body_without_a_wrap_codes_zero():
    body = MusculoskeletalModel(POST_XML, allow_unloaded=True)
    post, knob = (int(body.mj_model.geom(name).id) for name in ("post", "knob"))
    assert wrap_geoms(body) == [[(post, 1, False)], [(post, 1, False), (knob, 2, False)]]
    assert np.all(wrap_states(MusculoskeletalModel("paper_arm"), np.zeros((3, 2)))[:, 0] > 0)  # paper arm: wraps
    with pytest.raises(BodySchemaInputError, match="q has shape"):
        wrap_states(body, np.zeros((2, 3)))
