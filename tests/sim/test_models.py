"""Any tendon-driven MJCF: the packaged extra robots (3 joints / 8 muscles, OpenSim-style) work like the paper arm.

Everything the pipeline uses -- joint count, ranges, muscles -- must come from the model, and the
physics checks of tests/sim/test_sim.py must hold for each of them.
"""
import mujoco
import numpy as np
import pytest
from physics_checks import assert_drawn_muscles_match_mujoco, assert_G_matches_finite_differences

from lightning_bodyschema.errors import BodySchemaInputError
from lightning_bodyschema.sim import MusculoskeletalModel, SpringParams, generate_equilibrium_samples, paper_arm_xml
from lightning_bodyschema.sim.model import packaged_model_names, packaged_model_xml

# per-muscle f_max [N] for the OpenSim-style arm, as in configs/opensim_like-diff.yaml
OPENSIM_F_MAX_N = [200.0, 200.0, 150.0, 150.0, 120.0, 120.0]
EXTRA = {  # name -> (joints, muscles, spring)
    "arm3_8": (3, 8, SpringParams()),
    "opensim_like_arm": (2, 6, SpringParams(f_max_n=OPENSIM_F_MAX_N)),
}


@pytest.fixture(scope="module", params=sorted(EXTRA))
def robot(request):
    return request.param, MusculoskeletalModel(request.param)


def _xml_joint_ranges(name):
    """Joint ranges read straight from the packaged XML, without our loader."""
    spec = mujoco.MjSpec.from_string(packaged_model_xml(name))
    return np.array([j.range for j in spec.joints])


def _grid(model, n):
    lo, hi = model.q_range.T
    axes = [np.linspace(a, b, n) for a, b in zip(lo, hi)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, model.n_joints)


def test_packaged_models_are_listed_and_loadable():
    assert {"paper_arm", "arm3_8", "opensim_like_arm"} <= set(packaged_model_names())
    assert paper_arm_xml() == packaged_model_xml("paper_arm")
    with pytest.raises(BodySchemaInputError, match="arm3_8.*opensim_like_arm.*paper_arm"):
        MusculoskeletalModel("arm_9_joints")  # neither a packaged name nor a file: the error lists the names
    with pytest.raises(BodySchemaInputError, match="unknown packaged model 'arm_9_joints'"):
        packaged_model_xml("arm_9_joints")


def test_joints_and_ranges_come_from_the_model(robot, rng):
    name, model = robot
    n_joints, n_muscles, _ = EXTRA[name]
    assert (model.n_joints, model.n_muscles) == (n_joints, n_muscles)
    np.testing.assert_array_equal(model.q_range, _xml_joint_ranges(name))
    assert np.any(model.q_range.sum(axis=1) != 0)  # asymmetric ranges, unlike the paper arm's [-1, 1]
    q = model.sample_q(rng, 2000)
    lo, hi = model.q_range.T
    assert np.all((q >= lo) & (q <= hi))
    # the draw covers each range, not a symmetric stand-in for it
    assert np.all(q.min(axis=0) - lo < 0.02 * (hi - lo)) and np.all(hi - q.max(axis=0) < 0.02 * (hi - lo))


def test_arm3_8_has_the_documented_asymmetric_ranges():
    np.testing.assert_array_equal(MusculoskeletalModel("arm3_8").q_range, [[-0.5, 1.5], [0.0, 2.1], [-0.8, 0.8]])


def test_G_matches_central_finite_differences(robot, rng):
    _, model = robot
    h = 1e-6
    lo, hi = model.q_range.T
    q = lo + h + (hi - lo - 2 * h) * rng.random((50, model.n_joints))  # q +- h stays inside the range
    assert_G_matches_finite_differences(model, q, h)


def test_no_moment_arm_changes_sign_over_the_joint_range(robot):
    _, model = robot
    _, G, _ = model.kinematics(_grid(model, 21))
    crossing = np.abs(G).max(axis=0) > 1e-9  # (M, N): muscle m crosses joint n
    assert np.all((G.max(axis=0) <= 0) | (G.min(axis=0) >= 0) | ~crossing)
    # a crossed joint keeps a real lever everywhere (>= 1.5 cm), not just a sign
    assert np.all(np.where(crossing, np.abs(G).min(axis=0), 1.0) >= 0.015)
    assert crossing.any(axis=1).all() and crossing.any(axis=0).all()  # every muscle acts, every joint is driven


def test_gravity_loads_every_joint(robot, rng):
    _, model = robot
    _, _, tau_bias = model.kinematics(model.sample_q(rng, 200))
    assert np.all(np.abs(tau_bias).max(axis=0) > 0.1)  # N m, on every joint


def test_equilibrium_dataset_holds_and_respects_f_max(robot):
    name, model = robot
    spring = EXTRA[name][2]
    samples = generate_equilibrium_samples(model, 300, seed=0, spring=spring)
    _, G, tau_bias = model.kinematics(samples.q)
    residual_nm = np.einsum("bmn,bm->bn", -G, samples.f) - tau_bias
    assert np.abs(residual_nm).max() <= 1e-6
    f_max = np.broadcast_to(np.asarray(spring.f_max_n, float), (model.n_muscles,))
    assert samples.f.min() >= 0.0 and np.all(samples.f <= f_max)
    assert samples.n_redrawn <= 0.1 * 300  # the healthy QP is feasible over (nearly all of) the range
    lo, hi = model.q_range.T
    assert np.all((samples.q >= lo) & (samples.q <= hi))


def test_opensim_like_arm_fixed_tendon_is_not_a_muscle():
    model = MusculoskeletalModel("opensim_like_arm")
    assert model.mj_model.ntendon == 7 and model.n_muscles == 6
    assert "shoulder_elbow_coupling" not in model.muscle_names
    with pytest.raises(BodySchemaInputError, match="unknown muscle"):
        MusculoskeletalModel("opensim_like_arm", muscles=["shoulder_elbow_coupling"])


def test_opensim_like_arm_actuators_are_removed():
    xml = packaged_model_xml("opensim_like_arm")
    assert len(mujoco.MjSpec.from_string(xml).actuators) == 6
    with pytest.raises(ValueError, match="(?i)lengthrange"):
        mujoco.MjModel.from_xml_string(xml)  # MuJoCo alone refuses the file: one length range does not converge
    model = MusculoskeletalModel("opensim_like_arm")
    assert model.mj_model.nu == 0 and "<actuator" not in model.xml


def test_opensim_like_arm_wraps_a_sphere_and_a_cylinder():
    m = MusculoskeletalModel("opensim_like_arm").mj_model
    wrap_kinds = {int(t) for t in m.wrap_type}
    assert int(mujoco.mjtWrap.mjWRAP_SPHERE) in wrap_kinds and int(mujoco.mjtWrap.mjWRAP_CYLINDER) in wrap_kinds


@pytest.mark.parametrize("source, gravity", [
    ("paper_arm", [0.0, 0.0, -9.81]),  # along the hinge axes
    ("paper_arm", [0.0, 0.0, 0.0]),
    ("opensim_like_arm", [0.0, 9.81, 0.0]),  # along its hinge axes (world -y)
])
def test_gravity_that_loads_no_joint_is_refused(source, gravity):
    with pytest.raises(BodySchemaInputError, match="does not load the joints.*allow_unloaded"):
        MusculoskeletalModel(source, gravity=gravity)
    model = MusculoskeletalModel(source, gravity=gravity, allow_unloaded=True)  # the opt-out for those who know
    assert np.abs(model.kinematics(model.sample_q(np.random.default_rng(0), 5))[2]).max() < 1e-9


def test_drawn_muscle_paths_have_mujoco_tendon_length(robot, rng):
    """Arcs on spheres and cylinders are drawn the way MuJoCo wraps (see tests/sim/test_twin.py)."""
    _, model = robot
    assert_drawn_muscles_match_mujoco(model, model.sample_q(rng, 20))


def test_drawing_plane_is_the_plane_of_motion():
    from lightning_bodyschema.plots.arm import view_plane

    for name, labels in [("paper_arm", ("x [m]", "y [m]")), ("opensim_like_arm", ("x [m]", "z [m]"))]:
        m = MusculoskeletalModel(name).mj_model
        d = mujoco.MjData(m)
        mujoco.mj_kinematics(m, d)
        plane = view_plane(m, d)
        assert (plane.label(plane.right), plane.label(plane.up)) == labels
        np.testing.assert_allclose(plane.normal, d.xaxis[0], atol=1e-6)  # +q turns counter-clockwise


def test_datamodule_on_arm3_8_normalizes_q_ranges_to_unit_interval():
    import torch

    from lightning_bodyschema.data import EquilibriumDataModule

    dm = EquilibriumDataModule(model="arm3_8", n_samples=200, cache_dir=None)
    dm.setup("fit")
    q_range = torch.as_tensor(dm.robot_model.q_range)
    torch.testing.assert_close(dm.normalizer.encode_q(q_range.T),
                               torch.tensor([[-1.0] * 3, [1.0] * 3], dtype=torch.float64))
    q_train, x_train = dm.splits["train"]
    assert q_train.shape == (160, 3) and x_train.shape == (160, 16)
    q_n = dm.normalizer.encode_q(q_train)
    assert q_n.min() >= -1.0 and q_n.max() <= 1.0


def test_kinematics_on_threads_are_the_same_numbers():
    """Each thread has its own MjData; the answers do not depend on how postures are split among threads."""
    model = MusculoskeletalModel("opensim_like_arm")
    q = model.sample_q(np.random.default_rng(3), 200)
    one = model.kinematics(q)
    for threads in (2, 3):
        for a, b in zip(one, model.kinematics(q, threads=threads)):
            assert a.tobytes() == b.tobytes()


@pytest.mark.parametrize("threads", [0, -1, 1.5, True, "2"])
def test_a_bad_thread_count_is_refused(threads):
    model = MusculoskeletalModel("opensim_like_arm")
    with pytest.raises(BodySchemaInputError, match=r"threads=.*integer >= 1"):
        model.kinematics(np.zeros((1, model.n_joints)), threads=threads)
