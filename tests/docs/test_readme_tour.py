"""The README's Quick tour and its deployment section run as written after command 1, in order.

Command 1 (``python tools/reproduce_paper.py --quick``) leaves the diffusion schema it trained at
``runs/quick/diff-1000/lightning_logs/version_0/checkpoints/last.ckpt``; here a short fit through the same CLI puts a
checkpoint at that path in a scratch folder that holds the repository's ``configs``, ``examples`` and ``tools``.
The blocks are read from README.md and run by bash, line for line, with two changes only: ``bodyschema`` is this
checkout's ``python -m lightning_bodyschema.cli`` (the installed script may be another checkout's), and the tour's
``bodyschema fit`` lines train 2 epochs on 200 samples (their paths and options are the README's, their length is
not a test's). ``tensorboard`` starts a server and is left out. Slow: a dozen processes, the export and a C++ build.
"""
from __future__ import annotations

import json
import os
import re
import shutil
import stat
import subprocess
from pathlib import Path

import pytest
from physics_checks import fit_tiny_checkpoint

from lightning_bodyschema.npz import default_file_mode
from lightning_bodyschema.status import STATUS_CODES

ROOT = Path(__file__).resolve().parents[2]
QUICK_CKPT = "runs/quick/diff-1000/lightning_logs/version_0/checkpoints/last.ckpt"  # what command 1 writes
SHORT_FIT = ("--trainer.max_epochs=2 --trainer.check_val_every_n_epoch=2 --faults.every_n_epochs=0 "
             "--progress.enabled=false --data.n_samples=200")

pytestmark = pytest.mark.slow


def readme_bash_block(heading: str) -> str:
    """The first ```bash block after the README heading ``heading``, continuation lines joined."""
    text = (ROOT / "README.md").read_text()
    section = text[text.index(f"\n{heading}\n"):]
    body = re.search(r"```bash\n(.*?)```", section, re.DOTALL).group(1)
    return body.replace("\\\n", " ")


def as_script(block: str) -> str:
    """The block as a bash script that stops at the first failing command (see the module docstring)."""
    lines = ["set -euo pipefail", 'bodyschema() { python -m lightning_bodyschema.cli "$@"; }']
    for line in block.splitlines():
        command = line.split("  #")[0].strip() if not line.lstrip().startswith("#") else ""
        if not command or command.startswith("tensorboard "):
            continue
        if command.startswith("bodyschema fit") and "--print_config" not in command:
            command = f"{command} {SHORT_FIT}"
        lines.append(command)
    return "\n".join(lines) + "\n"


@pytest.fixture(scope="module")
def after_command_1(tmp_path_factory):
    """A scratch folder as command 1 leaves the repository: the quick diffusion checkpoint, configs, tools."""
    folder = tmp_path_factory.mktemp("tour")
    for name in ("configs", "examples", "tools"):
        (folder / name).symlink_to(ROOT / name)
    ckpt = fit_tiny_checkpoint(folder / "runs" / "quick" / "diff-1000", "--data.n_samples=200",
                               "--faults.every_n_epochs=0", "--progress.enabled=false", epochs=30)
    assert Path(ckpt) == folder / QUICK_CKPT
    return folder


def run_block(folder: Path, heading: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    done = subprocess.run(["bash", "-c", as_script(readme_bash_block(heading))], cwd=folder, env=env,
                          capture_output=True, text=True, timeout=3600)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    return done


def test_the_quick_tour_runs_after_command_1(after_command_1):
    done = run_block(after_command_1, "## Quick tour")
    runs = after_command_1 / "runs"
    # bodyschema test logged beside the checkpoint; the later fit of the same config is still version_0
    assert (runs / "quick/diff-1000/lightning_logs/version_0/test/fault_benchmark.json").is_file()
    assert [p.name for p in (runs / "quick/diff-1000/lightning_logs").iterdir()] == ["version_0"]
    assert (runs / "diff/lightning_logs/version_0/checkpoints/last.ckpt").is_file()
    for name in ("paper_arm.npz", "cases.npz", "binding.npz", "commands.npz", "fast.npz", "commands.json", "arm.png"):
        assert (runs / name).is_file(), name
    assert "checkpoint:   runs/diff/lightning_logs/version_0/checkpoints/last.ckpt" in done.stdout  # as the user ran it
    assert "litlogger" not in done.stdout + done.stderr and "Attaching a spec" not in done.stdout + done.stderr


def test_the_deploy_section_runs_after_command_1(after_command_1):
    missing = [tool for tool in ("cmake", "ninja", "c++") if shutil.which(tool) is None]
    if missing:
        pytest.skip(f"the C++ steps need {missing}")
    done = run_block(after_command_1, "## Deploy in a C++ controller")
    package = after_command_1 / "runs" / "quick" / "adapter.pt2"
    assert package.is_file() and stat.S_IMODE(package.stat().st_mode) == default_file_mode()
    replies = [json.loads(line) for line in done.stdout.splitlines() if line.startswith('{"status"')]
    assert replies and all(reply["status_code"] in STATUS_CODES.values() for reply in replies), done.stdout[-2000:]
    assert "AdaptationResult(" in done.stdout  # step 2: the Python check printed the package's answer
    assert "FutureWarning" not in done.stderr, done.stderr[-2000:]
