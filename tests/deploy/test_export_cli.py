"""tools/export_adapter.py's refusals (no compile: they come before any work)."""
import os
import subprocess
import sys

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def test_export_cli_bad_input_exits_2_with_one_line(tmp_path):
    tool = os.path.join(REPO, "tools", "export_adapter.py")
    env = {**os.environ, "PYTHONPATH": REPO}
    for args in (["--ckpt", str(tmp_path / "none.ckpt"), "--out", str(tmp_path / "a.pt2"), "--batch-sizes", "0"],
                 ["--ckpt", str(tmp_path / "none.ckpt"), "--out", str(tmp_path / "a.zip")]):
        run = subprocess.run([sys.executable, tool, *args], capture_output=True, text=True, env=env, timeout=120)
        assert run.returncode == 2 and run.stderr.startswith("error: ") and run.stderr.count("\n") == 1, run.stderr
