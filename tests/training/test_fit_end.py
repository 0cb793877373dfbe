"""How a fit ends, whatever ends it: the final weights are validated, saved, benchmarked and drawn once.

Found by review, each failing on the code before its fix: step-counted validation (``check_val_every_n_epoch=None``)
ended unvalidated; EarlyStopping ended without the end-of-fit benchmark and figure; a last epoch with several
validations benchmarked at each; monitors on ``train/loss`` found no value; the sanity check counted as a validation.
"""
import warnings

import lightning as L
import pytest
import torch
from lightning.pytorch.callbacks import Callback, EarlyStopping, ModelCheckpoint
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from lightning_bodyschema.callbacks import FaultBenchmark, FinalValidation, ReconstructionFigure
from lightning_bodyschema.schemas import AutoEncoderSchema, DiffusionSchema, VAESchema

warnings.filterwarnings("ignore", message=".*does not have many workers.*")


class ValidatedAt(Callback):
    """The optimizer steps at which validations ended."""

    def __init__(self):
        self.steps = []

    def on_validation_end(self, trainer, pl_module):
        if not trainer.sanity_checking:
            self.steps.append(trainer.global_step)


def fit(schema, dm, tmp_path, callbacks=(), **options):
    defaults = dict(logger=L.pytorch.loggers.TensorBoardLogger(tmp_path), enable_progress_bar=False,
                    enable_model_summary=False, num_sanity_val_steps=0, enable_checkpointing=False)
    trainer = L.Trainer(callbacks=list(callbacks), **{**defaults, **options})
    trainer.fit(schema, dm)
    return trainer


def events(trainer):
    """{tag: [steps]} of the fit's TensorBoard scalars and images."""
    acc = EventAccumulator(trainer.logger.log_dir, size_guidance={"images": 0, "scalars": 0})
    acc.Reload()
    tags = acc.Tags()
    found = {tag: [e.step for e in acc.Scalars(tag)] for tag in tags["scalars"]}
    found.update({tag: [e.step for e in acc.Images(tag)] for tag in tags["images"]})
    return found


def benchmark_callbacks():
    return [FaultBenchmark(every_n_epochs=1000, n_per_condition=2, settle_check=False), FinalValidation(),
            ReconstructionFigure(every_n_validations=1000)]


@pytest.mark.parametrize("bound", [dict(max_steps=9, max_epochs=100), dict(max_epochs=3)])
def test_a_step_counted_fit_validates_and_saves_its_final_weights(dm, tmp_path, bound):
    """check_val_every_n_epoch=None with an int val_check_interval (the README's step-based pattern)."""
    L.seed_everything(0)
    validated, saves = ValidatedAt(), ModelCheckpoint(dirpath=tmp_path / "ckpt", save_last=True)
    trainer = fit(VAESchema(robot=dm.robot), dm, tmp_path, [validated, saves, FinalValidation()],
                  limit_train_batches=3, check_val_every_n_epoch=None, val_check_interval=4,
                  enable_checkpointing=True, **bound)
    assert trainer.global_step == 9 and validated.steps == [4, 8, 9]
    assert torch.load(tmp_path / "ckpt" / "last.ckpt", weights_only=True)["global_step"] == 9


def test_an_early_stopped_fit_is_benchmarked_and_drawn_at_its_stop(dm, tmp_path):
    L.seed_everything(0)
    stop = EarlyStopping(monitor="val/eq_residual_N_m", mode="min", patience=1, min_delta=1e3)
    trainer = fit(AutoEncoderSchema(robot=dm.robot), dm, tmp_path, [*benchmark_callbacks(), stop], max_epochs=50,
                  check_val_every_n_epoch=2, limit_train_batches=3)
    assert trainer.should_stop and trainer.global_step == 12  # stopped after its second validation
    logged = events(trainer)
    assert logged["fault/adapt_ok_fraction"] == [11] and logged["val/reconstruction"] == [11]


def test_the_last_epoch_benchmarks_once_at_its_end_not_at_each_validation(dm, tmp_path):
    L.seed_everything(0)
    trainer = fit(AutoEncoderSchema(robot=dm.robot), dm, tmp_path, benchmark_callbacks(), max_epochs=2,
                  limit_train_batches=4, val_check_interval=0.5, check_val_every_n_epoch=1)
    logged = events(trainer)
    assert logged["val/eq_residual_N_m"] == [1, 3, 5, 7]  # four validations, two in the last epoch
    assert logged["fault/adapt_ok_fraction"] == [7] and logged["val/reconstruction"] == [7]


@pytest.mark.parametrize("monitor", ["early_stopping", "checkpoint", "plateau"])
def test_train_loss_can_be_monitored(dm, tmp_path, monitor):
    """train/loss is logged every log_every_n_steps (a self.log costs a quarter of a step here), and at every
    epoch's end when a monitor reads it: EarlyStopping, ModelCheckpoint and ReduceLROnPlateau found nothing."""

    class Plateau(DiffusionSchema):
        def configure_optimizers(self):
            opt = torch.optim.Adam(self.parameters(), lr=1e-3)
            return {"optimizer": opt, "lr_scheduler": {
                "scheduler": torch.optim.lr_scheduler.ReduceLROnPlateau(opt, patience=0), "monitor": "train/loss"}}

    L.seed_everything(0)
    callbacks = {"early_stopping": [EarlyStopping(monitor="train/loss", patience=100, check_on_train_epoch_end=True)],
                 "checkpoint": [ModelCheckpoint(dirpath=tmp_path / "ckpt", monitor="train/loss", save_top_k=1),
                                FinalValidation()],  # saves at the fit's one validation, as in the CLI
                 "plateau": []}[monitor]
    schema = (Plateau if monitor == "plateau" else DiffusionSchema)(robot=dm.robot)
    trainer = fit(schema, dm, tmp_path, callbacks, max_epochs=3, limit_train_batches=3, log_every_n_steps=50,
                  check_val_every_n_epoch=100, enable_checkpointing=monitor == "checkpoint")
    assert trainer.global_step == 9 and float(trainer.callback_metrics["train/loss"]) > 0
    if monitor == "checkpoint":
        assert trainer.checkpoint_callback.best_model_score is not None


def test_the_sanity_check_is_not_counted_as_a_validation(dm, tmp_path):
    L.seed_everything(0)
    trainer = fit(DiffusionSchema(robot=dm.robot), dm, tmp_path, [ReconstructionFigure(every_n_validations=2)],
                  max_epochs=6, limit_train_batches=2, check_val_every_n_epoch=1, num_sanity_val_steps=1)
    assert events(trainer)["val/reconstruction"] == [3, 7, 11]  # the 2nd, 4th and 6th (last) validations
