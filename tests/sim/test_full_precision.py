"""The stored body is the body MyoSuite loads, to the last bit (issue 50, item 1).

MuJoCo's XML writer keeps 6 significant digits; a MyoSuite body's compiled masses, centres of mass and frames
(computed from meshes) were stored rounded, moving gravity torques by up to 1.6e-5 N m. Here the model MyoSuite
builds from the myo-sim package files and the model compiled from our stored XML are compared at random postures.
"""
import warnings

import mujoco
import numpy as np
import pytest

from lightning_bodyschema.sim import MusculoskeletalModel
from lightning_bodyschema.sim.mjcf import (full_precision_xml, quiet_attach_warnings, same_compiled_model,
                                           self_contained_xml)

RTOL = 1e-15  # a few units in the last place of a double; the 6-digit copy was off by up to 5e-6
N_POSTURES = 50


def _myosuite_model(name: str) -> mujoco.MjModel:
    """The model MyoSuite loads: myo-sim's own spec of ``name``, compiled."""
    myo_sim = pytest.importorskip("myo_sim")
    with quiet_attach_warnings(), warnings.catch_warnings():
        warnings.simplefilter("ignore")  # myo-sim's composition: "Attaching a spec with an empty prefix"
        return myo_sim.load_spec(name).compile()


def _ids(m: mujoco.MjModel, obj, names) -> np.ndarray:
    return np.array([mujoco.mj_name2id(m, obj, n) for n in names])


def _random_qpos(m: mujoco.MjModel, rng, n: int) -> np.ndarray:
    """(n, nq) postures: every limited hinge and slide joint uniform in its range, the rest at qpos0."""
    qpos = np.tile(m.qpos0, (n, 1))
    for j in np.flatnonzero(np.isin(m.jnt_type, [mujoco.mjtJoint.mjJNT_HINGE, mujoco.mjtJoint.mjJNT_SLIDE])
                            & m.jnt_limited.astype(bool)):
        qpos[:, m.jnt_qposadr[j]] = rng.uniform(*m.jnt_range[j], n)
    return qpos


def _within(ours: np.ndarray, theirs: np.ndarray, what: str):
    """Each row within RTOL of its magnitude (exact zeros, e.g. a tendon not spanning a joint, stay zero)."""
    scale = np.abs(theirs).max(axis=-1, keepdims=True)
    worst = (np.abs(ours - theirs) / np.where(scale > 0, scale, 1)).max()
    assert worst <= RTOL, f"{what}: off by {worst:.3g} of its scale"


@pytest.mark.parametrize("name", ["myoelbow_2dof", "myoarm"])
def test_stored_body_is_the_body_myosuite_loads(name):
    theirs = _myosuite_model(name)
    ours = MusculoskeletalModel(f"myo:{name}", allow_unloaded=True).mj_model
    bodies = _ids(theirs, mujoco.mjtObj.mjOBJ_BODY, [ours.body(i).name for i in range(ours.nbody)])
    for field in ("body_mass", "body_inertia", "body_ipos", "body_iquat", "body_pos", "body_quat"):
        np.testing.assert_array_equal(getattr(ours, field), getattr(theirs, field)[bodies], err_msg=field)
    sites = _ids(theirs, mujoco.mjtObj.mjOBJ_SITE, [ours.site(i).name for i in range(ours.nsite)])
    np.testing.assert_array_equal(ours.site_pos, theirs.site_pos[sites])  # the tendons' path points

    joints = [ours.joint(j).name for j in range(ours.njnt)]
    dof_ours = ours.jnt_dofadr[np.arange(ours.njnt)]
    dof_theirs = theirs.jnt_dofadr[_ids(theirs, mujoco.mjtObj.mjOBJ_JOINT, joints)]
    tendons = _ids(theirs, mujoco.mjtObj.mjOBJ_TENDON, [ours.tendon(t).name for t in range(ours.ntendon)])
    qpos_theirs = _random_qpos(theirs, np.random.default_rng(0), N_POSTURES)
    qpos_ours = qpos_theirs[:, theirs.jnt_qposadr[_ids(theirs, mujoco.mjtObj.mjOBJ_JOINT, joints)]]
    d_ours, d_theirs = mujoco.MjData(ours), mujoco.MjData(theirs)
    for q_o, q_t in zip(qpos_ours, qpos_theirs):
        d_ours.qpos[ours.jnt_qposadr], d_theirs.qpos[:] = q_o, q_t
        mujoco.mj_forward(ours, d_ours)
        mujoco.mj_forward(theirs, d_theirs)
        _within(d_ours.qfrc_bias[dof_ours], d_theirs.qfrc_bias[dof_theirs], "gravity torque qfrc_bias")
        _within(d_ours.ten_length, d_theirs.ten_length[tendons], "tendon length")
        J_theirs = _dense_ten_J(theirs, d_theirs)[np.ix_(tendons, dof_theirs)]
        _within(_dense_ten_J(ours, d_ours)[:, dof_ours], J_theirs, "moment arm ten_J")


def _dense_ten_J(m: mujoco.MjModel, d: mujoco.MjData) -> np.ndarray:
    """(ntendon, nv) moment arms from MuJoCo's ten_J, dense or sparse (rows by ten_J_rowadr/rownnz/colind)."""
    if d.ten_J.size == m.ntendon * m.nv:
        return d.ten_J.reshape(m.ntendon, m.nv).copy()
    dense = np.zeros((m.ntendon, m.nv))
    for t in range(m.ntendon):
        cols = slice(m.ten_J_rowadr[t], m.ten_J_rowadr[t] + m.ten_J_rownnz[t])
        dense[t, m.ten_J_colind[cols]] = d.ten_J[cols]
    return dense


def test_six_digits_would_have_moved_the_body():
    """The comparison above can fail: MuJoCo's default 6-digit text of the same body moves myoElbow's masses."""
    pytest.importorskip("myo_sim")
    spec = mujoco.MjSpec.from_string(MusculoskeletalModel("myo:myoelbow_2dof").xml)
    spec.compile()
    with full_precision_xml():
        exact = mujoco.MjModel.from_xml_string(spec.to_xml())
    rounded = mujoco.MjModel.from_xml_string(spec.to_xml())
    assert not same_compiled_model(exact, rounded)
    assert np.abs(exact.body_mass - rounded.body_mass).max() > 1e3 * RTOL * exact.body_mass.max()


@pytest.mark.parametrize("source", ["paper_arm", "opensim_like_arm", "myo:myoelbow_2dof"])
def test_a_stored_body_rebuilds_to_its_own_text(source):
    """A checkpoint's body, read back, is stored again as the same text: its hash names the same robot."""
    if source.startswith("myo:"):
        pytest.importorskip("myo_sim")
    model = MusculoskeletalModel(source, allow_unloaded=True)
    assert self_contained_xml(mujoco.MjSpec.from_string(model.xml)) == model.xml


def test_a_body_rounding_never_moved_keeps_its_six_digit_text():
    """The paper arm compiles to the same model from MuJoCo's 6-digit text (its numbers are short): that text,
    the one every earlier release stored, stays, so checkpoints trained on it still name their robot."""
    xml = MusculoskeletalModel("paper_arm").xml
    spec = mujoco.MjSpec.from_string(xml)
    spec.compile()
    assert xml == spec.to_xml()
    assert 'quat="0.707107 -0.707107 0 0"' in xml  # a normalized quaternion, 6 digits: it recompiles to itself


def test_without_the_precision_hook_the_text_is_written_and_the_loss_named(monkeypatch):
    """A MuJoCo build without the writer's precision hook still stores the body, rounded, and says so."""
    from lightning_bodyschema.sim import mjcf

    monkeypatch.setattr(mjcf, "_mujoco_precision_hooks", lambda: None)
    with pytest.warns(RuntimeWarning, match="6 significant digits"):
        xml = MusculoskeletalModel("paper_arm").xml
    monkeypatch.undo()
    assert xml == MusculoskeletalModel("paper_arm").xml  # the paper arm's text never depended on the hook
