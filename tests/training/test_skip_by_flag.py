"""A step with non-finite gradients is skipped without a read on the host when the optimizer is a fused Adam on an
accelerator (the check's flag goes to its ``found_inf``), and by dropping the gradients on the CPU and for any other
optimizer; either way the weights stay, and ``skipped_steps`` counts it. The flag path runs here on the CPU by
emptying ``HOST_READ_DEVICES``."""
import lightning as L
import pytest
import torch
from lightning.pytorch.callbacks import Callback

from lightning_bodyschema.schemas import DiffusionSchema
from lightning_bodyschema.training import lightning_module


class Overflowing(DiffusionSchema):
    """Its loss overflows at optimizer step 3; ``sgd``: a plain SGD instead of the default fused Adam."""

    sgd = False

    def training_loss(self, q_n, x_n):
        loss, logs = super().training_loss(q_n, x_n)
        return (loss * torch.finfo(loss.dtype).max * 4 if self.trainer.global_step == 3 else loss), logs

    def configure_optimizers(self):
        return torch.optim.SGD(self.parameters(), lr=1e-3) if self.sgd else super().configure_optimizers()


class Weights(Callback):
    def __init__(self):
        self.before, self.after, self.flags = {}, {}, {}

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        self.before[batch_idx] = [p.detach().clone() for p in pl_module.parameters()]

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
        self.after[batch_idx] = [p.detach().clone() for p in pl_module.parameters()]
        self.flags[batch_idx] = getattr(trainer.optimizers[0], "found_inf", None)


@pytest.mark.parametrize("path", ["flag", "host_read", "sgd"])
def test_an_overflowing_step_is_skipped_by_either_path(dm, path, monkeypatch):
    if path == "flag":  # the accelerator's path, on the CPU
        monkeypatch.setattr(lightning_module, "HOST_READ_DEVICES", frozenset())
    L.seed_everything(0)
    schema, weights = Overflowing(robot=dm.robot), Weights()
    schema.sgd = path == "sgd"
    L.Trainer(max_epochs=1, logger=False, enable_checkpointing=False, enable_progress_bar=False,
              enable_model_summary=False, num_sanity_val_steps=0, check_val_every_n_epoch=10,
              callbacks=[weights]).fit(schema, dm)
    assert all(torch.equal(a, b) for a, b in zip(weights.before[3], weights.after[3]))  # the overflow: untouched
    assert any(not torch.equal(a, b) for a, b in zip(weights.before[4], weights.after[4]))  # training goes on
    assert schema.skipped_steps == 1
    if path == "flag":  # set at every step, 1 only at the overflow
        assert [float(weights.flags[i]) for i in range(6)] == [0.0, 0.0, 0.0, 1.0, 0.0, 0.0]
    else:
        assert all(flag is None for flag in weights.flags.values())
    state = schema.trainer.optimizers[0].state
    if path != "sgd":  # Adam's own count of its steps: the skipped one is not among them
        steps = {int(state[p]["step"]) for p in schema.parameters()}
        assert steps == {schema.trainer.global_step - 1}
    assert all(torch.isfinite(p).all() for p in schema.parameters())


def test_both_paths_give_the_same_weights(dm, monkeypatch):
    """The flag path (fused step told to skip) and the host read (gradients dropped) leave the same weights."""
    results = []
    for devices in (frozenset(), frozenset({"cpu"})):
        monkeypatch.setattr(lightning_module, "HOST_READ_DEVICES", devices)
        L.seed_everything(0)
        schema = Overflowing(robot=dm.robot)
        L.Trainer(max_epochs=1, logger=False, enable_checkpointing=False, enable_progress_bar=False,
                  enable_model_summary=False, num_sanity_val_steps=0, check_val_every_n_epoch=10).fit(schema, dm)
        results.append([p.detach().clone() for p in schema.parameters()])
    assert all(torch.equal(a, b) for a, b in zip(*results))
