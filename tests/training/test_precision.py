"""Every precision goes through Lightning's precision plugin on every optimizer step: a short fit trains under each
CPU precision, and a loss made to overflow is skipped (weights and optimizer state untouched), not applied."""
import copy

import lightning as L
import pytest
import torch
from lightning.pytorch.callbacks import Callback
from lightning.pytorch.plugins import MixedPrecision

from lightning_bodyschema.schemas import AutoEncoderSchema, DiffusionSchema, VAESchema

SCHEMAS = {"diff": DiffusionSchema, "ae": AutoEncoderSchema, "vae": VAESchema}
PRECISIONS = ["32-true", "64-true", "bf16-mixed"]


def fit(schema, dm, precision, callbacks=(), **options):
    plugins = []
    if precision == "16-mixed":  # Lightning maps 16-mixed on a CPU to bf16; ask for float16 + GradScaler explicitly
        plugins, precision = [MixedPrecision("16-mixed", "cpu", scaler=torch.amp.GradScaler("cpu"))], None
    trainer = L.Trainer(precision=precision, plugins=plugins, logger=False, enable_checkpointing=False,
                        enable_progress_bar=False, enable_model_summary=False, num_sanity_val_steps=0,
                        check_val_every_n_epoch=10 ** 6, callbacks=list(callbacks), **options)
    trainer.fit(schema, dm)
    return trainer


class Losses(Callback):
    def __init__(self):
        self.losses = []

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
        self.losses.append(float(outputs["loss"]))


@pytest.mark.parametrize("precision", PRECISIONS)
@pytest.mark.parametrize("name", SCHEMAS)
def test_a_short_fit_trains_under_every_cpu_precision(dm, name, precision):
    L.seed_everything(0)
    schema = SCHEMAS[name](robot=dm.robot)
    losses = Losses()
    fit(schema, dm, precision, [losses], max_epochs=8)
    first, last = sum(losses.losses[:10]) / 10, sum(losses.losses[-10:]) / 10
    assert last < 0.8 * first, f"{name} {precision}: mean loss {first:.4f} -> {last:.4f}"
    weights = list(schema.parameters())
    assert all(torch.isfinite(p).all() for p in weights)
    assert weights[0].dtype == (torch.float64 if precision == "64-true" else torch.float32)


def overflowing(cls, at_step):
    """``cls`` whose loss overflows (inf in any dtype) at optimizer step ``at_step``."""
    class Overflowing(cls):
        def training_loss(self, q_n, x_n):
            loss, logs = super().training_loss(q_n, x_n)
            if self.trainer.global_step == at_step:
                loss = loss * torch.finfo(loss.dtype).max * 4  # overflows to inf
            return loss, logs
    return Overflowing


class Snapshots(Callback):
    """Weights and Adam's state before and after every batch."""

    def __init__(self):
        self.before, self.after = {}, {}

    @staticmethod
    def _state(trainer, pl_module):
        state = trainer.optimizers[0].state
        steps = [int(state[p]["step"]) if p in state else 0 for p in pl_module.parameters()]
        return copy.deepcopy(pl_module.state_dict()), steps

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        self.before[trainer.global_step] = self._state(trainer, pl_module)

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
        self.after[batch_idx] = self._state(trainer, pl_module)


@pytest.mark.parametrize("precision", PRECISIONS + ["16-mixed"])
@pytest.mark.parametrize("name", ["diff", "ae", "vae"])
def test_an_overflowing_loss_is_skipped_not_applied(dm, name, precision):
    L.seed_everything(0)
    schema = overflowing(SCHEMAS[name], at_step=3)(robot=dm.robot)
    snaps = Snapshots()
    fit(schema, dm, precision, [snaps], max_epochs=1)
    (w_before, steps_before), (w_after, steps_after) = snaps.before[3], snaps.after[3]
    for key in w_before:
        if key.startswith(("encoder", "decoder", "eps_model")):
            assert torch.equal(w_before[key], w_after[key]), f"{key} changed by the overflowing step"
    assert steps_after == steps_before  # Adam's moments and step counts untouched
    if precision != "16-mixed":
        assert schema.skipped_steps == 1  # the GradScaler skips by itself (and lowers its scale) under 16-mixed
    w_next, _ = snaps.after[4]
    assert any(not torch.equal(w_after[k], w_next[k]) for k in w_after if k.startswith(("decoder", "eps_model")))
    assert all(torch.isfinite(p).all() for p in schema.parameters())


@pytest.mark.parametrize("name", ["diff", "ae"])
def test_16_mixed_clips_unscaled_gradients(dm, name):
    """The default optimizer was a fused Adam, which unscales inside its step: Lightning refused to clip under a
    GradScaler ("does not allow for gradient clipping"). The clipped norm is of the unscaled gradients."""
    class GradNorms(Callback):
        norms = []

        def on_train_start(self, trainer, pl_module):  # what the optimizer steps with: unscaled, then clipped
            trainer.optimizers[0].register_step_pre_hook(lambda *_: self.norms.append(float(
                torch.nn.utils.get_total_norm([p.grad for p in pl_module.parameters() if p.grad is not None]))))

    L.seed_everything(0)
    recorder = GradNorms()
    trainer = fit(SCHEMAS[name](robot=dm.robot), dm, "16-mixed", [recorder], max_steps=8, gradient_clip_val=1e-3)
    assert trainer.global_step == 8 and len(recorder.norms) == 8
    assert max(recorder.norms) <= 1e-3 * (1 + 1e-3)


@pytest.mark.parametrize("precision", ["bf16-true", "16-true"])
def test_half_true_precisions_are_refused_before_they_quantise_the_si_data(dm, precision):
    """Lightning casts every input batch to the 16-bit dtype first: lengths of ~0.15 m in 0.5 mm steps (bf16), and
    validation then died on ``.numpy()`` of a bfloat16 tensor. One clear error instead."""
    from lightning_bodyschema.errors import BodySchemaInputError

    with pytest.raises(BodySchemaInputError, match=f"precision={precision}.*bf16-mixed"):
        fit(DiffusionSchema(robot=dm.robot), dm, precision, max_steps=2)
