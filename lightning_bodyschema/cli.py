"""``bodyschema``: the LightningCLI front end (fit, validate, test, predict).

    bodyschema fit --config configs/diff.yaml
    bodyschema fit --config configs/ae-10.yaml --config configs/quick.yaml
    bodyschema fit --model DiffusionSchema --data.n_samples 800 --trainer.max_epochs 100

The data module's robot (XML, muscles, spring) is linked into the schema at instantiation, so every
checkpoint is self-contained. User errors exit with code 2 and one line, without a traceback.
"""
from __future__ import annotations

import sys
import warnings

import torch
from lightning.pytorch.callbacks import ModelCheckpoint
from lightning.pytorch.cli import LightningCLI

from .callbacks import EpochProgressBar, FaultBenchmark, ReconstructionFigure
from .data import EquilibriumDataModule
from .errors import BodySchemaInputError
from .schemas import AutoEncoderSchema, BodySchema, DiffusionSchema, VAESchema  # noqa: F401 (short names)


class BodySchemaCLI(LightningCLI):
    def add_arguments_to_parser(self, parser):
        parser.link_arguments("data.robot", "model.init_args.robot", apply_on="instantiate")
        # always-on callbacks, configurable as --progress.*, --figures.* and --faults.*
        parser.add_lightning_class_args(EpochProgressBar, "progress")
        parser.add_lightning_class_args(ReconstructionFigure, "figures")
        parser.add_lightning_class_args(FaultBenchmark, "faults")
        # checkpoints: keep last.ckpt beside the newest epoch file, so `--ckpt_path .../last.ckpt` always works
        parser.add_lightning_class_args(ModelCheckpoint, "checkpoint")
        parser.set_defaults({"checkpoint.save_last": True})


def _trainer_defaults() -> dict:
    return {
        "max_epochs": 10000,  # the paper's setting
        "check_val_every_n_epoch": 500,
        "log_every_n_steps": 50,  # one step per epoch: log every 50 epochs
        "num_sanity_val_steps": 0,
        "enable_model_summary": False,
    }


def main(args=None):
    torch.set_num_threads(1)  # one thread per process is fastest for these tiny MLPs (DESIGN §7)
    torch.set_flush_denormal(True)
    # one Lightning step per epoch by design (DESIGN §4): the "fewer batches than log interval" notice is noise
    warnings.filterwarnings("ignore", message=".*smaller than the logging interval.*")
    warnings.filterwarnings("ignore", message=".*LeafSpec.*")
    try:
        BodySchemaCLI(BodySchema, EquilibriumDataModule, subclass_mode_model=True, args=args,
                      seed_everything_default=0, save_config_kwargs={"overwrite": True},
                      trainer_defaults=_trainer_defaults(), auto_configure_optimizers=False)
    except Exception as err:  # jsonargparse wraps errors raised while instantiating classes
        cause = _input_error_in_chain(err)
        if cause is None:
            raise
        print(f"error: {cause}", file=sys.stderr)
        raise SystemExit(2) from None


def _input_error_in_chain(err: BaseException | None) -> BodySchemaInputError | None:
    """The user-input error at the root of ``err``'s cause/context chain, if there is one."""
    seen = set()
    while err is not None and id(err) not in seen:
        if isinstance(err, BodySchemaInputError):
            return err
        seen.add(id(err))
        err = err.__cause__ or err.__context__
    return None


if __name__ == "__main__":
    main()
