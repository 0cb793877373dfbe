"""tools/static_opt.py refuses a bad input in one stderr line (issue 50, item 5), in a fresh process as a user runs it.

Building a body makes notes (here "locked 1 joint(s) that no muscle crosses": the config's muscles span the elbow
only). A run that ends in a refused input shows the error alone and keeps the notes in the tool's log; a run that
succeeds still prints them.
"""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("myo_sim")
ROOT = Path(__file__).resolve().parents[2]
CONFIG = """data:
  model: myo:myoelbow_2dof
  muscles: [TRImed_tendon, TRIlat_tendon, BRA_tendon]
"""


def _run(tmp_path, elbow_rad: float) -> subprocess.CompletedProcess:
    (tmp_path / "elbow.yaml").write_text(CONFIG)
    (tmp_path / "postures.csv").write_text(f"r_elbow_flex\n{elbow_rad}\n")
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1",
           "BODYSCHEMA_CACHE_DIR": str(tmp_path / "cache")}  # a first run: no names remembered
    return subprocess.run([sys.executable, str(ROOT / "tools" / "static_opt.py"), "--config", str(tmp_path / "elbow.yaml"),
                           "--postures", str(tmp_path / "postures.csv"), "--out", str(tmp_path / "out.csv")],
                          capture_output=True, text=True, env=env, cwd=tmp_path, timeout=600)


def test_a_refused_posture_is_one_stderr_line_and_the_notes_go_to_the_log(tmp_path):
    run = _run(tmp_path, 9.0)  # beyond the elbow's range: refused once the body is built
    assert run.returncode == 2
    assert run.stderr.splitlines() == [run.stderr.strip()] and run.stderr.startswith("error: ")
    assert "r_elbow_flex" in run.stderr and "outside its range" in run.stderr and "Traceback" not in run.stderr
    log = (tmp_path / "cache" / "logs" / "static_opt.log").read_text()
    assert "note: locked 1 joint(s) that no muscle crosses" in log and "outside its range" in log
    assert not (tmp_path / "out.csv").exists()


def test_a_run_that_succeeds_still_prints_its_notes(tmp_path):
    run = _run(tmp_path, 1.0)
    assert run.returncode == 0, run.stderr
    assert "locked 1 joint(s) that no muscle crosses" in run.stderr and (tmp_path / "out.csv").exists()
    assert not (tmp_path / "cache" / "logs").exists()
