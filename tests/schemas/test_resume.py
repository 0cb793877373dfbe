"""Determinism and resume: same seed -> same weights; a fit killed midway and resumed ends where an uninterrupted one does.

Three 60-epoch fits in fresh processes (slow); the default run resumes in-process from mid-epoch checkpoints
(tests/training/test_steps.py) and checks the dataset bytes across processes (tests/data/test_dataset_determinism.py).
"""
import glob
import os
import subprocess
import sys
import time

import pytest
import torch

ARGS = ["--model=DiffusionSchema", "--model.batch_size=32", "--data.n_samples=400", "--trainer.max_epochs=60",
        "--trainer.check_val_every_n_epoch=1000", "--trainer.deterministic=true", "--trainer.logger=false",
        "--checkpoint.every_n_epochs=1", "--checkpoint.save_top_k=-1", "--checkpoint.save_on_train_epoch_end=true",
        "--faults.every_n_epochs=0",
        "--progress.enabled=false"]


def _cli(tmp_path, name, *extra):
    return [sys.executable, "-m", "lightning_bodyschema.cli", "fit", *ARGS, f"--data.cache_dir={tmp_path / 'cache'}",
            f"--trainer.default_root_dir={tmp_path / name}", f"--checkpoint.dirpath={tmp_path / name / 'ckpt'}", *extra]


def _final_weights(folder):
    path = os.path.join(folder, "ckpt", "last.ckpt")
    return torch.load(path, map_location="cpu", weights_only=True)["state_dict"]


def _assert_same(a, b):
    assert a.keys() == b.keys()
    for key in a:
        assert torch.equal(a[key], b[key]), f"{key} differs"


@pytest.mark.slow
def test_same_seed_same_weights_and_a_killed_fit_resumes_to_the_same_weights(tmp_path):
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    for name in ("first", "second"):
        subprocess.run(_cli(tmp_path, name), check=True, capture_output=True, env=env, timeout=300)
    _assert_same(_final_weights(tmp_path / "first"), _final_weights(tmp_path / "second"))

    # interrupt for real: SIGKILL once the 20th epoch's checkpoint is on disk, then resume from the newest one
    proc = subprocess.Popen(_cli(tmp_path, "killed"), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env)
    deadline = time.time() + 240
    while not glob.glob(str(tmp_path / "killed" / "ckpt" / "epoch=19-*.ckpt")):
        assert proc.poll() is None and time.time() < deadline, "the fit ended before it could be interrupted"
        time.sleep(0.01)
    proc.kill()
    proc.wait()
    done = sorted(glob.glob(str(tmp_path / "killed" / "ckpt" / "epoch=*.ckpt")),
                  key=lambda p: int(os.path.basename(p).split("-")[0].split("=")[1]))
    resume_from = done[-2]  # the newest file may be half-written by the kill
    epoch = int(os.path.basename(resume_from).split("-")[0].split("=")[1])
    assert 18 <= epoch < 58, f"killed at epoch {epoch}: not midway"
    os.remove(tmp_path / "killed" / "ckpt" / "last.ckpt")  # it may be half-written by the kill
    subprocess.run(_cli(tmp_path, "killed", f"--ckpt_path={resume_from}"), check=True, capture_output=True, env=env,
                   timeout=300)
    _assert_same(_final_weights(tmp_path / "first"), _final_weights(tmp_path / "killed"))
