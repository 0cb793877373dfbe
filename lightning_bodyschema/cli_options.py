"""The options each ``bodyschema`` subcommand accepts, copied from its parser, so that ``cli.main`` can refuse a
misspelt option before it imports torch and Lightning (seconds, where building the parser takes tens of seconds on
a loaded 2-core machine).

The copy is right for the Lightning version it was made with (``LIGHTNING_VERSION``; another version may have other
Trainer options: the quick check is then skipped) and for this package's callbacks (``tests/cli`` compares it to the
parser). Remake it with ``python -m lightning_bodyschema.cli_options`` after changing an option.
"""
from __future__ import annotations

import pprint
import sys
from pathlib import Path

LIGHTNING_VERSION = '2.6.6'
COMMON = ['--checkpoint', '--checkpoint.auto_insert_metric_name', '--checkpoint.dirpath',
 '--checkpoint.enable_version_counter', '--checkpoint.every_n_epochs', '--checkpoint.every_n_train_steps',
 '--checkpoint.filename', '--checkpoint.mode', '--checkpoint.monitor', '--checkpoint.save_last',
 '--checkpoint.save_on_exception', '--checkpoint.save_on_train_epoch_end', '--checkpoint.save_top_k',
 '--checkpoint.save_weights_only', '--checkpoint.train_time_interval', '--checkpoint.verbose', '--ckpt_path',
 '--config', '--data', '--data.help', '--faults', '--faults.binding_n_per_condition',
 '--faults.every_n_epochs', '--faults.n_per_condition', '--faults.out_dir', '--faults.protocols',
 '--faults.seed', '--faults.settle_check', '--faults.variant', '--figures', '--figures.every_n_validations',
 '--final_validation', '--final_validation.enabled', '--help', '--init_from', '--init_from.ckpt',
 '--init_from.keep_normalizer', '--lr_scheduler', '--lr_scheduler.help', '--model', '--model.help',
 '--optimizer', '--optimizer.help', '--print_config', '--progress', '--progress.enabled', '--seed_everything',
 '--trainer', '--trainer.accelerator', '--trainer.accelerator.help', '--trainer.accumulate_grad_batches',
 '--trainer.barebones', '--trainer.benchmark', '--trainer.callbacks', '--trainer.callbacks+',
 '--trainer.callbacks.help', '--trainer.check_val_every_n_epoch', '--trainer.default_root_dir',
 '--trainer.detect_anomaly', '--trainer.deterministic', '--trainer.devices', '--trainer.devices+',
 '--trainer.enable_autolog_hparams', '--trainer.enable_checkpointing', '--trainer.enable_model_summary',
 '--trainer.enable_progress_bar', '--trainer.fast_dev_run', '--trainer.gradient_clip_algorithm',
 '--trainer.gradient_clip_val', '--trainer.inference_mode', '--trainer.limit_predict_batches',
 '--trainer.limit_test_batches', '--trainer.limit_train_batches', '--trainer.limit_val_batches',
 '--trainer.log_every_n_steps', '--trainer.logger', '--trainer.logger+', '--trainer.logger.help',
 '--trainer.max_epochs', '--trainer.max_steps', '--trainer.max_time', '--trainer.min_epochs',
 '--trainer.min_steps', '--trainer.model_registry', '--trainer.num_nodes', '--trainer.num_sanity_val_steps',
 '--trainer.overfit_batches', '--trainer.plugins', '--trainer.plugins+', '--trainer.plugins.help',
 '--trainer.precision', '--trainer.profiler', '--trainer.profiler.help',
 '--trainer.reload_dataloaders_every_n_epochs', '--trainer.strategy', '--trainer.strategy.help',
 '--trainer.sync_batchnorm', '--trainer.use_distributed_sampler', '--trainer.val_check_interval',
 '--weights_only']  # every subcommand's
ONLY = {'fit': [], 'test': ['--verbose'], 'validate': ['--verbose']}  # one subcommand's


def options(subcommand: str) -> set[str]:
    """The options ``bodyschema <subcommand>`` accepts (empty for a name that is no subcommand)."""
    if subcommand not in ONLY:
        return set()
    return set(COMMON) | set(ONLY[subcommand])


def write(path: Path = Path(__file__)) -> None:
    """Replace ``LIGHTNING_VERSION``, ``COMMON`` and ``ONLY`` in this file by the installed Lightning's and the
    parsers' (``cli_app.known_options``)."""
    from importlib.metadata import version

    from .cli_app import known_options

    known = known_options()
    common = sorted(set.intersection(*(set(names) for names in known.values())))
    only = {name: sorted(set(names) - set(common)) for name, names in known.items()}
    text = path.read_text()
    body = (f"LIGHTNING_VERSION = {version('lightning')!r}\n"
            f"COMMON = {pprint.pformat(common, width=110, compact=True)}  # every subcommand's\n"
            f"ONLY = {pprint.pformat(only, width=110, compact=True)}  # one subcommand's\n")
    temporary = path.with_name(path.name + ".tmp")
    temporary.write_text(text[:text.index("LIGHTNING_VERSION = ")] + body + text[text.index("\n\n\ndef options(") + 1:])
    temporary.replace(path)


if __name__ == "__main__":
    write()
    sys.exit(0)
