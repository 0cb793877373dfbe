"""Every MyoSuite body (issue 27): the stored XML drops what it must with the meshes, floating bases are held.

The MJCF written here always runs; the tests on MyoSuite's own models skip without myo-sim.
"""
import os

import mujoco
import numpy as np
import pytest

from lightning_bodyschema.errors import BodySchemaInputError
from lightning_bodyschema.sim import MusculoskeletalModel

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

# a hanging two-link leg on a floating pelvis; the shin's collision shape is a mesh named by a contact pair
FLOATING_LEG = """<mujoco><compiler angle="radian"/><option gravity="0 0 -9.81"/>
  <asset><mesh name="shin" vertex="0 0 0  0.05 0 0  0 0.05 0  0 0 -0.3"/></asset>
  <worldbody><body name="pelvis" pos="0 0 1"><freejoint name="root"/>
      <geom name="pelvis" type="box" size="0.1 0.1 0.05" mass="5"/>
      <site name="p_front" pos="0.05 0 -0.02"/><site name="p_back" pos="-0.05 0 -0.02"/>
      <body name="thigh" pos="0 0 -0.05"><joint name="hip" axis="0 1 0" range="-1 1"/>
        <geom name="thigh" type="capsule" fromto="0 0 0 0 0 -0.4" size="0.04" mass="3"/>
        <site name="t_front" pos="0.04 0 -0.1"/><site name="t_back" pos="-0.04 0 -0.1"/>
        <site name="k_front" pos="0.04 0 -0.3"/><site name="k_back" pos="-0.04 0 -0.3"/>
        <body name="shin" pos="0 0 -0.4"><joint name="knee" axis="0 1 0" range="-1.5 0"/>
          <geom name="shin_mesh" type="mesh" mesh="shin" mass="2"/>
          <geom name="shin_col" type="capsule" fromto="0 0 0 0 0 -0.3" size="0.03" contype="0" conaffinity="0"/>
          <site name="s_front" pos="0.04 0 -0.08"/><site name="s_back" pos="-0.04 0 -0.08"/>
        </body></body></body></worldbody>
  <contact><pair geom1="shin_mesh" geom2="pelvis"/><pair geom1="shin_col" geom2="pelvis"/>
    <exclude body1="thigh" body2="shin"/></contact>
  <tendon><spatial name="hip_f"><site site="p_front"/><site site="t_front"/></spatial>
    <spatial name="hip_b"><site site="p_back"/><site site="t_back"/></spatial>
    <spatial name="knee_f"><site site="k_front"/><site site="s_front"/></spatial>
    <spatial name="knee_b"><site site="k_back"/><site site="s_back"/></spatial></tendon></mujoco>"""


def test_contact_pairs_on_dropped_mesh_geoms_go_with_them():
    """myolegs_osl failed to load: "geom 'osl_proximal_adapter_geom_1' not found in collision 4"."""
    model = MusculoskeletalModel(FLOATING_LEG, fixed_base=True)
    m = model.mj_model
    assert m.nmesh == 0 and m.npair == 1 and m.nexclude == 1  # the pair on primitives and the exclude stay
    pair = {mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_GEOM, int(g)) for g in (m.pair_geom1[0], m.pair_geom2[0])}
    assert pair == {"shin_col", "pelvis"}
    assert "shin_mesh" not in model.xml and "<mesh" not in model.xml


def _potential_energy(model, q):
    m = model.mj_model
    d = mujoco.MjData(m)
    m.opt.enableflags |= int(mujoco.mjtEnableBit.mjENBL_ENERGY)
    d.qpos[:] = q[0]
    mujoco.mj_forward(m, d)
    m.opt.enableflags &= ~int(mujoco.mjtEnableBit.mjENBL_ENERGY)
    return d.energy[0]


def test_a_free_joint_is_refused_naming_the_option_and_fixed_base_welds_it_at_the_reference_pose():
    with pytest.raises(BodySchemaInputError, match=r"\['root'\] are free joints.*fixed_base=True.*data.fixed_base"):
        MusculoskeletalModel(FLOATING_LEG)
    model = MusculoskeletalModel(FLOATING_LEG, fixed_base=True)
    assert model.joint_names == ["hip", "knee"] and model.mj_model.nq == 2
    pelvis = mujoco.mj_name2id(model.mj_model, mujoco.mjtObj.mjOBJ_BODY, "pelvis")
    d = mujoco.MjData(model.mj_model)
    mujoco.mj_kinematics(model.mj_model, d)
    np.testing.assert_array_equal(d.xpos[pelvis], [0, 0, 1])  # where the MJCF puts it
    # the held base carries the leg: tau_bias is the hanging leg's gravity torque d V / d q (central differences)
    q, h = np.array([[0.4, -0.7]]), 1e-6
    tau = model.kinematics(q)[2][0]
    fd = [(_potential_energy(model, q + h * e) - _potential_energy(model, q - h * e)) / (2 * h) for e in np.eye(2)]
    np.testing.assert_allclose(tau, fd, atol=1e-6)
    assert np.abs(tau).min() > 0.1  # [N m]: gravity loads both joints
    rebuilt = MusculoskeletalModel(model.xml)  # the stored XML needs no option
    assert rebuilt.xml == model.xml
    np.testing.assert_allclose(rebuilt.kinematics(q)[2], model.kinematics(q)[2], atol=0)


def test_a_ball_joint_is_refused_saying_what_to_do():
    xml = FLOATING_LEG.replace('<joint name="knee" axis="0 1 0" range="-1.5 0"/>', '<joint name="knee" type="ball"/>')
    with pytest.raises(BodySchemaInputError, match=r"\['knee'\] are ball joints.*three hinge joints"):
        MusculoskeletalModel(xml, fixed_base=True)


def test_myolegs_osl_loads():
    pytest.importorskip("myo_sim")
    model = MusculoskeletalModel("myo:myolegs_osl", fixed_base=True)
    assert model.mj_model.npair > 0 and model.n_joints > 0 and model.n_muscles > 0


@pytest.mark.parametrize("config", ["myoelbow-diff.yaml", "myoarm-diff.yaml"])
def test_exact_equilibrium_commands_settle_on_myosuite_bodies(config):
    """The oracle's commands (exact static equilibria) come to rest at their posture. On myoArm every case read
    NOT_SETTLED: the constraint solver's early stop made the free joints jitter around the couplings."""
    pytest.importorskip("myo_sim")
    from lightning_bodyschema.apps.common import robot_from_config
    from lightning_bodyschema.sim import generate_equilibrium_samples
    from lightning_bodyschema.sim.settle import SettleParams, settle

    model, spring, _ = robot_from_config(os.path.join(REPO, "configs", config))
    samples = generate_equilibrium_samples(model, 12, seed=0, spring=spring)
    _, G, tau = model.kinematics(samples.q)
    assert np.abs(np.einsum("bmn,bm->bn", -G, samples.f) - tau).max() <= 1e-6  # exact equilibria [N m]
    params = SettleParams()
    out = settle(model, samples.l_motor, samples.f, samples.q, spring=spring, params=params)
    assert out.status_names == ["SETTLED"] * 12
    assert np.abs(out.qvel_rad_s).max() < params.qvel_tol_rad_s
    assert out.E_q_phys.max() < 1e-3  # [rad]: the rest posture is the commanded one (couplings' softness aside)


def test_make_dataset_holds_a_floating_base_when_asked(tmp_path, capsys):
    from lightning_bodyschema.apps.dataset_tool import make_dataset_main
    from lightning_bodyschema.data import read_recorded

    path = tmp_path / "leg.xml"
    path.write_text(FLOATING_LEG)
    with pytest.raises(SystemExit) as exit_info:
        make_dataset_main(["--model", str(path), "--n", "10", "--out", str(tmp_path / "leg.npz")])
    errors = capsys.readouterr().err.strip().splitlines()
    assert exit_info.value.code == 2 and len(errors) == 1 and "fixed_base" in errors[0]
    make_dataset_main(["--model", str(path), "--fixed-base", "--n", "10", "--out", str(tmp_path / "leg.npz"),
                       "--seed", "1"])
    table = read_recorded(str(tmp_path / "leg.npz"))
    model = MusculoskeletalModel(FLOATING_LEG, fixed_base=True)
    assert table.joints == model.joint_names
    _, G, tau = model.kinematics(table.q)
    assert np.abs(np.einsum("bmn,bm->bn", -G, table.f) - tau).max() <= 1e-6
