"""Shared by the statics tests: the README's Python blocks, run from the repository root."""
from __future__ import annotations

import sys
from pathlib import Path

import pytest


@pytest.fixture
def readme_block(monkeypatch):
    """``run(marker) -> namespace``: README's one Python block containing ``marker``, run from the repository root
    (the block's relative paths, e.g. configs/myoarm.yaml, resolve as a reader's would)."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "docs"))
    from test_readme_examples import ROOT, block

    def run(marker: str) -> dict:
        monkeypatch.chdir(ROOT)
        namespace = {}
        exec(block("python", marker), namespace)
        return namespace

    return run
