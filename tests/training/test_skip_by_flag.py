"""A step with non-finite gradients is skipped without a read on the host when the optimizer is a fused Adam (the
check's flag goes to its ``found_inf``), and by dropping the gradients for any other optimizer; either way the
weights stay, and ``skipped_steps`` counts it."""
import lightning as L
import pytest
import torch
from lightning.pytorch.callbacks import Callback

from lightning_bodyschema.schemas import DiffusionSchema


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


@pytest.mark.parametrize("sgd", [False, True], ids=["fused_adam", "sgd"])
def test_an_overflowing_step_is_skipped_by_either_path(dm, sgd):
    L.seed_everything(0)
    schema, weights = Overflowing(robot=dm.robot), Weights()
    schema.sgd = sgd
    L.Trainer(max_epochs=1, logger=False, enable_checkpointing=False, enable_progress_bar=False,
              enable_model_summary=False, num_sanity_val_steps=0, check_val_every_n_epoch=10,
              callbacks=[weights]).fit(schema, dm)
    assert all(torch.equal(a, b) for a, b in zip(weights.before[3], weights.after[3]))  # the overflow: untouched
    assert any(not torch.equal(a, b) for a, b in zip(weights.before[4], weights.after[4]))  # training goes on
    assert schema.skipped_steps == 1
    if sgd:
        assert all(flag is None for flag in weights.flags.values())
    else:  # the flag path: set at every step, 1 only at the overflow
        assert [float(weights.flags[i]) for i in range(6)] == [0.0, 0.0, 0.0, 1.0, 0.0, 0.0]
    assert all(torch.isfinite(p).all() for p in schema.parameters())
