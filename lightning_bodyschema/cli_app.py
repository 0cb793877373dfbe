"""The ``bodyschema`` command itself (``cli.main`` imports it once the arguments pass the quick option check):
``BodySchemaCLI``, LightningCLI with this package's input checks (module ``cli``'s docstring)."""
from __future__ import annotations

import glob
import logging
import os
import sys
import warnings
from typing import Optional

import torch
from jsonargparse import ActionSubCommands
from lightning.fabric.utilities.exceptions import MisconfigurationException
from lightning.pytorch.callbacks import ModelCheckpoint
from lightning.pytorch.cli import LightningCLI
from lightning.pytorch.loggers import TensorBoardLogger

from .callbacks import EpochProgressBar, FaultBenchmark, FinalValidation, InitFrom, ReconstructionFigure
from .cli_parser import OneLineErrorParser, _known_options
from .data import EquilibriumDataModule, RecordedDataModule  # noqa: F401 (--data RecordedDataModule)
from .errors import BodySchemaInputError
from .schemas import (AutoEncoderSchema, BodySchema, DiffusionSchema, StructuredSchema,  # noqa: F401 (short names)
                      VAESchema)
from .training.fit_loop import check_val_check_interval, half_precision_refusal
from .training.lightning_module import RENAMED_METRICS
from .schemas.loading import check_checkpoint, read_checkpoint, schema_class


DESCRIPTION = ("Train and evaluate body schemas of musculoskeletal robots (AE, VAE, diffusion; Kawaharazuka & "
               "Ikemoto). Subcommands: fit (train, with validation in physical units and the in-fit fault "
               "benchmark), validate and test (a checkpoint on the data's splits). Adapting commands to faults: "
               "tools/predict.py, tools/adapt_cases.py, or schema.adapt from Python.")


class _HeldSeedNote(logging.Filter):
    """Holds Lightning's "Seed set to N" line (logged before the classes are built) until they are: a bad option
    then prints its one error line alone, and a good run still says its seed."""

    def __init__(self):
        super().__init__()
        self.holding, self.held = True, []

    def filter(self, record: logging.LogRecord) -> bool:
        if self.holding and "Seed set to" in str(record.msg):
            self.held.append(record)
            return False
        return True

    def release(self) -> None:
        self.holding, held, self.held = False, self.held, []
        for record in held:
            logging.getLogger(record.name).handle(record)


_SEED_NOTE = _HeldSeedNote()


class BodySchemaCLI(LightningCLI):
    def instantiate_classes(self) -> None:
        super().instantiate_classes()
        _SEED_NOTE.release()

    @staticmethod
    def subcommands() -> dict[str, set[str]]:
        """fit, validate and test; no predict (see the module docstring)."""
        return {name: skip for name, skip in LightningCLI.subcommands().items() if name != "predict"}

    def add_arguments_to_parser(self, parser):
        parser.link_arguments("data.robot", "model.init_args.robot", apply_on="instantiate")
        # the data module serves the minibatches; --model.batch_size (recorded in the checkpoint) sets its size
        parser.link_arguments("model.init_args.batch_size", "data.init_args.batch_size")
        # always-on callbacks, configurable as --progress.*, --figures.* and --faults.*
        parser.add_lightning_class_args(EpochProgressBar, "progress")
        parser.add_lightning_class_args(ReconstructionFigure, "figures")
        parser.add_lightning_class_args(FaultBenchmark, "faults")
        # physical metrics at the end of every fit, whatever check_val_every_n_epoch
        parser.add_lightning_class_args(FinalValidation, "final_validation")
        # fine-tune: --init_from.ckpt OLD.ckpt starts from its weights and normalizer (a fresh optimizer and schedule)
        parser.add_lightning_class_args(InitFrom, "init_from")
        # checkpoints: keep last.ckpt beside the newest epoch file, so `--ckpt_path .../last.ckpt` always works
        parser.add_lightning_class_args(ModelCheckpoint, "checkpoint")
        parser.set_defaults({"checkpoint.save_last": True})
        # --data is a class option (EquilibriumDataModule or RecordedDataModule): the simulation module by default
        parser.set_defaults({"data": {"class_path": "lightning_bodyschema.data.EquilibriumDataModule"}})

    # ---------------------------------------------------------------- input checks (exit 2, one line)
    def parse_arguments(self, parser, args):
        # main() always passes the command line explicitly; LightningCLI's "args and sys.argv both given" warning
        # would fire on every run (and under pytest, whose sys.argv is not ours), so parse without it
        self.config = parser.parse_args(args)
        # before Lightning's own torch.load of --ckpt_path, which dies with a traceback on a bad file
        self._checkpoint = None
        subcommand = self.config.get("subcommand")
        ckpt_path = _resolve_ckpt_keyword(self.config[subcommand]) if subcommand else None
        if ckpt_path and str(ckpt_path) not in _LIGHTNING_CKPT_KEYWORDS:
            # the loader's every check (schemas/loading.py): Lightning then imports the checkpoint's _class_path
            # and loads its hyperparameters and weights, which must have passed first
            self._checkpoint = read_checkpoint(str(ckpt_path))
            checked = check_checkpoint(self._checkpoint, str(ckpt_path))
            _check_same_class(checked.cls, self.config[subcommand].get("model"), ckpt_path)

    def before_instantiate_classes(self):
        config = self.config[self.subcommand]
        if config["trainer"].get("enable_progress_bar") is False:
            # Lightning refuses a progress-bar callback beside enable_progress_bar=False; ours is always in the
            # callbacks, so the Trainer flag switches it off instead (same effect: no bar)
            config["progress"]["enabled"] = False
            config["trainer"]["enable_progress_bar"] = True
        if config["trainer"].get("enable_checkpointing") is False and config.get("checkpoint") is not None:
            # likewise for the always-present ModelCheckpoint: it keeps nothing instead
            config["checkpoint"]["save_top_k"] = 0
            config["checkpoint"]["save_last"] = False
            config["trainer"]["enable_checkpointing"] = True
        if str(config["trainer"].get("precision")) in ("16-true", "bf16-true"):  # before any file is written
            raise BodySchemaInputError(half_precision_refusal(config["trainer"]["precision"]))
        _check_monitor(config.get("checkpoint"))
        if self.subcommand == "fit":
            _check_max_epochs(config)
            if config.get("lr_scheduler") and not config.get("optimizer"):
                # LightningCLI would drop it without a word: the schema's own optimizer brings its own schedule
                raise BodySchemaInputError(
                    f"--lr_scheduler {config['lr_scheduler'].get('class_path')} needs --optimizer too (e.g. "
                    "--optimizer Adam --optimizer.lr 1e-3); without --optimizer the schema trains with Adam and "
                    "its cosine schedule from --model.lr to --model.lr_final")
        if self._checkpoint is not None:  # before the trainer exists: nothing printed, nothing written
            data = _data_module(config["data"])  # light: the robot only (a recorded file is read), no dataset yet
            _check_same_robot(self._checkpoint, config.get("ckpt_path"), data)


    def before_fit(self):
        # before the dataset is built and the run folder written (Lightning checks this only once the fit loop starts)
        if hasattr(self.datamodule, "train_batches_per_epoch"):
            check_val_check_interval(self.trainer, self.datamodule.train_batches_per_epoch(self.trainer.world_size))

    def before_validate(self):
        self._log_beside_the_checkpoint("validate")

    def before_test(self):
        self._log_beside_the_checkpoint("test")

    def _log_beside_the_checkpoint(self, subcommand: str):
        """With the default logger, validate and test log (and the benchmark writes its tables) into
        ``<the checkpoint's run>/<subcommand>``, else ``<default_root_dir>/lightning_logs/<subcommand>``: never a new
        ``version_N`` folder, which would shift the version of the next fit into that root."""
        if self.config[subcommand]["trainer"].get("logger") not in (None, True) or not self.trainer.loggers:
            return  # the user's own logger (or none) decides
        ckpt = self.config[subcommand].get("ckpt_path")
        folder = os.path.dirname(os.path.abspath(str(ckpt))) if ckpt else ""
        if os.path.basename(folder) == "checkpoints":
            folder = os.path.dirname(folder)  # .../version_N: the fit that wrote the checkpoint
        else:
            folder = os.path.join(self.trainer.default_root_dir, "lightning_logs")
        self.trainer.loggers = [TensorBoardLogger(save_dir=folder, name="", version=subcommand,
                                                  default_hp_metric=False)]

    def after_fit(self):
        outputs = fit_outputs(self.trainer)  # on every rank: trainer.log_dir is a collective under DDP
        if self.trainer.is_global_zero:
            print(outputs)


def fit_outputs(trainer) -> str:
    """Where a finished fit wrote what a user looks at next: its checkpoint, logs, TensorBoard events and the
    in-fit fault benchmark (scalars and box plots in those events; ``bodyschema test`` writes the full tables)."""
    checkpoint = trainer.checkpoint_callback
    ckpt = checkpoint and (checkpoint.last_model_path or checkpoint.best_model_path)
    events = [lg.log_dir for lg in trainer.loggers if type(lg).__name__ == "TensorBoardLogger"]
    lines = ["fit done. Outputs:",
             f"  checkpoint:   {ckpt or 'none kept (--trainer.enable_checkpointing=false)'}",
             f"  logs, config: {trainer.log_dir}"]
    if events:
        lines += [f"  TensorBoard:  tensorboard --logdir {events[0]}",
                  "  benchmark:    the in-fit fault benchmark is in those events (scalars fault/*, "
                  "figure fault/boxplots)"]
    if ckpt:
        lines.append(f"  full benchmark tables: bodyschema test --config <this fit's config> --ckpt_path {ckpt}")
    return "\n".join(lines)


def _data_module(data_config):
    """The configured data module (``--data`` is a subclass of EquilibriumDataModule: RecordedDataModule too)."""
    classes = {cls.__name__: cls for cls in (EquilibriumDataModule, RecordedDataModule)}
    name = str(data_config["class_path"]).rpartition(".")[2]
    cls = classes.get(name)
    if cls is None:
        raise BodySchemaInputError(f"--data {data_config['class_path']!r}: --ckpt_path is checked against "
                                   f"{list(classes)} only")
    return cls(**data_config["init_args"].as_dict())


# a misspelt flag is an error, not a prefix of some option (argparse's default would run
# `--trainer.max_epoch=3` as max_epochs); config files never accepted abbreviations either
_NO_ABBREVIATIONS = {"allow_abbrev": False, **{name: {"allow_abbrev": False} for name in BodySchemaCLI.subcommands()}}


def _trainer_defaults() -> dict:
    return {
        "max_epochs": 10000,  # the paper's setting
        "check_val_every_n_epoch": 500,
        "log_every_n_steps": 50,  # optimizer steps: every 5 epochs of the paper's 640 samples in batches of 64
        "num_sanity_val_steps": 0,
        "enable_model_summary": False,
        "default_root_dir": "runs",  # every output of a run under runs/ (git-ignored), not the working tree
    }


def _cli_kwargs(args: list[str]) -> dict:
    """``BodySchemaCLI``'s arguments for the command line ``args`` (also what ``known_options`` builds)."""
    return dict(args=args, seed_everything_default=0, save_config_kwargs={"overwrite": True},
                trainer_defaults=_trainer_defaults(), subclass_mode_model=True, subclass_mode_data=True,
                parser_kwargs={**_NO_ABBREVIATIONS, "prog": "bodyschema", "description": DESCRIPTION},
                parser_class=OneLineErrorParser)


def run(args: list[str]) -> "BodySchemaCLI":
    """Run ``bodyschema`` on ``args`` (``cli.main``); a user error exits 2 with one line."""
    torch.set_num_threads(1)  # one thread per process is fastest for these tiny MLPs (docs/design.md: data, training)
    torch.set_flush_denormal(True)
    # 10 optimizer steps per epoch with the paper's data: the "fewer batches than log interval" notice is noise
    warnings.filterwarnings("ignore", message=".*smaller than the logging interval.*")
    warnings.filterwarnings("ignore", message=".*LeafSpec.*")
    # --optimizer / --lr_scheduler replace the schema's default Adam + cosine by design (README, Lightning)
    warnings.filterwarnings("ignore", message=".*configure_optimizers` will be overridden by.*")
    for name in ("lightning.pytorch.utilities.rank_zero", "lightning.fabric.utilities.rank_zero"):
        logging.getLogger(name).addFilter(_no_tip)  # the same function: added once however often run() is
    _SEED_NOTE.holding, _SEED_NOTE.held = True, []
    logging.getLogger("lightning.fabric.utilities.seed").addFilter(_SEED_NOTE)
    try:
        return BodySchemaCLI(BodySchema, EquilibriumDataModule, **_cli_kwargs(args))
    except Exception as err:  # jsonargparse wraps errors raised while instantiating classes
        cause = _input_error_in_chain(err)
        if cause is None:
            raise
        print(f"error: {' '.join(str(cause).split())}", file=sys.stderr)  # one line, whatever the message
        raise SystemExit(2) from None


def _no_tip(record: logging.LogRecord) -> bool:
    """False for Lightning's "Tip: ... try installing litlogger / litmodels" lines, printed on every fit: advice
    about a cloud service, not about this run."""
    return "Tip:" not in str(record.msg)


class _ParserBuilt(Exception):
    """Raised by ``known_options``' CLI once its parser exists: nothing parsed, run or written."""


def known_options() -> dict[str, list[str]]:
    """Every ``--option`` each subcommand's parser accepts (``cli_options`` keeps a copy)."""

    class _ParserOnly(BodySchemaCLI):
        def parse_arguments(self, parser, args):
            raise _ParserBuilt(parser)

    try:
        _ParserOnly(BodySchema, EquilibriumDataModule, **_cli_kwargs([]))
    except _ParserBuilt as built:
        parser = built.args[0]
    chooser = next(a for a in parser._actions if isinstance(a, ActionSubCommands))
    return {name: _known_options(sub) for name, sub in sorted(chooser._name_parser_map.items())}


_LIGHTNING_CKPT_KEYWORDS = ("hpc", "registry")  # --ckpt_path values left to Lightning (not file paths)


def _resolve_ckpt_keyword(config):
    """``--ckpt_path last``: the newest ``last.ckpt`` under ``--trainer.default_root_dir`` (Lightning looks only in
    this run's new version folder, finds nothing and silently starts over); ``best`` and an empty path: one line."""
    ckpt_path = config.get("ckpt_path")
    if ckpt_path is None or str(ckpt_path) not in ("", "best", "last") and str(ckpt_path).strip():
        return ckpt_path
    if not str(ckpt_path).strip():  # `--ckpt_path "$CKPT"` with CKPT unset
        raise BodySchemaInputError(f"--ckpt_path {str(ckpt_path)!r} is empty: give a checkpoint file, last (the "
                                   "newest last.ckpt under --trainer.default_root_dir), or leave the option out")
    root = config["trainer"].get("default_root_dir") or os.getcwd()
    if ckpt_path == "best":
        raise BodySchemaInputError("--ckpt_path best is the best checkpoint of a fit run earlier in the same Python "
                                   "process, which a new bodyschema run has not; give its file (under "
                                   f"{os.path.join(root, 'lightning_logs', 'version_*', 'checkpoints')}) or last")
    found = glob.glob(os.path.join(glob.escape(str(root)), "**", "checkpoints", "last.ckpt"), recursive=True)
    if not found:
        raise BodySchemaInputError(f"--ckpt_path last: no .../checkpoints/last.ckpt under --trainer.default_root_dir "
                                   f"{str(root)!r}; give the checkpoint file, or the root of the earlier fit")
    config["ckpt_path"] = max(found, key=os.path.getmtime)
    print(f"--ckpt_path last: {config['ckpt_path']}")
    return config["ckpt_path"]


def _check_max_epochs(config):
    """Refuse epoch counts that train nothing, or forever under a schedule that needs an end."""
    steps = config["trainer"].get("max_steps")
    if steps is not None and steps != -1 and steps <= 0:
        raise BodySchemaInputError(f"--trainer.max_steps={steps} trains nothing; give a positive number of optimizer "
                                   "steps, or -1 (the default) to let max_epochs end the fit")
    epochs = config["trainer"].get("max_epochs")
    if epochs is None or epochs > 0:
        return
    if epochs != -1:
        raise BodySchemaInputError(f"--trainer.max_epochs={epochs} trains nothing; give a positive number of "
                                   "epochs (or -1 for endless training with a constant learning rate)")
    if config["trainer"].get("max_steps") not in (None, -1):
        return  # bounded by steps, as Lightning documents: the schedule spans the epochs those steps take
    init_args = config["model"].get("init_args") if config.get("model") is not None else None
    if init_args is not None and init_args.get("lr_final") is not None:
        raise BodySchemaInputError(
            f"--trainer.max_epochs=-1 (endless training) cannot anneal the learning rate to "
            f"--model.lr_final={init_args.get('lr_final')}; give a positive max_epochs or max_steps, "
            "or --model.lr_final=null for a constant learning rate")


def _check_monitor(checkpoint_config):
    """Refuse a checkpoint monitor on a renamed metric (Lightning would warn, each validation, that it is missing)."""
    monitor = str((checkpoint_config or {}).get("monitor") or "")
    stage, _, name = monitor.rpartition("/")
    if name in RENAMED_METRICS:
        raise BodySchemaInputError(f"--checkpoint.monitor={monitor}: that metric is now "
                                   f"{stage + '/' if stage else ''}{RENAMED_METRICS[name]} (the same quantity, in N m)")


def _check_same_class(cls, model_config, ckpt_path):
    """Refuse a checkpoint of another schema class than --model (Lightning would fail on its hyperparameters)."""
    named = model_config.get("class_path") if model_config is not None else None
    if named and schema_class(str(named), where="--model") is not cls:
        raise BodySchemaInputError(f"--ckpt_path {str(ckpt_path)!r} holds a {cls.__name__}, but --model is {named}; "
                                   f"give --model={cls.__name__} (or the config the checkpoint was trained with)")


def _check_same_robot(checkpoint: dict, ckpt_path, datamodule):
    """Refuse a checkpoint whose robot (model XML, muscles, spring) is not the data module's.

    Lightning would otherwise fail deep inside ``load_state_dict`` (other sizes) or, worse, run a
    same-sized schema of another robot without a word.
    """
    trained = checkpoint.get("hyper_parameters", {}).get("robot") or {}
    trained_hash, here = checkpoint["bodyschema"].get("model_xml_sha256"), datamodule.robot
    differs = [what for what, same in (
        ("model XML", trained_hash == datamodule.robot_model.xml_hash),
        ("muscles", list(trained.get("muscles", here["muscles"])) == list(here["muscles"])),
        ("spring", trained.get("spring", here["spring"]) == here["spring"])) if not same]
    if differs:
        raise BodySchemaInputError(
            f"--ckpt_path {str(ckpt_path)!r} was trained on another robot ({', '.join(differs)} differ): "
            f"{len(trained.get('muscles', []))} muscles {list(trained.get('muscles', []))} (xml sha256 "
            f"{str(trained_hash)[:12]}), but the data's robot is {datamodule.robot_model} (xml sha256 "
            f"{datamodule.robot_model.xml_hash[:12]}); give the config (--data.*) the checkpoint was trained with")


def _input_error_in_chain(err: BaseException | None) -> BaseException | None:
    """The user-input error at the root of ``err``'s cause/context chain, if there is one.

    Lightning's ``MisconfigurationException`` (e.g. an accelerator this machine lacks) is a user error too.
    """
    seen = set()
    while err is not None and id(err) not in seen:
        if isinstance(err, (BodySchemaInputError, MisconfigurationException)):
            return err
        seen.add(id(err))
        err = err.__cause__ or err.__context__
    return None

