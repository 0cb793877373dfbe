"""Validate at the end of every fit, whatever ``check_val_every_n_epoch``.

The paper's configs validate every 500 epochs, so a 300-epoch run (``configs/quick.yaml`` over a 10000-epoch
config) would end without a single physical metric, figure or fault benchmark. This callback makes the last
epoch a validation epoch when it would not be one. The validation is Lightning's own (same loop, logging,
checkpoint monitors and callbacks), not a side run: only the interval changes, for that one epoch.
"""
from __future__ import annotations

from lightning.pytorch.callbacks import Callback


class FinalValidation(Callback):
    """Make a fit's last epoch (by ``max_epochs`` or ``max_steps``) a validation epoch."""

    def __init__(self, enabled: bool = True):
        """enabled: False keeps Lightning's plain interval (no validation at the end unless it falls due)."""
        self.enabled = enabled
        self._interval = None  # the user's check_val_every_n_epoch while the last epoch is forced
        self._epoch_start_step = None  # global_step when the current epoch started
        self._steps_per_epoch = None  # optimizer steps the last epoch took (a schema may step once per minibatch)

    def on_train_epoch_start(self, trainer, pl_module):
        self._epoch_start_step = trainer.global_step
        steps = self._steps_per_epoch or trainer.num_training_batches
        if not self.enabled or trainer.check_val_every_n_epoch is None or not _is_last_epoch(trainer, steps):
            return
        epoch = trainer.current_epoch + 1  # epochs completed when this one ends
        if epoch % trainer.check_val_every_n_epoch != 0:  # Lightning would skip validation here
            self._interval = trainer.check_val_every_n_epoch
            trainer.check_val_every_n_epoch = epoch  # epoch % epoch == 0: this epoch validates

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
        # max_steps reached inside an epoch: Lightning validates at an epoch's last batch or on a requested stop
        # only, so request the stop (the fit ends here anyway) and the epoch's validation runs
        if (self.enabled and trainer.max_steps is not None and trainer.max_steps > 0
                and trainer.global_step >= trainer.max_steps and not trainer.fit_loop.epoch_loop.batch_progress.is_last_batch):
            trainer.should_stop = True

    def on_train_epoch_end(self, trainer, pl_module):
        self._steps_per_epoch = trainer.global_step - self._epoch_start_step

    def on_train_end(self, trainer, pl_module):
        self._restore(trainer)

    def on_exception(self, trainer, pl_module, exception):
        self._restore(trainer)

    def _restore(self, trainer):
        if self._interval is not None:
            trainer.check_val_every_n_epoch, self._interval = self._interval, None


def _is_last_epoch(trainer, steps_per_epoch) -> bool:
    """True when the epoch starting now is the fit's last: ``max_epochs`` reached, or ``max_steps`` reached within it
    (``steps_per_epoch``: optimizer steps an epoch takes, as the previous epoch did)."""
    if trainer.max_epochs is not None and trainer.max_epochs > 0 and trainer.current_epoch + 1 >= trainer.max_epochs:
        return True
    return (trainer.max_steps is not None and trainer.max_steps > 0 and steps_per_epoch not in (None, float("inf"))
            and trainer.global_step + steps_per_epoch >= trainer.max_steps)
