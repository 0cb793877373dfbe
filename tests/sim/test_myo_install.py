"""The one documented MyoSuite install keeps MuJoCo 4 importable (issue 25, item 6).

myo-sim 0.2.4 declares mujoco<4: installed with its dependencies it replaces MuJoCo 4 and ``import mujoco`` fails.
The README's MyoSuite install must therefore add it with --no-deps, no extra of this package may depend on it, and
the environment the tests run in (built by that install, .ci/run) must import MuJoCo 4.
"""
import os
import re
import subprocess
import sys
import tomllib

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def _readme_myosuite_install() -> list[str]:
    with open(os.path.join(REPO, "README.md")) as fh:
        section = fh.read().split("## MyoSuite bodies", 1)[1].split("\n## ", 1)[0]
    return [line for line in section.splitlines() if re.match(r"\s*pip install", line)]


def test_the_readme_installs_myo_sim_without_its_mujoco_pin():
    (line,) = _readme_myosuite_install()  # one documented install
    commands = [c.split("#")[0].strip() for c in line.split("&&")]
    myo = [c for c in commands if "myo-sim" in c or ".[" in c]
    assert myo == ['pip install --no-deps "myo-sim==0.2.4"'], line
    assert 'pip install --no-deps "myo-sim==0.2.4"' in open(os.path.join(REPO, ".ci", "run")).read()


def test_no_extra_depends_on_myo_sim():
    with open(os.path.join(REPO, "pyproject.toml"), "rb") as fh:
        project = tomllib.load(fh)["project"]
    requirements = project["dependencies"] + sum(project.get("optional-dependencies", {}).values(), [])
    assert not [r for r in requirements if re.match(r"myo[-_]sim", r, re.I)]


def test_mujoco_4_imports_beside_myo_sim():
    """What the documented install leaves: MuJoCo 4 imports, and so does myo-sim (in a fresh process)."""
    code = "import mujoco, myo_sim; print(mujoco.__version__)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert int(out.stdout.strip().split(".")[0]) >= 4, out.stdout


def test_a_broken_mujoco_stops_with_one_line_naming_the_repair(tmp_path):
    """A MuJoCo that no longer imports (what mujoco<4 over MuJoCo 4 leaves) is named with the repair command."""
    broken = tmp_path / "mujoco"
    broken.mkdir()
    (broken / "__init__.py").write_text("from . import _missing_native_module\n")
    env = {**os.environ, "PYTHONPATH": f"{tmp_path}{os.pathsep}{REPO}"}
    code = "import lightning_bodyschema.sim"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, cwd=REPO, timeout=120)
    last = out.stderr.strip().splitlines()[-1]
    assert out.returncode != 0 and last.startswith("ImportError: MuJoCo does not import")
    assert '--force-reinstall --no-deps "mujoco>=4" "mujoco-core>=4" "mujoco-studio>=4"' in last
