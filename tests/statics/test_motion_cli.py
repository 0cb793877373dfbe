"""tools/static_opt.py --motion: a motion file in (CSV, NPZ, OpenSim .mot), one row per frame out with activations,
controls, tensions, residuals and statuses; the differentiator's accuracy on an analytic motion; --plot; --track
(computed muscle control in MuJoCo); bad input is one line, exit 2, and no file."""
from __future__ import annotations

import csv
import re

import numpy as np
import pytest
from physics_checks import rounding_tol

from lightning_bodyschema.apps.static_opt import static_opt_main
from lightning_bodyschema.npz import load_npz, save_npz

pytest.importorskip("myo_sim")
from lightning_bodyschema.statics import StaticBody, inverse_dynamics  # noqa: E402
from lightning_bodyschema.statics.differentiate import differentiate  # noqa: E402
from lightning_bodyschema.statics.track import track_motion  # noqa: E402

ELBOW = ["--model", "myo:myoelbow_2dof"]
JOINTS = ["r_shoulder_elev", "r_elbow_flex"]


def swing(step=0.002, seconds=2.0):
    """The forearm swinging 0.8 +- 0.5 rad at 0.5 Hz, the upper arm 0.1 +- 0.05 rad: every frame held within full
    activation by the healthy elbow."""
    t = np.arange(0.0, seconds + step / 2, step)
    mid, amp, w = np.array([0.1, 0.8]), np.array([0.05, 0.5]), np.pi
    phase = w * t[:, None]
    return t, mid + amp * np.sin(phase), amp * w * np.cos(phase), -amp * w ** 2 * np.sin(phase)


@pytest.fixture(scope="module")
def elbow():
    return StaticBody("myo:myoelbow_2dof")


@pytest.fixture(autouse=True)
def built_once(monkeypatch, elbow):
    import lightning_bodyschema.statics as statics

    real = statics.StaticBody
    monkeypatch.setattr(statics, "StaticBody", lambda source, **o: elbow if source == ELBOW[1] else real(source, **o))


def _csv(path, t, q, extra=None):
    columns = {"t": t, **{j: q[:, k] for k, j in enumerate(JOINTS)}, **(extra or {})}
    path.write_text(",".join(columns) + "\n" + "\n".join(",".join(repr(float(v)) for v in row)
                                                        for row in zip(*columns.values())) + "\n")
    return str(path)


def test_csv_motion_round_trip_matches_the_library(tmp_path):
    """Given derivatives: the file's rows are the library's answer exactly (repr floats), residuals included."""
    t, q, qvel, qacc = swing()
    extra = {f"qvel_{j}": qvel[:, k] for k, j in enumerate(JOINTS)} | {f"qacc_{j}": qacc[:, k]
                                                                       for k, j in enumerate(JOINTS)}
    out, plot = tmp_path / "out.csv", tmp_path / "act.png"
    static_opt_main(ELBOW + ["--motion", _csv(tmp_path / "m.csv", t, q, extra), "--residual", "r_elbow_flex",
                             "--out", str(out), "--plot", str(plot), "--no-progress"])
    rows = list(csv.DictReader(out.open()))
    expected = inverse_dynamics("myo:myoelbow_2dof", q, qvel, qacc, t=t, residual_dofs=["r_elbow_flex"])
    assert len(rows) == len(t) and [r["status"] for r in rows] == [str(s) for s in expected.status]
    for label, values in (("activation", expected.activation), ("control", expected.control),
                          ("tension_n", expected.tension_n)):
        got = np.array([[float(r[f"{m}.{label}"]) for m in expected.muscles] for r in rows])
        np.testing.assert_array_equal(got, values)
    np.testing.assert_array_equal([float(r["r_elbow_flex.residual_nm"]) for r in rows], expected.residual_nm[:, 0])
    assert plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_derivatives_by_the_differentiator_and_from_a_mot_in_degrees(tmp_path):
    """No derivative columns: the Savitzky-Golay derivatives (within 1e-5 rad/s and 1e-2 rad/s^2 of the analytic ones
    here: 0.2 % of the 4.9 rad/s^2 peak; measured 3.8e-6 and 2.2e-3); a .mot in degrees with an extra coordinate gives
    the CSV's answer."""
    t, q, qvel, qacc = swing()
    velocity, acceleration = differentiate(t, q)
    assert np.abs(velocity - qvel).max() < 1e-5 and np.abs(acceleration - qacc).max() < 1e-2
    mot = tmp_path / "m.mot"
    header = "swing\nversion=1\nnRows={}\nnColumns=4\ninDegrees=yes\nendheader\ntime\tr_shoulder_elev\tr_elbow_flex\t" \
             "pelvis_tx\n".format(len(t))
    rows = np.column_stack([t, np.rad2deg(q), np.zeros_like(t)])
    mot.write_text(header + "".join("\t".join(repr(float(v)) for v in row) + "\n" for row in rows))
    static_opt_main(ELBOW + ["--motion", str(mot), "--out", str(tmp_path / "mot.npz"), "--no-progress"])
    static_opt_main(ELBOW + ["--motion", _csv(tmp_path / "m.csv", t, q), "--out", str(tmp_path / "csv.npz"),
                             "--no-progress"])
    from_mot, from_csv = load_npz(str(tmp_path / "mot.npz")), load_npz(str(tmp_path / "csv.npz"))
    # degrees written as repr's exact floats and read back to radians: a rounding or two at the angles' scale;
    # degrees taken for radians are off 57-fold
    np.testing.assert_allclose(from_mot["q"], q, rtol=0, atol=rounding_tol(4, q))
    np.testing.assert_allclose(from_mot["activation"], from_csv["activation"], atol=1e-9)
    # the CSV holds repr's exact floats: the tool differentiates the same q by the same filter, bit for bit
    np.testing.assert_array_equal(from_csv["qacc"], acceleration)


def test_tracking_follows_the_motion_and_a_fall_is_reported(elbow):
    """Computed muscle control follows the swing within 0.02 rad RMS (2 ms control step) and open loop drifts more;
    with every elbow flexor cut nothing holds the arm and the error is large (the check can fail)."""
    motion = swing()
    report = track_motion(elbow, *motion)
    assert report.rms_rad < 0.02 and not report.failed.any()
    assert report.open_loop_rms_rad > report.rms_rad
    cut = track_motion(elbow, *motion, faults={"cut": ["BIClong_tendon", "BICshort_tendon", "BRA_tendon"]})
    assert cut.failed.all() and cut.rms_rad > 0.1


@pytest.mark.parametrize("args, match", [
    (["--postures", "P", "--track"], "--track needs --motion"),
    (["--motion", "missing.csv"], "--motion 'missing.csv' does not exist"),
    (["--motion", "NO_T"], "no 't' column"),
    (["--motion", "HALF_QVEL"], r"qvel_<joint> columns miss \['r_elbow_flex'\]"),
    (["--motion", "UNEVEN"], "not evenly spaced"),
    (["--motion", "M", "--residual", "pelvis_tx"], r"residual_dofs \['pelvis_tx'\]"),
    (["--motion", "M", "--smooth-window", "-1"], "window is -1.0 s"),
])
def test_bad_input_is_one_line_and_no_file(tmp_path, capsys, args, match):
    t, q, qvel, _ = swing(seconds=0.2)
    files = {"P": _csv(tmp_path / "p.csv", t, q), "M": _csv(tmp_path / "m.csv", t, q),
             "NO_T": str(tmp_path / "no_t.npz"), "HALF_QVEL": _csv(tmp_path / "h.csv", t, q,
                                                                  {"qvel_r_shoulder_elev": qvel[:, 0]}),
             "UNEVEN": _csv(tmp_path / "u.csv", t ** 1.1, q)}
    save_npz(files["NO_T"], **{j: q[:, k] for k, j in enumerate(JOINTS)})
    args = [files.get(a, a) for a in args]
    out = tmp_path / "out.csv"
    with pytest.raises(SystemExit) as exit_info:
        static_opt_main(ELBOW + args + ["--out", str(out), "--no-progress"])
    err = capsys.readouterr().err
    assert exit_info.value.code == 2 and len(err.strip().splitlines()) == 1
    assert re.search(match, err) and not out.exists()


@pytest.mark.slow
def test_myoarm_reach_tracks_and_mujoco_follows():
    """The held-out-style myoArm reach (tools/bench_static_opt.py --motion): MuJoCo's forward acceleration is the
    requested one on every ok frame (through the config's locks and the wrist's couplings), and computed muscle
    control tracks it within 0.02 rad RMS at a 2 ms control step."""
    import sys
    from pathlib import Path

    import yaml

    from lightning_bodyschema.statics.check import mujoco_motion_error

    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tools"))
    from bench_static_opt import reach

    with open("configs/myoarm.yaml") as fh:
        locks = yaml.safe_load(fh)["data"]["locked_joints"]
    body = StaticBody("myo:myoarm", locked_joints=locks)
    motion = reach(body)
    result = inverse_dynamics(body, *motion[1:], t=motion[0])
    sample = result.take(np.arange(0, len(result.q), 20))
    assert sample.ok.all() and np.abs(mujoco_motion_error(body, sample)).max() <= 1e-6
    assert track_motion(body, *motion).rms_rad < 0.02
