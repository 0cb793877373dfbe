#!/usr/bin/env python
"""Training throughput: the DDPM schema through Lightning vs a plain PyTorch loop of the same model.

Both run the same maths (same network, fused Adam, minibatches of 64 from the 640 train samples, cosine
LR), side by side in one process, alternating, several repeats; prints medians and the ratio. Lightning
runs one training step per minibatch (automatic optimization, the 32-true precision plugin). Beside them, a
one-weight module through the same Trainer setup and through a plain loop: the difference is Lightning's own
per-step cost (its floor), which bounds the ratio any Lightning step of this maths can reach.

    python tools/bench_training.py --epochs 2000 --repeats 3
    python tools/bench_training.py --epochs 300 --hook-times   # where a step's time goes, hook by hook
"""
import argparse
import contextlib
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
from lightning_bodyschema.training.finite import all_finite  # noqa: E402


def plain_loop(dm, epochs, batch_size=64, same_step=False):
    """The reference: the schema's own loss, an ordinary loop, no Lightning. ``same_step``: also the per-step work
    the schema's ``training_step`` adds to its loss (normalize each SI minibatch, skip a non-finite gradient), so
    the difference to Lightning is Lightning's alone."""
    schema = DiffusionSchema(robot=dm.robot)
    schema.normalizer.load_state_dict(dm.normalizer.state_dict())
    q, x = dm.splits["train"] if same_step else schema._normalized(dm.splits["train"])
    schema._minibatch_affine = schema.normalizer.affine()
    opt = torch.optim.Adam(schema.parameters(), lr=1e-3, fused=True)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=epochs, eta_min=1e-5)
    for _ in range(epochs):
        for idx in torch.randperm(len(q)).split(batch_size):
            batch = schema._normalized_minibatch((q[idx], x[idx])) if same_step else (q[idx], x[idx])
            loss, _ = schema.training_loss(*batch)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            if same_step and not all_finite([p.grad for p in schema.parameters()]):
                continue
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


class _TrivialModule(L.LightningModule):
    """One weight, one multiply: a step with almost no maths, so its cost is Lightning's own per-step work."""

    def __init__(self):
        super().__init__()
        self.weight = torch.nn.Parameter(torch.ones(1))

    def training_step(self, batch, batch_idx):
        return (self.weight * batch).sum()

    def configure_optimizers(self):
        return torch.optim.SGD(self.parameters(), lr=1e-9)


class _Batches:
    """A re-iterable loader of ``n`` one-element batches (a plain list would be read as n data loaders)."""

    def __init__(self, n):
        self.batches = [torch.ones(1)] * n

    def __iter__(self):
        return iter(self.batches)

    def __len__(self):
        return len(self.batches)


def floor_runs(epochs, steps_per_epoch, logdir):
    """(plain, Lightning) runs of the trivial module: their difference per step is the least any Lightning
    step costs beyond its maths with this Trainer setup (same logger, progress bar, callbacks)."""
    batches = _Batches(steps_per_epoch)

    def plain():
        module = _TrivialModule()
        opt = torch.optim.SGD(module.parameters(), lr=1e-9)
        for _ in range(epochs):
            for batch in batches:
                loss = module.training_step(batch, 0)
                opt.zero_grad(set_to_none=True)
                loss.backward()
                opt.step()

    def lightning():
        trainer = L.Trainer(max_epochs=epochs, logger=L.pytorch.loggers.TensorBoardLogger(logdir), log_every_n_steps=50,
                            num_sanity_val_steps=0, enable_model_summary=False, enable_checkpointing=False,
                            callbacks=[EpochProgressBar()], enable_progress_bar=True)
        trainer.fit(_TrivialModule(), train_dataloaders=batches)
    return plain, lightning


@contextlib.contextmanager
def timed_hooks(acc: dict):
    """While open, every hook Lightning calls (module, callbacks, strategy, data module) adds its CPU time in ns to
    ``acc["depth kind.hook"]`` (inclusive of the hooks it calls, which count at depth + 1)."""
    from lightning.pytorch.trainer import call

    kinds = {"_call_lightning_module_hook": "module", "_call_callback_hooks": "callback",
             "_call_strategy_hook": "strategy", "_call_lightning_datamodule_hook": "datamodule"}
    originals, depth = {name: getattr(call, name) for name in kinds}, [0]

    def timed(fn, kind):
        def run(trainer, hook, *args, **kwargs):
            depth[0] += 1
            start = time.thread_time_ns()
            try:
                return fn(trainer, hook, *args, **kwargs)
            finally:
                depth[0] -= 1
                key = f"{depth[0]} {kind}.{hook}"
                acc[key] = acc.get(key, 0) + time.thread_time_ns() - start
        return run
    try:
        for name, kind in kinds.items():
            setattr(call, name, timed(originals[name], kind))
        yield acc
    finally:
        for name, original in originals.items():
            setattr(call, name, original)


def hook_times(fits: dict, steps: int) -> None:
    """Print each Lightning hook's CPU time per optimizer step in each fit of ``fits`` (name -> callable), side by
    side: where a step's time goes beyond its maths."""
    per_fit = {}
    for fit_name, fit in fits.items():
        with timed_hooks({}) as acc:
            fit()
        per_fit[fit_name] = {key: value / 1e3 / steps for key, value in acc.items()}
    keys = sorted({key for times in per_fit.values() for key in times},
                  key=lambda key: -max(times.get(key, 0.0) for times in per_fit.values()))
    print("hook CPU time per optimizer step (us; 'depth kind.hook', inclusive): " + " | ".join(per_fit))
    for key in keys:
        if max(times.get(key, 0.0) for times in per_fit.values()) >= 0.5:
            print(f"  {key:55s} " + " ".join(f"{times.get(key, 0.0):9.2f}" for times in per_fit.values()))


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--epochs", type=int, default=1000)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--hook-times", action="store_true",
                        help="instead: one fit of each Lightning run, each hook's CPU time per optimizer step")
    args = parser.parse_args()
    if args.epochs < 2 or args.repeats < 1:
        print(f"error: --epochs={args.epochs} must be >= 2 and --repeats={args.repeats} >= 1", file=sys.stderr)
        raise SystemExit(2)
    dm = EquilibriumDataModule(cache_dir=None)
    dm.prepare_data()
    dm.setup("fit")
    steps_per_epoch = len(dm.train_dataloader())
    floor_plain, floor_lightning = floor_runs(args.epochs, steps_per_epoch, tempfile.gettempdir())
    if args.hook_times:
        with tempfile.TemporaryDirectory() as logdir:
            hook_times({"schema": lambda: lightning_fit(dm, args.epochs, logdir), "floor": floor_lightning},
                       args.epochs * steps_per_epoch)
        return
    runs = [("plain", lambda: plain_loop(dm, args.epochs)),
            ("plain_step", lambda: plain_loop(dm, args.epochs, same_step=True)),
            ("lightning", lambda: lightning_fit(dm, args.epochs, logdir)),
            ("floor_plain", floor_plain), ("floor_lightning", floor_lightning)]
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
    steps = args.epochs * steps_per_epoch
    floor_ms = 1e3 * (med_cpu["floor_lightning"] - med_cpu["floor_plain"]) / steps
    plain_ms, ours_ms = 1e3 * med_cpu["plain"] / steps, 1e3 * (med_cpu["lightning"] - med_cpu["plain"]) / steps
    print(f"per optimizer step (CPU): maths {plain_ms:.3f} ms; Lightning adds {ours_ms:.3f} ms to it "
          f"({ours_ms / floor_ms:.2f} x its floor), and "
          f"{floor_ms:.3f} ms to a trivial module with the same Trainer setup (its floor): the least ratio a "
          f"Lightning step of this maths can reach is {(plain_ms + floor_ms) / plain_ms:.3f}")
    step_ms = 1e3 * med_cpu["plain_step"] / steps
    own_ms = 1e3 * (med_cpu["lightning"] - med_cpu["plain_step"]) / steps
    print(f"the schema's whole step (normalize, loss, non-finite check) in a plain loop {step_ms:.3f} ms; Lightning "
          f"adds {own_ms:.3f} ms to it: {own_ms / floor_ms:.2f} x its floor (goal <= 1.1)")
    per_epoch = (med["lightning"] - startup) / (args.epochs - 1)
    print(f"fit start-up {startup:.2f} s; per epoch {1e3 * per_epoch:.2f} ms vs plain {1e3 * med['plain'] / args.epochs:.2f}"
          f" ms (ratio {per_epoch * args.epochs / med['plain']:.3f})")
    print(f"extrapolated 10000 epochs through Lightning: {startup + per_epoch * 10000:.0f} s "
          f"(ratio {(startup + per_epoch * 10000) / (med['plain'] * 10000 / args.epochs):.3f})")


if __name__ == "__main__":
    main()
