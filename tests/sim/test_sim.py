"""Physics of the foundation: MuJoCo kinematics, the spring, the equilibrium dataset, clear errors."""
import mujoco
import numpy as np
import pytest
from physics_checks import assert_G_matches_finite_differences, rounding_tol, spring_length_tol

from lightning_bodyschema.errors import BodySchemaInputError
from lightning_bodyschema.sim import (MusculoskeletalModel, SpringParams, elongation_from_tension,
                                      generate_equilibrium_samples, paper_arm_xml, tension_from_elongation)

SPRING = SpringParams()


def test_paper_arm_structure_comes_from_the_model(arm):
    assert arm.n_joints == 2 and arm.n_muscles == 6
    np.testing.assert_array_equal(arm.q_range, [[-1.0, 1.0], [-1.0, 1.0]])
    assert arm.mj_model.opt.gravity[1] == pytest.approx(-9.81)
    masses = {mujoco.mj_id2name(arm.mj_model, mujoco.mjtObj.mjOBJ_BODY, b): arm.mj_model.body_mass[b]
              for b in range(arm.mj_model.nbody)}
    assert masses["upper_arm"] == pytest.approx(2.0) and masses["forearm"] == pytest.approx(2.0)


def test_G_matches_central_finite_differences(arm, rng):
    assert_G_matches_finite_differences(arm, arm.sample_q(rng, 120))


def test_no_moment_arm_changes_sign_over_the_joint_range(arm):
    grid = np.stack(np.meshgrid(np.linspace(-1, 1, 21), np.linspace(-1, 1, 21)), -1).reshape(-1, 2)
    _, G, _ = arm.kinematics(grid)
    crossing = np.abs(G).max(axis=0) > 1e-9
    assert np.all((G.max(axis=0) <= 0) | (G.min(axis=0) >= 0) | ~crossing)
    assert crossing.sum() == 8  # 4 monoarticular + 2 biarticular x 2 joints


def test_tau_bias_is_mujoco_bias_force_at_rest(arm, rng):
    q = arm.sample_q(rng, 30)
    _, _, tau_bias = arm.kinematics(q)
    data = mujoco.MjData(arm.mj_model)
    for b in range(len(q)):
        data.qpos[:], data.qvel[:] = q[b], 0.0
        mujoco.mj_forward(arm.mj_model, data)
        # E^T (qfrc_bias - qfrc_passive) from MuJoCo's same bias forces: the joint map's product and a subtraction,
        # a few roundings at the torques' scale (~4e-14 N m at 11 N m); a joint's gravity torque missed is N m
        np.testing.assert_allclose(tau_bias[b], data.qfrc_bias, rtol=0, atol=rounding_tol(16, data.qfrc_bias))
    # gravity loads the joints: a bent arm needs a shoulder torque of several N m
    assert np.abs(tau_bias[:, 0]).max() > 3.0


def test_spring_inverse_and_values():
    delta = np.linspace(0, 0.01, 50)
    f = tension_from_elongation(delta, SPRING)
    np.testing.assert_allclose(elongation_from_tension(f, SPRING), delta, rtol=0, atol=spring_length_tol(delta))
    assert tension_from_elongation(np.array(-0.01), SPRING) == 0.0  # slack muscle carries no tension
    assert SPRING.delta_max_m == pytest.approx(np.log(1.15) / 20.0)


def test_every_sample_is_a_static_equilibrium(arm, healthy):
    l_geo, G, tau_bias = arm.kinematics(healthy.q)
    residual = np.einsum("bmn,bm->bn", -G, healthy.f) - tau_bias
    assert np.abs(residual).max() <= 1e-6
    assert healthy.f.min() >= 0.0 and healthy.f.max() <= SPRING.f_max_n
    np.testing.assert_allclose(healthy.l_motor + elongation_from_tension(healthy.f, SPRING), l_geo, atol=1e-9)
    lo, hi = arm.q_range.T
    assert np.all((healthy.q >= lo) & (healthy.q <= hi))


def test_qpsolvers_path_agrees_with_native_proxqp(arm, rng):
    from lightning_bodyschema.sim import solve_equilibrium_qp

    q = arm.sample_q(rng, 5)
    _, G, tau = arm.kinematics(q)
    f_ref = 150 * rng.random((5, arm.n_muscles))
    f_native, ok_native = solve_equilibrium_qp(G, tau, f_ref, f_hi_n=150.0)
    assert ok_native.all()
    from lightning_bodyschema.solvers import BoxQP, qpsolvers_solve

    # the same problem through qpsolvers' unified interface (proxqp backend) gives the same tensions
    f_qps, solved = qpsolvers_solve(BoxQP.build(G, tau, f_ref, 0.0, 150.0), "proxqp")
    assert solved.all()
    np.testing.assert_allclose(f_qps, f_native, atol=1e-4)
    with pytest.raises(BodySchemaInputError, match="unknown QP solver"):
        solve_equilibrium_qp(G, tau, f_ref, f_hi_n=150.0, solver="no_such_solver")


def test_infeasible_draws_are_refused(arm):
    """With f_max = 1 N nothing can hold the arm against gravity: a clear error, not bad data."""
    with pytest.raises(BodySchemaInputError, match="too weak"):
        generate_equilibrium_samples(arm, 20, seed=0, spring=SpringParams(f_max_n=1.0))


def test_model_with_failing_muscle_actuator_still_loads():
    xml = paper_arm_xml().replace("</tendon>", """<spatial name="rigid"><site site="o_shoulder_flex"/>
      <site site="o_shoulder_ext"/></spatial></tendon>
      <actuator><muscle name="m_rigid" tendon="rigid"/></actuator>""")
    with pytest.raises(ValueError, match="lengthrange"):
        mujoco.MjModel.from_xml_string(xml)  # MuJoCo itself refuses it ...
    paper_muscles = MusculoskeletalModel("paper_arm").muscle_names
    model = MusculoskeletalModel(xml, muscles=paper_muscles + ["rigid"])  # ... we drop actuators, keep the tendons
    assert model.mj_model.nu == 0 and "rigid" in model.muscle_names
    assert MusculoskeletalModel(xml, muscles=["shoulder_flexor", "elbow_flexor"]).n_muscles == 2


@pytest.mark.parametrize("source, message", [
    ("/no/such/model.xml", "does not exist"),
    ("<mujoco><worldbody><body></mujoco>", "does not parse"),
    ("<mujoco><worldbody><body><joint range='-1 1'/><geom size='.1'/></body></worldbody></mujoco>",
     "no spatial tendons"),
])
def test_bad_model_gives_one_clear_error(source, message):
    with pytest.raises(BodySchemaInputError, match=message):
        MusculoskeletalModel(source)


def test_unknown_muscle_name_lists_the_allowed_ones():
    with pytest.raises(BodySchemaInputError, match="shoulder_flexor"):
        MusculoskeletalModel("paper_arm", muscles=["biceps"])
