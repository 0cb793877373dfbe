"""One version: the package's ``__version__``, pyproject.toml's, and the newest release section of CHANGELOG.md."""
import re
from pathlib import Path

import lightning_bodyschema

ROOT = Path(__file__).resolve().parents[2]


def test_the_version_is_the_same_everywhere():
    pyproject = re.search(r'^version = "([^"]+)"', (ROOT / "pyproject.toml").read_text(), re.M).group(1)
    released = re.search(r"^## \[(\d[^\]]*)\]", (ROOT / "CHANGELOG.md").read_text(), re.M).group(1)
    assert lightning_bodyschema.__version__ == pyproject
    assert pyproject == released or pyproject.startswith(released + ".post") or ".dev" in pyproject
