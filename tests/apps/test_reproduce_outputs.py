"""``tools/reproduce_paper.py --quick`` keeps a run's outputs together: checkpoints, dataset cache, results and
figures all under runs/quick, nothing in the working tree beside it (it used to train into runs/paper)."""
import json

import pytest

from lightning_bodyschema.apps.reproduce import main as reproduce_main


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory):
    """A tiny quick run (one schema, 2 epochs, 2 cases per condition) from an empty folder."""
    folder = tmp_path_factory.mktemp("quick")
    with pytest.MonkeyPatch.context() as patch:
        patch.chdir(folder)
        reproduce_main(["--quick", "--epochs", "2", "--models", "Diff", "--n-per-condition", "2", "--jobs", "1"])
    return folder, sorted(str(p.relative_to(folder)) for p in folder.rglob("*") if p.is_file())


def test_quick_outputs_are_all_under_runs_quick(quick_run):
    _, written = quick_run
    assert written and all(path.startswith("runs/quick/") for path in written), written


def test_quick_checkpoints_and_results_sit_together(quick_run):
    folder, written = quick_run
    assert any(p.startswith("runs/quick/diff-2/lightning_logs/") and p.endswith(".ckpt") for p in written), written
    assert any(p.startswith("runs/quick/cache/") for p in written), written  # the dataset cache too
    assert "runs/quick/docs/paper_boxplots.png" in written
    summary = json.loads((folder / "runs/quick/results.json").read_text())
    assert summary["epochs"] == 2 and summary["n_cases"] == 6 and "Diff" in summary["summary"]
