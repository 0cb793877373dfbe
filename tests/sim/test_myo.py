"""MyoSuite bodies (issue 15): loading by name, self-contained XML, muscles from actuators, couplings, locks.

Tests that need MyoSuite's models skip without myo-sim (CI installs it, see .ci/run); the coupling and
lock tests use small MJCF written here, so they always run.
"""
import os
import subprocess
import sys
import textwrap

import mujoco
import numpy as np
import pytest

from lightning_bodyschema.errors import BodySchemaInputError
from lightning_bodyschema.sim import MusculoskeletalModel

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


@pytest.fixture(scope="module")
def myoelbow():
    pytest.importorskip("myo_sim")
    return MusculoskeletalModel("myo:myoelbow_2dof")


@pytest.fixture(scope="module")
def myoarm():
    pytest.importorskip("myo_sim")
    return MusculoskeletalModel("myo:myoarm")


def _run_without_myo_sim(code: str) -> subprocess.CompletedProcess:
    """Run python code in a fresh process where ``import myo_sim`` fails (sys.modules entry None)."""
    prelude = "import sys; sys.modules['myo_sim'] = None\n"
    env = {**os.environ, "PYTHONPATH": REPO, "OMP_NUM_THREADS": "1"}
    return subprocess.run([sys.executable, "-c", prelude + textwrap.dedent(code)], capture_output=True, text=True,
                          env=env, cwd=REPO, timeout=300)


def test_myo_model_without_myo_sim_names_the_extra():
    out = _run_without_myo_sim("""
        from lightning_bodyschema.errors import BodySchemaInputError
        from lightning_bodyschema.sim import MusculoskeletalModel
        try:
            MusculoskeletalModel("myo:myoelbow_2dof")
        except BodySchemaInputError as err:
            print(err)
        """)
    assert out.returncode == 0, out.stderr
    assert 'pip install -e ".[myo]"' in out.stdout and "myo-sim" in out.stdout


def test_unknown_myo_name_lists_the_known_ones():
    pytest.importorskip("myo_sim")
    with pytest.raises(BodySchemaInputError, match="myo:no_such_body.*myoelbow_2dof"):
        MusculoskeletalModel("myo:no_such_body")


def test_stored_xml_is_self_contained(myoarm):
    xml = myoarm.xml
    assert "<include" not in xml and "file=" not in xml and "<mesh" not in xml and "meshdir" not in xml
    m = myoarm.mj_model
    assert m.nmesh == 0 and m.ntex == 0 and m.nmat == 0
    assert m.neq >= 11  # the shoulder girdle couplings survive


def test_self_contained_elbow_keeps_the_physics_of_myo_sim(myoelbow, rng):
    """The stripped XML (explicit inertias, no meshes) gives myo-sim's own model's kinematics and gravity."""
    import myo_sim

    spec = myo_sim.load_spec("myoelbow_2dof")
    for actuator in list(spec.actuators):
        spec.delete(actuator)
    m0 = spec.compile()
    q = myoelbow.sample_q(rng, 100)
    l_geo, _, tau = myoelbow.kinematics(q)
    d = mujoco.MjData(m0)
    ids = [mujoco.mj_name2id(m0, mujoco.mjtObj.mjOBJ_TENDON, n) for n in myoelbow.muscle_names]
    for b in range(len(q)):
        d.qpos[:] = q[b]
        mujoco.mj_forward(m0, d)
        np.testing.assert_allclose(d.ten_length[ids], l_geo[b], atol=1e-6)  # XML writes ~9 digits
        np.testing.assert_allclose(d.qfrc_bias, tau[b], atol=1e-5 * max(1.0, np.abs(tau[b]).max()))


def test_checkpoint_xml_rebuilds_the_same_robot_without_myo_sim(myoarm, tmp_path):
    """A robot saved as its XML text is rebuilt exactly in a process that cannot import myo-sim."""
    rng = np.random.default_rng(7)
    q = myoarm.sample_q(rng, 100)
    l_geo, G, tau = myoarm.kinematics(q)
    np.savez(tmp_path / "robot.npz", xml=np.array(myoarm.xml), muscles=np.array(myoarm.muscle_names), q=q)
    out = _run_without_myo_sim(f"""
        import numpy as np
        from lightning_bodyschema.sim import MusculoskeletalModel
        a = np.load({str(tmp_path / "robot.npz")!r})
        model = MusculoskeletalModel(str(a["xml"]), muscles=[str(n) for n in a["muscles"]])
        l_geo, G, tau = model.kinematics(a["q"])
        np.savez({str(tmp_path / "rebuilt.npz")!r}, l_geo=l_geo, G=G, tau=tau)
        """)
    assert out.returncode == 0, out.stderr
    rebuilt = np.load(tmp_path / "rebuilt.npz")
    np.testing.assert_allclose(rebuilt["l_geo"], l_geo, atol=1e-9, rtol=0)
    np.testing.assert_allclose(rebuilt["G"], G, atol=1e-9, rtol=0)
    np.testing.assert_allclose(rebuilt["tau"], tau, atol=1e-9, rtol=0)


def test_ligaments_are_not_muscles_by_default(myoarm):
    names = myoarm.muscle_names
    assert myoarm.n_muscles == 63 and not any("ligament" in n for n in names)
    tendons = [mujoco.mj_id2name(myoarm.mj_model, mujoco.mjtObj.mjOBJ_TENDON, i)
               for i in range(myoarm.mj_model.ntendon)]
    assert sum("ligament" in t for t in tendons) == 4  # still in the model, just not muscles
    explicit = MusculoskeletalModel(myoarm.xml, muscles=["s_glenohum_ligament", "DELT1_tendon"])
    assert explicit.muscle_names == ["s_glenohum_ligament", "DELT1_tendon"]


def test_peak_forces_come_from_the_actuators(myoelbow):
    import myo_sim

    m = myo_sim.load_spec("myoelbow_2dof").compile()
    expected = {mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_TENDON, int(m.actuator_trnid[a, 0])): m.actuator_gainprm[a, 2]
                for a in range(m.nu)}
    np.testing.assert_array_equal(myoelbow.actuator_f_max_n, [expected[n] for n in myoelbow.muscle_names])
    assert len(set(myoelbow.actuator_f_max_n)) > 1  # per muscle, not one value
