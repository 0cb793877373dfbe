"""Validate at the end of every fit, whatever ``check_val_every_n_epoch`` or ``val_check_interval``.

The paper's configs validate every 500 epochs, so a 300-epoch run (``configs/quick.yaml`` over a 10000-epoch
config) would end without a single physical metric, figure or fault benchmark. This callback makes the last
epoch a validation epoch when it would not be one. The validation is Lightning's own (same loop, logging,
checkpoint monitors and callbacks), not a side run: only the interval changes, for that one epoch.
"""
from __future__ import annotations

import math

from lightning.pytorch.callbacks import Callback


class FinalValidation(Callback):
    """Make a fit's last epoch (by ``max_epochs`` or ``max_steps``) a validation epoch."""

    def __init__(self, enabled: bool = True):
        """enabled: False keeps Lightning's plain interval (no validation at the end unless it falls due)."""
        self.enabled = enabled
        self._interval = None  # the user's check_val_every_n_epoch while the last epoch is forced
        self._decided_epoch = None  # the epoch whose first batch (in this fit) was looked at

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        # decided at an epoch's first batch of this fit, not in on_train_epoch_start: a fit resumed from a
        # checkpoint starts inside (or right at) an epoch without that hook, and batch_idx says what is left
        if not self.enabled or trainer.current_epoch == self._decided_epoch:
            return
        self._decided_epoch = trainer.current_epoch
        if trainer.check_val_every_n_epoch is None:
            return
        remaining = math.ceil((trainer.num_training_batches - batch_idx) / trainer.accumulate_grad_batches)
        epoch = trainer.current_epoch + 1  # epochs completed when this one ends
        if _is_last_epoch(trainer, remaining) and epoch % trainer.check_val_every_n_epoch != 0:
            self._interval = trainer.check_val_every_n_epoch  # Lightning would skip validation here
            trainer.check_val_every_n_epoch = epoch  # epoch % epoch == 0: this epoch validates

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
        # Lightning validates at an epoch's last batch (epoch-counted validation, made due above), at a step-counted
        # interval, or on a requested stop. Where the fit ends otherwise, request the stop (the fit ends here anyway)
        # and Lightning validates: max_steps reached inside an epoch, or the last batch of a step-counted fit
        step_counted = trainer.max_steps is not None and trainer.max_steps > 0
        if not self.enabled or not (step_counted or trainer.check_val_every_n_epoch is None):
            return  # epoch-counted validation and no max_steps: Lightning validates the last epoch (made due above)
        last_batch = trainer.fit_loop.epoch_loop.batch_progress.is_last_batch
        by_steps = step_counted and trainer.global_step >= trainer.max_steps
        by_epochs = last_batch and _is_last_epoch(trainer, steps_left=None)
        if (by_steps and not last_batch) or (trainer.check_val_every_n_epoch is None and (by_steps or by_epochs)):
            trainer.should_stop = True

    def on_train_end(self, trainer, pl_module):
        self._restore(trainer)

    def on_exception(self, trainer, pl_module, exception):
        self._restore(trainer)

    def _restore(self, trainer):
        if self._interval is not None:
            trainer.check_val_every_n_epoch, self._interval = self._interval, None


def _is_last_epoch(trainer, steps_left) -> bool:
    """True when the epoch under way is the fit's last: ``max_epochs`` reached, or ``max_steps`` reached within the
    ``steps_left`` optimizer steps it still has."""
    if trainer.max_epochs is not None and trainer.max_epochs > 0 and trainer.current_epoch + 1 >= trainer.max_epochs:
        return True
    return (trainer.max_steps is not None and trainer.max_steps > 0 and steps_left not in (None, float("inf"))
            and trainer.global_step + steps_left >= trainer.max_steps)
