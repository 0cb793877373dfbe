"""One progress bar over all epochs: the paper trains 10000 tiny epochs, a bar per epoch is noise."""
from __future__ import annotations

from lightning.pytorch.callbacks import ProgressBar
from tqdm.auto import tqdm


class EpochProgressBar(ProgressBar):
    """``Epoch 1234/10000 [00:12<01:30, loss=0.012, val=0.15 N m]`` — updated once per epoch."""

    def __init__(self, enabled: bool = True):
        """enabled: False keeps logs clean (e.g. training in a background process writing to a file)."""
        super().__init__()
        self._enabled = enabled
        self.bar = None

    def disable(self):
        self._enabled = False

    def enable(self):
        self._enabled = True

    @property
    def is_enabled(self) -> bool:
        return self._enabled

    def on_train_start(self, trainer, pl_module):
        if self._enabled and trainer.is_global_zero:
            self.bar = tqdm(total=trainer.max_epochs, initial=trainer.current_epoch, desc="Epoch",
                            unit="ep", dynamic_ncols=True, mininterval=0.5)

    def on_train_epoch_end(self, trainer, pl_module):
        if self.bar is None:
            return
        self.bar.update(1)
        if trainer.current_epoch % 50 == 0:  # formatting metrics every epoch would cost more than training
            metrics = trainer.progress_bar_metrics
            post = {k.split("/")[-1]: f"{float(v):.4g}" for k, v in metrics.items()
                    if k in ("train/loss", "val/loss", "val/eq_residual_N_m")}
            self.bar.set_postfix(post, refresh=False)

    def on_validation_start(self, trainer, pl_module):
        # the bar advances at an epoch's end, after its validation: say what the pause before the last tick is
        if self.bar is None or trainer.sanity_checking:
            return
        due = any(cb._due_in_fit(trainer) for cb in trainer.callbacks if hasattr(cb, "_due_in_fit"))
        what = "validating, then the fault benchmark (~30 s on 2 cores)" if due else "validating"
        self.bar.set_description(f"Epoch {trainer.current_epoch + 1}: {what}", refresh=True)

    def on_validation_end(self, trainer, pl_module):
        if self.bar is not None and not trainer.sanity_checking:
            self.bar.set_description("Epoch", refresh=True)

    def on_train_end(self, trainer, pl_module):
        if self.bar is not None:
            self.bar.close()
            self.bar = None
