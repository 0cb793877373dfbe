#!/usr/bin/env python
"""Training throughput: the DDPM schema through Lightning vs a plain PyTorch loop of the same model.

Both run the same maths (same network, fused Adam, minibatches of 64 from the 640 train samples, cosine
LR), side by side in one process, alternating, several repeats; prints medians and the ratio. Lightning
runs one training step per minibatch (automatic optimization, the 32-true precision plugin).

    python tools/bench_training.py --epochs 2000 --repeats 3
"""
import argparse
import statistics
import sys
import tempfile
import time

import torch

torch.set_num_threads(1)
torch.set_flush_denormal(True)

import lightning as L  # noqa: E402

from lightning_bodyschema.callbacks import EpochProgressBar  # noqa: E402
from lightning_bodyschema.data import EquilibriumDataModule  # noqa: E402
from lightning_bodyschema.schemas import DiffusionSchema  # noqa: E402


def plain_loop(dm, epochs, batch_size=64):
    """The reference: the schema's own loss, an ordinary loop, no Lightning."""
    schema = DiffusionSchema(robot=dm.robot)
    schema.normalizer.load_state_dict(dm.normalizer.state_dict())
    q_n, x_n = schema._normalized(dm.splits["train"])
    opt = torch.optim.Adam(schema.parameters(), lr=1e-3, fused=True)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=epochs, eta_min=1e-5)
    for _ in range(epochs):
        for idx in torch.randperm(len(q_n)).split(batch_size):
            loss, _ = schema.training_loss(q_n[idx], x_n[idx])
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
        sched.step()
    return schema


def lightning_fit(dm, epochs, logdir):
    schema = DiffusionSchema(robot=dm.robot)
    trainer = L.Trainer(max_epochs=epochs, logger=L.pytorch.loggers.TensorBoardLogger(logdir), log_every_n_steps=50,
                        check_val_every_n_epoch=10 ** 9, num_sanity_val_steps=0, enable_model_summary=False,
                        enable_checkpointing=False, callbacks=[EpochProgressBar()], enable_progress_bar=True)
    trainer.fit(schema, datamodule=dm)
    return schema


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--epochs", type=int, default=1000)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    if args.epochs < 2 or args.repeats < 1:
        print(f"error: --epochs={args.epochs} must be >= 2 and --repeats={args.repeats} >= 1", file=sys.stderr)
        raise SystemExit(2)
    dm = EquilibriumDataModule(cache_dir=None)
    dm.prepare_data()
    dm.setup("fit")
    runs = [("plain", lambda: plain_loop(dm, args.epochs)),
            ("lightning", lambda: lightning_fit(dm, args.epochs, logdir))]
    times = {name: [] for name, _ in runs}
    cpu = {name: [] for name, _ in runs}  # CPU seconds of this (one-thread) process: steadier on a shared machine
    with tempfile.TemporaryDirectory() as logdir:
        for _ in range(args.repeats):
            for name, run in runs:
                start, start_cpu = time.perf_counter(), time.process_time()
                run()
                times[name].append(time.perf_counter() - start)
                cpu[name].append(time.process_time() - start_cpu)
        start = time.perf_counter()
        lightning_fit(dm, 1, logdir)  # the fixed cost of building and tearing down a fit (paid once per run)
        startup = time.perf_counter() - start
    med = {k: statistics.median(v) for k, v in times.items()}
    for name, value in med.items():
        print(f"{name:10s} median {value:7.2f} s for {args.epochs} epochs = {1e3 * value / args.epochs:6.2f} ms/epoch "
              f"(runs: {', '.join(f'{t:.2f}' for t in times[name])})")
    med_cpu = {k: statistics.median(v) for k, v in cpu.items()}
    for name, value in med_cpu.items():
        print(f"{name:10s} median CPU {value:7.2f} s = {1e3 * value / args.epochs:6.2f} ms/epoch "
              f"(runs: {', '.join(f'{t:.2f}' for t in cpu[name])})")
    print(f"ratio lightning/plain = {med['lightning'] / med['plain']:.3f} wall clock, "
          f"{med_cpu['lightning'] / med_cpu['plain']:.3f} CPU time  (goal <= 1.2)")
    per_epoch = (med["lightning"] - startup) / (args.epochs - 1)
    print(f"fit start-up {startup:.2f} s; per epoch {1e3 * per_epoch:.2f} ms vs plain {1e3 * med['plain'] / args.epochs:.2f}"
          f" ms (ratio {per_epoch * args.epochs / med['plain']:.3f})")
    print(f"extrapolated 10000 epochs through Lightning: {startup + per_epoch * 10000:.0f} s "
          f"(ratio {(startup + per_epoch * 10000) / (med['plain'] * 10000 / args.epochs):.3f})")


if __name__ == "__main__":
    main()
