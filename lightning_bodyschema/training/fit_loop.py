"""What a schema, the callbacks and the CLI need to know about Lightning's fit loop, in one place.

Each function takes the ``Trainer`` (or a value of its configuration) and reads only what Lightning documents or
what these functions name; nothing here depends on a schema.
"""
from __future__ import annotations

import math

from lightning.pytorch.trainer.states import TrainerFn

from ..errors import BodySchemaInputError


def fit_ends_with_this_epoch(trainer) -> bool:
    """True at a validation (or an epoch's training end) after which the fit stops: the last batch of the last
    epoch of ``max_epochs`` (not a validation earlier in that epoch), ``max_steps`` reached (also inside an epoch),
    or a stop already requested. ``max_epochs=-1`` (endless) never ends by epochs. A stop that EarlyStopping
    requests after this validation is caught by ``on_train_end`` of the callbacks that ask."""
    last_batch = trainer.fit_loop.epoch_loop.batch_progress.is_last_batch
    by_epochs = last_batch and trainer.max_epochs is not None and 0 < trainer.max_epochs <= trainer.current_epoch + 1
    by_steps = trainer.max_steps is not None and trainer.max_steps > 0 and trainer.global_step >= trainer.max_steps
    return bool(by_epochs or by_steps or trainer.should_stop)


def is_last_batch(trainer) -> bool:
    """True while the fit loop runs the last training batch of an epoch."""
    return trainer.fit_loop.epoch_loop.batch_progress.is_last_batch


def logs_this_step(trainer) -> bool:
    """True on the steps Lightning's logger writes (its own test, so ``log_every_n_steps`` means what it documents)."""
    return trainer._logger_connector.should_update_logs


def publish_train_metrics(trainer, metrics: dict, prog_bar: tuple = (), to_loggers: bool = True) -> None:
    """What ``self.log(name, value)`` in a training step leaves behind, without Lightning's metric collection
    (whose every ``self.log`` costs a sizeable share of a small minibatch step): ``metrics`` (name -> 0-dim
    tensor) in ``trainer.callback_metrics`` and ``trainer.logged_metrics`` (what monitors and callbacks read),
    those named in ``prog_bar`` as numbers in ``trainer.progress_bar_metrics``, and with ``to_loggers`` written
    to every logger at the step Lightning writes this training step's values at, beside ``epoch`` as Lightning
    adds it, then saved (``logger.save()``, as Lightning does after each write)."""
    scalars = {name: float(value) for name, value in metrics.items()}
    trainer.callback_metrics.update(metrics)
    trainer.logged_metrics.update(metrics)
    trainer.progress_bar_metrics.update({name: scalars[name] for name in prog_bar if name in scalars})
    if not to_loggers:
        return
    step = trainer.fit_loop.epoch_loop._batches_that_stepped
    for logger in trainer.loggers:
        logger.log_metrics({**scalars, "epoch": trainer.current_epoch}, step=step)
        logger.save()


def remember_batch_hook_owners(trainer) -> bool:
    """Make Lightning's choice between the data module's and the LightningModule's batch hooks
    (``on_before_batch_transfer``, ``transfer_batch_to_device``, ``on_after_batch_transfer``) once per attached
    data, not at every batch: Lightning 2.x asks ``is_overridden`` of both twice per hook and batch, and the
    answer is fixed while its data-hook selector (one per ``fit`` / ``validate`` / ...) lives. The selector's
    ``get_instance`` is memoised on that selector alone. False (nothing changed) where this Lightning keeps no
    such selector."""
    selector = getattr(getattr(trainer, "_data_connector", None), "_datahook_selector", None)
    get_instance = getattr(selector, "get_instance", None)
    if get_instance is None or "get_instance" in vars(selector):
        return get_instance is not None
    owners: dict = {}

    def remembered(hook_name: str):
        if hook_name not in owners:
            owners[hook_name] = get_instance(hook_name)
        return owners[hook_name]
    selector.get_instance = remembered
    return True


def batches_trained_this_epoch(trainer) -> int:
    """The fit loop's count of this epoch's batches already trained on (what a checkpoint must resume after)."""
    return trainer.fit_loop.epoch_loop.batch_progress.current.processed


def limited_batches(trainer, batches: int) -> int:
    """The training batches of an epoch as Lightning runs them: ``limit_train_batches`` is a count or a fraction."""
    limit = trainer.limit_train_batches
    return min(batches, limit) if isinstance(limit, int) else max(1, int(batches * limit))


def check_val_check_interval(trainer, batches_per_epoch: int) -> None:
    """An int ``val_check_interval`` counts batches within an epoch (unless ``check_val_every_n_epoch`` is None):
    refuse one longer than the epoch in one line (the CLI before anything is written), not with Lightning's
    ValueError once the fit loop starts."""
    interval = trainer.val_check_interval
    if not isinstance(interval, int) or isinstance(interval, bool) or trainer.check_val_every_n_epoch is None:
        return
    batches = limited_batches(trainer, batches_per_epoch)
    if interval > batches:
        raise BodySchemaInputError(
            f"--trainer.val_check_interval={interval} is more than the {batches} training batches of an epoch; give "
            f"at most {batches}, a fraction of an epoch (e.g. 0.5), or --trainer.check_val_every_n_epoch=null to "
            f"count {interval} steps across epochs")


def weight_averaging_last(trainer) -> None:
    """Put Lightning's ``WeightAveraging`` callbacks (``EMAWeightAveraging``, SWA) after every other callback but the
    checkpoints, in place. They swap the averaged weights in at ``on_validation_epoch_start`` and the trained ones
    back at ``on_validation_epoch_end``: a callback that scores or plots the validated weights in its own
    ``on_validation_epoch_end`` (the fault benchmark, the reconstruction figure) must run before that swap."""
    from lightning.pytorch.callbacks import Checkpoint, WeightAveraging

    averaging = [cb for cb in trainer.callbacks if isinstance(cb, WeightAveraging)]
    if averaging:
        others = [cb for cb in trainer.callbacks if not isinstance(cb, (WeightAveraging, Checkpoint))]
        checkpoints = [cb for cb in trainer.callbacks if isinstance(cb, Checkpoint)]
        trainer.callbacks[:] = others + averaging + checkpoints


def check_same_batch_size(schema_batch_size, data_batch_size) -> None:
    """The data module serves the minibatches; the schema's ``batch_size`` (which its checkpoint records) must be
    the same number. The CLI links ``--model.batch_size`` to the data module; in Python give both."""
    if None not in (schema_batch_size, data_batch_size) and schema_batch_size != data_batch_size:
        raise BodySchemaInputError(f"the schema's batch_size={schema_batch_size} differs from the data module's "
                                   f"batch_size={data_batch_size}; give both the same (the CLI links "
                                   "--model.batch_size to the data)")


def monitors_train_metrics(trainer) -> bool:
    """Does a callback or a scheduler monitor a ``train/*`` metric (which then must be fresh at every epoch end)?"""
    monitors = [getattr(cb, "monitor", None) for cb in trainer.callbacks]
    monitors += [config.monitor for config in trainer.lr_scheduler_configs]
    return any(isinstance(m, str) and m.startswith("train/") for m in monitors)


def half_precision_refusal(precision) -> str:
    """Why ``16-true`` / ``bf16-true`` are refused (Lightning casts every input batch to that dtype first)."""
    return (f"--trainer.precision={precision} casts the SI data themselves (lengths in m, tensions in N) to a "
            "16-bit float before the schema sees them (bfloat16 keeps ~3 digits: 0.5 mm steps on a 0.15 m "
            "length); use 16-mixed or bf16-mixed (float32 weights and data, 16-bit matmuls), 32-true or 64-true")


def mixed_precision_refusal(schema_name: str, precision) -> str:
    """Why a schema whose ``MIXED_PRECISION`` is False refuses ``16-mixed`` / ``bf16-mixed``."""
    return (f"--trainer.precision={precision}: {schema_name} learns muscle lengths to hundredths of a millimetre "
            "(1e-4 of their spread) and a 16-bit matmul keeps ~3 significant digits; use 32-true or 64-true "
            "(on a GPU too)")


def is_fitting(trainer) -> bool:
    """True while ``trainer`` (or None) runs a fit."""
    return trainer is not None and trainer.state.fn == TrainerFn.FITTING


def drop_checkpoint_callback_state_unless_fitting(trainer, checkpoint: dict) -> None:
    """Forget the saved ``ModelCheckpoint`` state when a checkpoint is only evaluated (validate / test).

    That state (best score, best paths) matters only to a resumed fit. A ``bodyschema test`` logs into a new
    version folder, so Lightning would find another dirpath and warn that best_model_score "won't be reloaded",
    which is right and irrelevant there. The weights, hyperparameters and RNG state are untouched.
    """
    if trainer is None or trainer.state.fn in (None, TrainerFn.FITTING) or "callbacks" not in checkpoint:
        return
    checkpoint["callbacks"] = {key: state for key, state in checkpoint["callbacks"].items()
                               if not str(key).startswith("ModelCheckpoint")}


def epochs_of_fit(trainer) -> int:
    """Epochs this fit will run: ``max_epochs``, or fewer when ``max_steps`` ends it first."""
    epochs = int(trainer.max_epochs) if trainer.max_epochs not in (None, -1) else None
    if trainer.max_steps not in (None, -1):
        batches = trainer.num_training_batches
        if batches in (None, float("inf")) or batches == 0:  # not known yet when optimizers are configured
            batches = limited_batches(
                trainer, len(trainer.datamodule.train_dataloader()) if trainer.datamodule is not None else 1)
        steps_per_epoch = max(1, math.ceil(batches / trainer.accumulate_grad_batches))
        by_steps = math.ceil(trainer.max_steps / steps_per_epoch)
        epochs = by_steps if epochs is None else min(epochs, by_steps)
    return max(1, epochs or 1)
