"""DDP with 2 CPU processes (gloo) through the real CLI: each rank trains on its own shard, the weights stay identical,
and a 2-rank fit with half the per-rank batch reaches the 1-rank fit's validation residual."""
import os
import subprocess
import sys
import time

import pytest
import torch

from lightning_bodyschema.data import EquilibriumDataModule

HERE = os.path.dirname(os.path.abspath(__file__))
DDP = ("--trainer.strategy=ddp", "--trainer.devices=2", "--trainer.accelerator=cpu")


def run_fit(tmp_path, name, batch_size, epochs, *extra, model="DiffusionSchema"):
    """``bodyschema fit`` of a schema (the diffusion one by default) in a subprocess; returns (seconds, one record
    per rank)."""
    out = tmp_path / name
    out.mkdir()
    args = [sys.executable, "-m", "lightning_bodyschema.cli", "fit", f"--model={model}",
            f"--model.batch_size={batch_size}", f"--trainer.max_epochs={epochs}",
            f"--trainer.check_val_every_n_epoch={epochs}", "--trainer.logger=false",
            "--progress.enabled=false", "--faults.every_n_epochs=0",
            f"--data.cache_dir={tmp_path / 'cache'}", f"--trainer.default_root_dir={out}",
            "--trainer.callbacks+=ddp_probe.RecordRank", f"--trainer.callbacks.out_dir={out}", *extra]
    env = {**os.environ, "OMP_NUM_THREADS": "1",
           "PYTHONPATH": os.pathsep.join([HERE, os.environ.get("PYTHONPATH", "")])}
    start = time.perf_counter()
    done = subprocess.run(args, capture_output=True, text=True, env=env, timeout=1800)
    assert done.returncode == 0, (done.returncode, done.stdout[-3000:], done.stderr[-3000:])
    return time.perf_counter() - start, [torch.load(p, weights_only=True) for p in sorted(out.glob("rank*.pt"))]


@pytest.mark.parametrize("model", ["DiffusionSchema", pytest.param("AutoEncoderSchema", marks=pytest.mark.slow),
                                   pytest.param("VAESchema", marks=pytest.mark.slow)])  # slow: a DDP fit each
def test_ddp_two_cpu_ranks_shard_the_data_and_keep_identical_weights(tmp_path, model):
    epochs = 5
    seconds, ranks = run_fit(tmp_path, "ddp", 32, epochs, *DDP, model=model)
    print(f"2-rank DDP fit, {epochs} epochs: {seconds:.1f} s wall clock")
    assert [r["world_size"] for r in ranks] == [2, 2]
    dm = EquilibriumDataModule(cache_dir=str(tmp_path / "cache"))
    dm.setup("fit")
    train_q = dm.splits["train"][0]
    seen = [{tuple(row.tolist()) for row in r["rows"]} for r in ranks]
    assert seen[0].isdisjoint(seen[1]), "the ranks trained on overlapping samples"
    assert seen[0] | seen[1] == {tuple(row.tolist()) for row in train_q}, "the shards do not cover the train split"
    assert all(len(r["rows"]) == len(train_q) // 2 for r in ranks)
    for key, value in ranks[0]["state_dict"].items():
        assert torch.equal(value, ranks[1]["state_dict"][key]), f"{key} differs between the ranks"
    # the same seed on every rank, re-seeded with the rank at train start: each rank draws its own noise
    assert not torch.equal(ranks[0]["rng_state"], ranks[1]["rng_state"]), "the ranks draw the same noise"
    # gradients averaged over 2 x 32 samples: as many optimizer steps as one rank with batches of 64
    assert ranks[0]["global_step"] == ranks[1]["global_step"] == epochs * len(train_q) // 64
    # every rank validates the whole held-out split (a median does not average over shards), so the reduced value
    # is the same on every rank
    assert ranks[0]["val_rows"] == ranks[1]["val_rows"] == len(dm.splits["val"][0])
    assert ranks[0]["val_eq_residual"] == ranks[1]["val_eq_residual"]


@pytest.mark.slow
def test_ddp_with_half_the_batch_per_rank_reaches_the_single_process_residual(tmp_path):
    epochs = 300
    seconds, ranks = run_fit(tmp_path, "ddp", 32, epochs, *DDP)
    single_seconds, (single,) = run_fit(tmp_path, "single", 64, epochs)
    assert ranks[0]["global_step"] == single["global_step"]
    ddp_res, one_res = ranks[0]["val_eq_residual"], single["val_eq_residual"]
    print(f"{epochs} epochs: 2 ranks x 32 {seconds:.0f} s, val eq residual {ddp_res:.3f} N m; "
          f"1 rank x 64 {single_seconds:.0f} s, {one_res:.3f} N m")
    assert abs(ddp_res - one_res) <= 0.1 * one_res
