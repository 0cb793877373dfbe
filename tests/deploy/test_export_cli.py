"""tools/export_adapter.py's refusals (no compile: they come before any work)."""
import importlib.util
import os

import pytest

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def export_main():
    spec = importlib.util.spec_from_file_location("export_adapter", os.path.join(REPO, "tools", "export_adapter.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.main


@pytest.mark.parametrize("extra, message", [(["--batch-sizes", "0"], "batch size '0'"),
                                            (["--out-zip"], "ends in .pt2"), ([], "does not exist")])
def test_export_cli_bad_input_exits_2_with_one_line(tmp_path, capsys, extra, message):
    out = str(tmp_path / ("a.zip" if extra == ["--out-zip"] else "a.pt2"))
    args = ["--ckpt", str(tmp_path / "none.ckpt"), "--out", out] + [a for a in extra if a != "--out-zip"]
    with pytest.raises(SystemExit) as exit_info:
        export_main()(args)
    err = capsys.readouterr().err
    assert exit_info.value.code == 2 and err.startswith("error: ") and err.count("\n") == 1 and message in err
    assert not os.listdir(tmp_path)  # nothing written
