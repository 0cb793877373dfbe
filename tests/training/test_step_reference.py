"""What a Lightning training step does, against references computed by hand.

The step's fast paths (the non-finite check read on the host, ``optimizer_zero_grad`` setting the gradients to
None, no call into Lightning's clipping when nothing clips, the data module handing CPU batches over as they are,
train/* published without ``self.log``) must leave the maths and the users' curves as they were: the weights of a
fit equal a plain loop's bit for bit, and the TensorBoard scalars equal what ``self.log`` wrote."""
import csv
import math

import lightning as L
import pytest
import torch
from lightning.pytorch.callbacks import Callback
from lightning.pytorch.loggers import CSVLogger, TensorBoardLogger

from lightning_bodyschema.schemas import DiffusionSchema
from lightning_bodyschema.training.finite import all_finite


def fit(dm, schema, **options):
    defaults = dict(logger=False, enable_checkpointing=False, enable_progress_bar=False, enable_model_summary=False,
                    num_sanity_val_steps=0, check_val_every_n_epoch=10 ** 6, max_epochs=3)
    trainer = L.Trainer(**{**defaults, **options})
    trainer.fit(schema, dm)
    return trainer


@pytest.mark.parametrize("accumulate", [1, 2])
def test_a_fit_ends_with_the_weights_of_a_plain_loop(dm, accumulate):
    """Same seed, same minibatches (the data module's loader), the schema's loss, fused Adam stepped every
    ``accumulate`` batches on the mean gradient, the cosine schedule per epoch: the same weights, bit for bit."""
    epochs = 3
    L.seed_everything(0)
    schema = DiffusionSchema(robot=dm.robot)
    fit(dm, schema, max_epochs=epochs, accumulate_grad_batches=accumulate)

    L.seed_everything(0)
    ref = DiffusionSchema(robot=dm.robot)
    ref.normalizer.load_state_dict(dm.normalizer.state_dict())
    ref._minibatch_affine = ref.normalizer.affine()
    opt = torch.optim.Adam(ref.parameters(), lr=ref.hparams.lr, fused=True)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=epochs, eta_min=ref.hparams.lr_final)
    loader = dm.train_dataloader()
    for epoch in range(epochs):
        loader.sampler.set_epoch(epoch)
        for i, batch in enumerate(loader):
            loss, _ = ref.training_loss(*ref._normalized_minibatch(batch))
            (loss / accumulate).backward()
            if (i + 1) % accumulate == 0:
                assert all_finite([p.grad for p in ref.parameters()])
                opt.step()
                opt.zero_grad(set_to_none=True)
        sched.step()
    for (name, got), want in zip(schema.named_parameters(), ref.parameters()):
        assert torch.equal(got, want), name


class SelfLogged(DiffusionSchema):
    """The reference: train/loss and train/lr through Lightning's ``self.log`` on the steps the loggers write."""

    def _log_train(self, trainer, loss):
        if trainer._logger_connector.should_update_logs:
            self.log("train/loss", loss.detach(), prog_bar=True)
            self.log("train/lr", trainer.optimizers[0].param_groups[0]["lr"])


def scalars(logdir):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    events = EventAccumulator(str(logdir), size_guidance={"scalars": 0})
    events.Reload()
    return {tag: [(e.step, e.value) for e in events.Scalars(tag)] for tag in events.Tags()["scalars"]}


def test_tensorboard_curves_equal_what_self_log_writes(dm, tmp_path):
    """train/loss, train/lr and epoch at every log_every_n_steps-th optimizer step (Lightning's steps: 6, 13, ...
    for 7), with the values ``self.log`` wrote, and nothing else; the loss is the step's own, the learning rate the
    cosine schedule's at that epoch."""
    curves, losses = {}, {}
    for cls in (DiffusionSchema, SelfLogged):
        L.seed_everything(0)
        record = LossRecorder()
        logger = TensorBoardLogger(tmp_path, name=cls.__name__)
        fit(dm, cls(robot=dm.robot), logger=logger, log_every_n_steps=7, callbacks=[record])
        curves[cls], losses[cls] = scalars(logger.log_dir), record.losses
    ours = curves[DiffusionSchema]
    assert ours == curves[SelfLogged]
    assert set(ours) == {"train/loss", "train/lr", "epoch", "hp_metric"}  # hp_metric: the logger's own
    assert [step for step, _ in ours["train/loss"]] == [6, 13, 20, 27]  # 30 steps: 3 epochs of 10 minibatches
    assert [value for _, value in ours["epoch"]] == [0, 1, 2, 2]
    for step, value in ours["train/loss"]:
        assert value == pytest.approx(losses[DiffusionSchema][step], rel=1e-6)
    cosine = {epoch: 1e-5 + 0.5 * (1e-3 - 1e-5) * (1 + math.cos(math.pi * epoch / 3)) for epoch in range(3)}
    for (_, value), epoch in zip(ours["train/lr"], [0, 1, 2, 2]):
        assert value == pytest.approx(cosine[epoch], rel=1e-6)


class LossRecorder(Callback):
    """Each optimizer step's training loss, by the step's index."""

    def __init__(self):
        self.losses = {}

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
        self.losses[trainer.global_step - 1] = float(outputs["loss"])


def test_the_trainer_and_a_csv_logger_see_train_metrics_as_self_log_left_them(dm, tmp_path):
    """After a fit without monitors: train/loss in callback_metrics and logged_metrics (tensors) and in
    progress_bar_metrics (a number), equal to the last loss written; a CSV logger's rows hold train/loss,
    train/lr and epoch together, one row per logging step."""
    L.seed_everything(0)
    record = LossRecorder()
    logger = CSVLogger(tmp_path)
    trainer = fit(dm, DiffusionSchema(robot=dm.robot), logger=logger, log_every_n_steps=5, callbacks=[record])
    last = record.losses[29]
    assert float(trainer.callback_metrics["train/loss"]) == pytest.approx(last, rel=1e-6)
    assert float(trainer.logged_metrics["train/loss"]) == pytest.approx(last, rel=1e-6)
    assert trainer.progress_bar_metrics["train/loss"] == pytest.approx(last, rel=1e-6)
    assert "train/lr" in trainer.callback_metrics and "train/lr" not in trainer.progress_bar_metrics
    with open(f"{logger.log_dir}/metrics.csv") as f:
        rows = list(csv.DictReader(f))
    assert [int(r["step"]) for r in rows] == [4, 9, 14, 19, 24, 29]
    assert all(r["train/loss"] and r["train/lr"] and r["epoch"] for r in rows)
    assert float(rows[-1]["train/loss"]) == pytest.approx(last, rel=1e-6)


def test_the_data_module_hands_cpu_batches_over_and_lets_lightning_move_the_rest(dm):
    """A (q, x) tuple of CPU tensors bound for the CPU comes back as the same tuple; bound for another device,
    or of another kind, Lightning moves it (its tensors then lie on that device)."""
    q, x = dm.splits["train"]
    batch = (q[:4], x[:4])
    assert dm.transfer_batch_to_device(batch, torch.device("cpu"), 0) is batch
    moved = dm.transfer_batch_to_device(batch, torch.device("meta"), 0)
    assert [t.device.type for t in moved] == ["meta", "meta"] and [t.shape for t in moved] == [q[:4].shape, x[:4].shape]
    as_list = dm.transfer_batch_to_device([q[:4], x[:4]], torch.device("meta"), 0)
    assert isinstance(as_list, list) and as_list[0].device.type == "meta"


def test_batch_hooks_are_chosen_once_per_fit_and_still_reach_the_data_module(dm):
    """Lightning's choice of the data module's or the LightningModule's batch hooks is remembered for the fit
    (``fit_loop.remember_batch_hook_owners``; it returns False on a Lightning without the selector it memoises,
    which fails here first), and every batch still goes through the data module's ``transfer_batch_to_device``."""
    from lightning_bodyschema.data import EquilibriumDataModule
    from lightning_bodyschema.training.fit_loop import remember_batch_hook_owners

    class Counting(EquilibriumDataModule):
        transfers = 0

        def transfer_batch_to_device(self, batch, device, dataloader_idx):
            Counting.transfers += 1
            return super().transfer_batch_to_device(batch, device, dataloader_idx)

    data = Counting(cache_dir=None)
    seen = {}

    class Probe(Callback):
        def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
            selector = trainer._data_connector._datahook_selector
            seen["memoised"] = "get_instance" in vars(selector)
            seen["owner"] = selector.get_instance("transfer_batch_to_device")
            seen["again"] = remember_batch_hook_owners(trainer)

    L.seed_everything(0)
    fit(data, DiffusionSchema(robot=data.robot), max_epochs=1, callbacks=[Probe()])
    assert seen == {"memoised": True, "owner": data, "again": True}
    assert Counting.transfers == 10  # one per minibatch
