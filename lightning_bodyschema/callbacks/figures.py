"""TensorBoard figure of predicted vs true healthy commands at validation postures."""
from __future__ import annotations

import matplotlib.pyplot as plt
from lightning.pytorch.callbacks import Callback
from lightning.pytorch.utilities import rank_zero_only

from .._numpy import to_numpy
from ..plots.reconstruction import reconstruction_figure
from ..training.fit_loop import fit_ends_with_this_epoch
from .steps import averaged_weights_now, stopped_after_last_validation, validation_log_step


class ReconstructionFigure(Callback):
    """Every ``every_n_validations`` validations (and at the end of fit), log ``val/reconstruction``."""

    def __init__(self, every_n_validations: int = 5):
        self.every_n_validations = every_n_validations
        self._count = 0  # validations seen (Lightning's sanity check is not one)
        self._validated_at = self._logged_at = None  # log steps of the last validation and figure

    @rank_zero_only
    def on_validation_epoch_end(self, trainer, pl_module):
        if trainer.sanity_checking:
            return
        self._count += 1
        self._validated_at = validation_log_step(trainer)
        if self._count % self.every_n_validations == 0 or fit_ends_with_this_epoch(trainer):
            self.log_figure(trainer, pl_module)

    @rank_zero_only
    def on_train_end(self, trainer, pl_module):
        # a stop EarlyStopping requested after on_validation_epoch_end: the figure of the weights the fit ended with
        if stopped_after_last_validation(trainer, self._validated_at, self._logged_at):
            averaged_weights_now(trainer, pl_module)  # the weights the fit saves, under weight averaging too
            self.log_figure(trainer, pl_module)

    def log_figure(self, trainer, pl_module):
        experiment = getattr(trainer.logger, "experiment", None)
        if not hasattr(experiment, "add_figure"):
            return
        q, x = trainer.datamodule.splits["val"]
        l_motor, f = pl_module.infer(q)
        m = pl_module.n_muscles
        x = to_numpy(x)
        fig = reconstruction_figure(x[:, :m], l_motor, x[:, m:], f,
                                    title=f"{type(pl_module).__name__}, epoch {trainer.current_epoch}")
        self._logged_at = validation_log_step(trainer)
        experiment.add_figure("val/reconstruction", fig, global_step=self._logged_at)
        plt.close(fig)
