"""Fine-tuning (``bodyschema fit --init_from.ckpt OLD.ckpt``): a schema trained on one robot's data continues on new
data from its own weights and normalizer, and then fits the new data better than it did."""
from __future__ import annotations

import glob
import warnings

import numpy as np
import pytest
import torch

from lightning_bodyschema.apps.dataset_tool import make_dataset_main
from lightning_bodyschema.cli import main as cli_main
from lightning_bodyschema.data import RecordedDataModule
from lightning_bodyschema.schemas import load_schema


def _fit(root, data, epochs, *extra):
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*LightningCLI's args parameter.*")
        cli_main(["fit", "--model=DiffusionSchema", "--data=RecordedDataModule", f"--data.path={data}",
                  f"--trainer.max_epochs={epochs}", f"--trainer.check_val_every_n_epoch={epochs}",
                  f"--trainer.default_root_dir={root}", "--faults.every_n_epochs=0", "--progress.enabled=false",
                  *extra])
    return sorted(glob.glob(f"{root}/lightning_logs/version_*/checkpoints/last.ckpt"))[-1]


def _errors_on(schema, data):
    dm = RecordedDataModule(data)
    dm.setup("test")
    q, x = dm.splits["val"]
    return schema.physical_errors(q, x)


@pytest.fixture(scope="module")
def old_and_new(tmp_path_factory):
    root = tmp_path_factory.mktemp("finetune")
    old_data, new_data = str(root / "old.npz"), str(root / "new.npz")
    make_dataset_main(["--n", "200", "--seed", "1", "--out", old_data])
    # the new data: the same robot with other moment arms, masses and springs (+-20 %), e.g. after a repair
    make_dataset_main(["--n", "200", "--seed", "2", "--out", new_data, "--mismatch", "0.2", "--mismatch-seed", "3"])
    old_ckpt = _fit(root / "old", old_data, 200)
    return root, old_ckpt, new_data


def test_fine_tuned_schema_fits_the_new_data_better_and_keeps_its_normalizer(old_and_new):
    root, old_ckpt, new_data = old_and_new
    fine_ckpt = _fit(root / "fine", new_data, 60, f"--init_from.ckpt={old_ckpt}")
    old, fine = load_schema(old_ckpt), load_schema(fine_ckpt)
    before, after = _errors_on(old, new_data), _errors_on(fine, new_data)
    print(f"\nnew data, median errors before / after the fine-tune: f {before['f_err_n']:.2f} / "
          f"{after['f_err_n']:.2f} N, l_motor {before['l_motor_err_mm']:.2f} / {after['l_motor_err_mm']:.2f} mm")
    # motor lengths carry the new body (moment arms set l_geo); tensions are drawn at random around equilibrium in
    # the data (the QP's f_ref), so their median error measures that spread more than the fit
    assert after["l_motor_err_mm"] < 0.7 * before["l_motor_err_mm"]
    for name in ("x_mean", "x_std", "q_lo", "q_hi"):  # the old units, not a refit to the new data
        assert torch.equal(getattr(fine.normalizer, name), getattr(old.normalizer, name)), name
    # a fresh schema trained as long on the new data starts from nothing: the fine-tune is ahead of it
    fresh = load_schema(_fit(root / "fresh", new_data, 60))
    assert after["l_motor_err_mm"] < _errors_on(fresh, new_data)["l_motor_err_mm"]


def test_fine_tune_can_refit_the_normalizer_and_refuses_a_missing_checkpoint(old_and_new, capsys):
    root, old_ckpt, new_data = old_and_new
    refit = load_schema(_fit(root / "refit", new_data, 2, f"--init_from.ckpt={old_ckpt}",
                             "--init_from.keep_normalizer=false"))
    dm = RecordedDataModule(new_data)
    dm.setup("fit")
    np.testing.assert_array_equal(refit.normalizer.x_mean.numpy(), dm.normalizer.x_mean.numpy())
    with pytest.raises(SystemExit) as exit_info:
        _fit(root / "missing", new_data, 2, f"--init_from.ckpt={root}/nope.ckpt")
    assert exit_info.value.code == 2 and "nope.ckpt' does not exist" in capsys.readouterr().err
