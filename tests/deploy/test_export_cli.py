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


def test_a_pinned_digest_is_checked_before_anything_is_loaded(tmp_path, monkeypatch):
    """A package runs compiled code: a file whose SHA-256 is not the pinned one is refused unread by torch."""
    from torch.export.pt2_archive import _package as pt2

    from lightning_bodyschema.deploy import file_sha256, load_exported
    from lightning_bodyschema.errors import BodySchemaInputError

    path = tmp_path / "forged.pt2"
    path.write_bytes(b"PK\x03\x04 not really a package" * 50)
    monkeypatch.setattr(pt2, "load_pt2", lambda *a, **k: pytest.fail("loaded"))
    with pytest.raises(BodySchemaInputError, match="refused unloaded"):
        load_exported(str(path), expected_sha256="0" * 64)
    with pytest.raises(BodySchemaInputError, match="64 hex digits"):
        load_exported(str(path), expected_sha256="abc")
    with pytest.raises(BodySchemaInputError, match="corrupt or truncated"):  # the right digest: on to the checks
        load_exported(str(path), expected_sha256=file_sha256(str(path)).upper())


def test_check_package_bad_input_exits_2_with_one_line(tmp_path, capsys):
    spec = importlib.util.spec_from_file_location("check_package", os.path.join(REPO, "tools", "check_package.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    with pytest.raises(SystemExit) as exit_info:
        module.main(["--ckpt", str(tmp_path / "none.ckpt"), "--package", str(tmp_path / "none.pt2"), "--cases", "0"])
    err = capsys.readouterr().err
    assert exit_info.value.code == 2 and err.startswith("error: ") and err.count("\n") == 1 and "--cases 0" in err
