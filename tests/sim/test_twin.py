"""The torch kinematic twin must agree with MuJoCo, and its inverse kinematics must reach what is reachable."""
import numpy as np
import pytest
import torch
from physics_checks import assert_drawn_muscles_match_mujoco

from lightning_bodyschema.errors import BodySchemaInputError
from lightning_bodyschema.sim import MusculoskeletalModel
from lightning_bodyschema.sim.twin import TorchKinematicTwin


@pytest.fixture(scope="module")
def twin(arm):
    return TorchKinematicTwin(arm)


def test_hand_position_matches_mujoco(arm, twin, rng):
    q = arm.sample_q(rng, 200)
    hand_m = twin.site_position(q).numpy()
    np.testing.assert_allclose(hand_m, arm.site_position(q, "hand"), atol=1e-6, rtol=0)
    assert np.ptp(hand_m[:, 0]) > 0.5  # the postures really spread the hand over the workspace


def test_every_site_matches_mujoco(arm, twin, rng):
    """Not only the hand: every site, including those on the fixed base, sits where MuJoCo puts it."""
    q = arm.sample_q(rng, 20)
    for site in twin.site_names:
        np.testing.assert_allclose(twin.site_position(q, site).numpy(), arm.site_position(q, site), atol=1e-9)


def test_autograd_jacobian_matches_mujoco_finite_differences(arm, twin, rng):
    q = arm.sample_q(rng, 30) * 0.99  # keep q +- h inside the range
    _, jac = twin.site_jacobian(q)
    h = 1e-6
    for j in range(arm.n_joints):
        dq = np.zeros(arm.n_joints)
        dq[j] = h
        fd = (arm.site_position(q + dq, "hand") - arm.site_position(q - dq, "hand")) / (2 * h)
        np.testing.assert_allclose(jac[:, :, j].numpy(), fd, atol=1e-7, rtol=0)
    # planar arm: with the hand 0.7 m from the shoulder, the shoulder column is never small
    assert (jac[:, :, 0].norm(dim=1) > 0.3).all()


def test_site_position_backpropagates(twin):
    q = torch.tensor([[0.3, -0.2]], dtype=torch.float64, requires_grad=True)
    twin.site_position(q)[0, 0].backward()
    _, jac = twin.site_jacobian(q.detach())
    torch.testing.assert_close(q.grad[0], jac[0, 0])


def test_ik_reaches_reachable_targets_within_limits(arm, twin, rng):
    q_true = arm.sample_q(rng, 100)
    target_m = arm.site_position(q_true, "hand")
    result = twin.inverse_kinematics(target_m, tol_m=1e-4)
    assert result.reached.all()
    reached_m = arm.site_position(result.q.numpy(), "hand")  # judged by MuJoCo, not by the twin
    assert np.linalg.norm(reached_m - target_m, axis=1).max() <= 1e-3
    lo, hi = arm.q_range.T
    assert ((result.q.numpy() >= lo) & (result.q.numpy() <= hi)).all()


def test_ik_reports_unreachable_target(arm, twin):
    reachable_m = arm.site_position([[0.3, -0.5]], "hand")[0]
    result = twin.inverse_kinematics([[5.0, 0.0, 0.0], reachable_m, [0.0, -0.3, 0.0]])
    assert result.reached.tolist() == [False, True, False]
    # the hand stays within 0.7 m of the shoulder at (0, -0.2): > 4 m from the first target;
    # with the elbow bent at most 1 rad it stays >= 0.61 m from the shoulder, so 0.1 m away is too close
    assert result.error_m[0] > 4.0 and result.error_m[2] > 0.5
    lo, hi = arm.q_range.T
    assert ((result.q.numpy() >= lo) & (result.q.numpy() <= hi)).all()


def test_joint_offsets_and_order_follow_mujoco(rng):
    """Hinges away from their body origin, a reference angle, a body with two joints and a branching tree."""
    xml = """<mujoco><compiler angle="radian"/><worldbody>
      <body name="a" pos="0.1 0 0" quat="0.9 0.1 0.3 0.2">
        <joint name="offset_hinge" axis="0 1 0" pos="0.05 0.02 0" range="-1 1" ref="0.3"/>
        <geom size="0.02"/>
        <body name="b" pos="0 -0.3 0.1">
          <joint name="z" axis="0 0 1" pos="0 0.04 0" range="-1 1"/>
          <joint name="x" axis="1 0.2 0" pos="0.03 0 0.01" range="-1 1"/>
          <geom size="0.02"/><site name="tip" pos="0.1 -0.2 0.05"/><site name="mid" pos="0 0 0"/>
        </body></body>
      <body name="branch" pos="-0.2 0 0"><joint name="w" axis="0 0 1" pos="0 0.1 0" range="-1 1"/>
        <geom size="0.02"/><site name="branch_tip" pos="0 -0.1 0"/></body></worldbody>
      <tendon><spatial name="t"><site site="mid"/><site site="tip"/></spatial></tendon></mujoco>"""
    model = MusculoskeletalModel(xml)
    twin = TorchKinematicTwin(model)
    q = model.sample_q(rng, 50)
    for site in ("tip", "mid", "branch_tip"):
        np.testing.assert_allclose(twin.site_position(q, site).numpy(), model.site_position(q, site), atol=1e-9)


def test_bad_input_is_refused_with_a_clear_message(twin):
    with pytest.raises(BodySchemaInputError, match="unknown site 'foot'"):
        twin.site_position([[0.0, 0.0]], site="foot")
    with pytest.raises(BodySchemaInputError, match="expected \\(B, 2\\)"):
        twin.site_position([[0.0, 0.0, 0.0]])
    with pytest.raises(BodySchemaInputError, match="target_xyz"):
        twin.inverse_kinematics([[0.0, float("nan"), 0.0]])


def test_drawn_muscle_paths_have_mujoco_tendon_length(arm, rng):
    """The figure's muscle paths (straight parts + arcs on the cylinders) are MuJoCo's tendons.

    An arc drawn the wrong way round the cylinder would be off by centimetres; the 24-point chords
    of the right arc are short by < 0.1 %.
    """
    assert_drawn_muscles_match_mujoco(arm, arm.sample_q(rng, 30))


def test_draw_arm_refuses_postures_outside_the_joint_range(arm, tmp_path):
    from lightning_bodyschema.plots.arm import draw_arm

    with pytest.raises(BodySchemaInputError, match="outside the joint ranges"):
        draw_arm(arm, [[0.0, 1.5]], path=tmp_path / "arm.png")
    assert list(tmp_path.iterdir()) == []
