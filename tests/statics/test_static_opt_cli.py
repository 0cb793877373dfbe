"""tools/static_opt.py: postures in, one row per posture out (named by muscle, status as name and code); bad input is
one line, exit 2, and no file."""
from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from lightning_bodyschema.apps.static_opt import static_opt_main
from lightning_bodyschema.npz import load_npz, save_npz
from lightning_bodyschema.status import Status

pytest.importorskip("myo_sim")
ROOT = Path(__file__).resolve().parents[2]
ELBOW = ["--model", "myo:myoelbow_2dof"]


@pytest.fixture(autouse=True)
def built_once(monkeypatch):
    """The tool builds its body through ``statics.StaticBody``; build the elbow once for the whole module."""
    import lightning_bodyschema.statics as statics

    cache, real = _BODIES, statics.StaticBody

    def cached(source, **options):
        key = (source, repr(sorted(options.items())))
        if key not in cache:
            cache[key] = real(source, **options)
        return cache[key]

    monkeypatch.setattr(statics, "StaticBody", cached)


_BODIES: dict = {}


def _postures_csv(path, rows, header=("r_shoulder_elev", "r_elbow_flex")):
    path.write_text(",".join(header) + "\n" + "".join(",".join(str(v) for v in row) + "\n" for row in rows))
    return str(path)


def test_csv_round_trip_matches_the_library(tmp_path):
    from lightning_bodyschema.statics import static_optimization

    q = np.array([[0.0, 0.3], [0.2, 1.0], [0.4, 1.6]])
    out = tmp_path / "out.csv"
    static_opt_main(ELBOW + ["--postures", _postures_csv(tmp_path / "q.csv", q), "--cut", "BRA_tendon",
                             "--out", str(out), "--no-progress"])
    rows = list(csv.DictReader(out.open()))
    expected = static_optimization("myo:myoelbow_2dof", q, faults={"cut": ["BRA_tendon"]})
    assert [r["status"] for r in rows] == [str(s) for s in expected.status]
    assert [int(r["status_code"]) for r in rows] == [Status(s).code for s in expected.status]
    got = np.array([[float(r[f"{m}.tension_n"]) for m in expected.muscles] for r in rows])
    np.testing.assert_array_equal(got, expected.tension_n)  # repr(float): exact
    assert all(float(r["BRA_tendon.tension_n"]) == 0.0 for r in rows)


def test_npz_with_faults_file(tmp_path):
    faults = tmp_path / "faults.json"
    faults.write_text(json.dumps({"cut": ["BRA_tendon"], "weak": {"TRIlat_tendon": 150.0}}))
    postures = tmp_path / "q.npz"
    save_npz(str(postures), q_r_shoulder_elev=np.zeros(4), q_r_elbow_flex=np.linspace(0.3, 1.5, 4))
    out = tmp_path / "out.npz"
    static_opt_main(ELBOW + ["--postures", str(postures), "--faults", str(faults), "--out", str(out),
                             "--no-progress"])
    arrays = load_npz(str(out))
    assert arrays["muscles"].tolist()[5] == "BRA_tendon" and (arrays["tension_n"][:, 5] == 0).all()
    held = np.isfinite(arrays["tension_n"][:, 1])
    assert held.any() and (arrays["tension_n"][held, 1] <= 150.0 + 1e-9).all()
    assert arrays["activation"].shape == (4, 6) and arrays["status_code"].dtype == np.int32


@pytest.mark.parametrize("columns, rows, extra, match", [
    (("r_shoulder_elev", "r_elbow_flex"), [[0.0, 9.0]], [], "r_elbow_flex.*outside its range"),
    (("r_shoulder_elev", "r_elbow_flex"), [[0.0, 1.0], [0.0, "nan"]], [], "row 2 .*, joint 'r_elbow_flex' is nan"),
    (("r_shoulder_elev",), [[0.0]], [], r"missing columns \['r_elbow_flex'\]"),
    (("r_shoulder_elev", "r_elbow_flex", "wrist"), [[0.0, 1.0, 0.0]], [], r"columns \['wrist'\] are not free joints"),
    (("r_shoulder_elev", "r_elbow_flex"), [[0.0, 1.0]], ["--cut", "BRAx"], "unknown muscle 'BRAx'"),
    (("r_shoulder_elev", "r_elbow_flex"), [[0.0, 1.0]], ["--cut", "BRA"], r"'BRA' \(did you mean 'BRA_tendon'\?\)"),
    (("r_shoulder_elev", "r_elbw_flex"), [[0.0, 1.0]], [], r"did you mean 'r_elbow_flex'\?"),
    (("r_shoulder_elev", "r_elbow_flex"), [[0.0, 1.0]], ["--weak", "BRA_tendon"], "expected NAME=NUMBER"),
    (("r_shoulder_elev", "r_elbow_flex"), [[0.0, 1.0]], ["--threads", "0"], r"threads=0; give an integer >= 1"),
])
def test_bad_input_exits_2_with_one_line_and_no_file(tmp_path, capsys, columns, rows, extra, match):
    out = tmp_path / "out.csv"
    with pytest.raises(SystemExit) as stop:
        static_opt_main(ELBOW + ["--postures", _postures_csv(tmp_path / "q.csv", rows, columns), "--out", str(out),
                                 "--no-progress"] + extra)
    assert stop.value.code == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error:") and "\n" not in err and __import__("re").search(match, err), err
    assert list(tmp_path.iterdir()) == [tmp_path / "q.csv"]  # nothing written, not even a temporary file


def test_a_misspelt_muscle_is_refused_before_the_body_is_built_once_the_body_is_known(tmp_path, capsys):
    """The first run remembers the body's names; the next refuses a misspelt one before building anything."""
    postures = _postures_csv(tmp_path / "q.csv", [[0.0, 1.0]])
    static_opt_main(ELBOW + ["--postures", postures, "--out", str(tmp_path / "a.csv"), "--no-progress"])
    assert "building the body" in capsys.readouterr().out
    with pytest.raises(SystemExit) as stop:
        static_opt_main(ELBOW + ["--postures", postures, "--cut", "BRA", "--out", str(tmp_path / "b.csv")])
    out, err = capsys.readouterr()
    assert stop.value.code == 2 and "building the body" not in out and "did you mean 'BRA_tendon'?" in err
    assert not (tmp_path / "b.csv").exists()


def test_a_misspelt_muscle_is_refused_before_the_first_build(tmp_path, capsys, monkeypatch):
    """No remembered names (a fresh cache): the parsed MJCF's tendons bound the names, so a misspelt one is refused
    without building the body."""
    import lightning_bodyschema.statics as statics

    monkeypatch.setenv("BODYSCHEMA_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.setattr(statics, "StaticBody", lambda *a, **k: pytest.fail("the body was built"))
    postures = _postures_csv(tmp_path / "q.csv", [[0.0, 1.0]])
    with pytest.raises(SystemExit) as stop:
        static_opt_main(ELBOW + ["--postures", postures, "--cut", "BRA", "--out", str(tmp_path / "b.csv")])
    out, err = capsys.readouterr()
    assert stop.value.code == 2 and "building the body" not in out and "did you mean 'BRA_tendon'?" in err
    assert len(err.strip().splitlines()) == 1 and not (tmp_path / "b.csv").exists()


def test_help_has_an_example():
    result = subprocess.run([sys.executable, str(ROOT / "tools" / "static_opt.py"), "--help"], capture_output=True,
                            text=True, env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"}, timeout=120)
    assert result.returncode == 0 and "example:" in result.stdout and "--cut" in result.stdout
