"""Where a schema runs: ``load_schema(map_location=)``, the tools' ``--device``, and the precisions a schema refuses
(each bad value one line, exit 2, nothing written)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from lightning_bodyschema.errors import BodySchemaInputError
from lightning_bodyschema.schemas import load_schema
from lightning_bodyschema.schemas.loading import check_device
from physics_checks import fit_tiny_checkpoint

NO_CUDA = "cuda" if not torch.cuda.is_available() else f"cuda:{torch.cuda.device_count()}"  # a device this box lacks


@pytest.fixture(scope="module")
def ckpt(tmp_path_factory):
    root = tmp_path_factory.mktemp("device")
    return fit_tiny_checkpoint(root / "fit", "--data.n_samples=200", "--faults.every_n_epochs=0",
                               "--progress.enabled=false", epochs=2)


@pytest.mark.parametrize("bad", ["gpu0", "cuda:x", 3.5, NO_CUDA])
def test_a_device_this_machine_lacks_is_one_line(bad):
    with pytest.raises(BodySchemaInputError, match="map_location=") as err:
        check_device(bad, "map_location")
    assert "\n" not in str(err.value) and repr(bad) in str(err.value)


def test_load_schema_moves_to_map_location(ckpt):
    plain, moved = load_schema(ckpt), load_schema(ckpt, map_location=torch.device("cpu"))
    assert moved.device.type == "cpu" and not moved.training
    q = np.array([[0.3, 0.4]])
    np.testing.assert_array_equal(plain.infer(q)[0], moved.infer(q)[0])
    with pytest.raises(BodySchemaInputError, match="map_location"):
        load_schema(ckpt, map_location=NO_CUDA)
    with pytest.raises(BodySchemaInputError, match="map_location"):
        type(plain).load_from_checkpoint(ckpt, map_location=NO_CUDA)


def test_tools_take_device_and_refuse_a_missing_one_in_one_line(ckpt, tmp_path, capsys):
    from lightning_bodyschema.apps.case_tools import adapt_cases_main, make_cases_main

    cases, out = tmp_path / "cases.npz", tmp_path / "adapted.npz"
    make_cases_main(["--ckpt", ckpt, "--seed", "0", "--out", str(cases), "--n-per-condition", "2"])
    adapt_cases_main(["--ckpt", ckpt, "--cases", str(cases), "--out", str(out), "--sampler", "strided20",
                      "--device", "cpu"])
    assert np.load(out)["l_motor"].shape == (6, 6)
    capsys.readouterr()
    with pytest.raises(SystemExit) as exit_:
        adapt_cases_main(["--ckpt", ckpt, "--cases", str(cases), "--out", str(tmp_path / "no.npz"),
                          "--device", NO_CUDA])
    err = capsys.readouterr().err.strip().splitlines()
    assert exit_.value.code == 2 and len(err) == 1 and NO_CUDA in err[0], err
    assert not (tmp_path / "no.npz").exists()


def test_structured_schema_refuses_mixed_precision_in_one_line(tmp_path, capsys):
    from lightning_bodyschema.cli import main as cli_main

    with pytest.raises(SystemExit) as exit_:
        cli_main(["fit", "--model=StructuredSchema", "--model.batch_size=64", "--data.n_samples=100",
                  "--trainer.max_epochs=1", "--trainer.precision=bf16-mixed", f"--trainer.default_root_dir={tmp_path}",
                  "--data.cache_dir=null"])
    err = [line for line in capsys.readouterr().err.splitlines() if line.startswith("error")]
    assert exit_.value.code == 2 and len(err) == 1, err  # the data module's progress lines come before
    assert "bf16-mixed" in err[0] and "StructuredSchema" in err[0] and "32-true" in err[0]
