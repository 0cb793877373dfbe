"""``SchemaLightningModule``: the Lightning side of every body schema (``schemas.BodySchema`` inherits it).

What it does with the schema's contract (``contract.py``): one training step per minibatch on normalized data
(``training_loss``), validation and test in physical units (``physical_errors``), ``predict`` through ``infer``,
the declared hooks (``epoch_hook``, ``refreshes_derived_state``) at the points of the fit they need, Adam with a
cosine schedule, a skipped step for non-finite gradients, and the RNG state in checkpoints. The schema supplies
``normalizer``, ``robot_model``, ``capabilities``, ``training_loss``, ``physical_errors``, ``infer`` and
``clear_caches``.
"""
from __future__ import annotations

import lightning as L
import torch
from lightning.pytorch.plugins.precision import HalfPrecision, MixedPrecision

from ..contract import EPOCH_HOOK, REFRESHES_DERIVED_STATE
from ..errors import BodySchemaInputError
from .finite import all_finite, non_finite_flag
from .fit_loop import (check_same_batch_size, check_val_check_interval, drop_checkpoint_callback_state_unless_fitting,
                       epochs_of_fit, half_precision_refusal, is_fitting, is_last_batch, logs_this_step,
                       mixed_precision_refusal,
                       monitors_train_metrics, publish_train_metrics, remember_batch_hook_owners,
                       weight_averaging_last)

# renamed metrics: old name -> new name (one name per quantity: the old one is no longer logged; CHANGELOG.md)
RENAMED_METRICS = {"eq_residual_nm": "eq_residual_N_m"}


class SchemaLightningModule(L.LightningModule):
    """The fit, validation, test and predict loops of a body schema; see the module docstring."""

    def __init__(self):
        super().__init__()
        self.skipped_steps = 0  # optimizer steps skipped for non-finite gradients in this fit
        self._log_train_at_epoch_end = False  # set when a fit starts: log train/* at every epoch end too
        self._minibatch_affine = None  # the normalizer's affine maps during a fit (``_normalized_minibatch``)

    # Lightning sets ``_current_fx_name`` twice around every hook it calls (dozens of times per optimizer step), and
    # nn.Module.__setattr__ checks each time whether a string is a parameter, buffer or module. A plain string can
    # be none of these: it goes straight into the instance dict (the class defines no descriptor of that name).
    # False: the schema refuses 16-mixed / bf16-mixed (its maths needs more digits than a 16-bit matmul keeps)
    MIXED_PRECISION = True

    @property
    def skipped_steps(self) -> int:
        """Optimizer steps skipped for non-finite gradients in this fit (a fused optimizer's skips are counted on
        the device and read here)."""
        on_device = self.__dict__.get("_skipped_on_device")
        return self._skipped_counted + (0 if on_device is None else int(on_device))

    @skipped_steps.setter
    def skipped_steps(self, value: int) -> None:
        self.__dict__["_skipped_counted"], self.__dict__["_skipped_on_device"] = int(value), None

    def __setattr__(self, name, value):
        if name == "_current_fx_name" and (type(value) is str or value is None):
            self.__dict__[name] = value
        else:
            super().__setattr__(name, value)

    def setup(self, stage: str):
        if self._trainer is not None and isinstance(self.trainer.precision_plugin, HalfPrecision):
            raise BodySchemaInputError(half_precision_refusal(self.trainer.precision))
        if self._trainer is not None and isinstance(self.trainer.precision_plugin, MixedPrecision) \
                and not self.MIXED_PRECISION:
            raise BodySchemaInputError(mixed_precision_refusal(type(self).__name__, self.trainer.precision))
        datamodule = getattr(self.trainer, "datamodule", None) if self._trainer is not None else None
        if datamodule is not None and stage == "fit":
            if datamodule.robot_model.xml_hash != self.robot_model.xml_hash:
                raise BodySchemaInputError("the schema's robot differs from the data module's robot")
            self.normalizer.load_state_dict(datamodule.normalizer.state_dict())
            self.clear_caches()  # the penalty builder depends on the normalizer
            check_same_batch_size(self.hparams.get("batch_size"), getattr(datamodule, "batch_size", None))
            if hasattr(datamodule, "train_batches_per_epoch"):
                check_val_check_interval(self.trainer, datamodule.train_batches_per_epoch(self.trainer.world_size))
        if self._trainer is not None and stage == "fit":
            weight_averaging_last(self.trainer)  # validation callbacks see the averaged weights they validate

    def configure_optimizers(self):
        """Adam (fused, unless a GradScaler runs) with the cosine schedule from ``lr`` to ``lr_final`` over the
        fit's epochs, stepped once per epoch. The CLI's ``--optimizer`` / ``--lr_scheduler`` replace both
        (LightningCLI's own mechanism)."""
        # under a GradScaler (16-mixed) not fused: a fused Adam unscales inside its own step, so Lightning could
        # neither clip (it refuses) nor show the hooks unscaled gradients
        scaler = getattr(self.trainer.precision_plugin, "scaler", None) if self._trainer is not None else None
        optimizer = torch.optim.Adam(self.parameters(), lr=self.hparams.lr, fused=scaler is None)
        if self.hparams.lr_final is None:
            return optimizer
        schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, T_max=epochs_of_fit(self.trainer),
                                                              eta_min=self.hparams.lr_final)
        return {"optimizer": optimizer, "lr_scheduler": schedule}

    def _normalized(self, batch):
        q, x = batch
        dtype = self.dtype
        return self.normalizer.encode_q(q).to(dtype), self.normalizer.encode_x(x).to(dtype)

    def _normalized_minibatch(self, batch):
        """``_normalized`` of a training minibatch, as one multiply-add per tensor with the normalizer's affine
        maps taken when the fit started (``on_train_start``)."""
        if self._minibatch_affine is None:
            return self._normalized(batch)
        (q, x), (q_scale, q_shift, x_scale, x_shift), dtype = batch, self._minibatch_affine, self.dtype
        return torch.addcmul(q_shift, q, q_scale).to(dtype), torch.addcmul(x_shift, x, x_scale).to(dtype)

    def training_step(self, batch, batch_idx):
        """One minibatch: Lightning runs the backward, the precision plugin (scaling, unscaling, inf checks),
        gradient clipping and accumulation, DDP's gradient averaging and the optimizer step."""
        q_n, x_n = self._normalized_minibatch(batch)
        loss, _ = self.training_loss(q_n, x_n)
        self._log_train(self.trainer, loss)
        return loss

    def _log_train(self, trainer, loss) -> None:
        """train/loss and train/lr on the steps the loggers write, and at each epoch's last batch when a monitor
        (EarlyStopping, ModelCheckpoint, ReduceLROnPlateau) reads train/*; published as a training step's
        ``self.log(..., prog_bar=True)`` leaves them (``fit_loop.publish_train_metrics``)."""
        writes, monitored = logs_this_step(trainer), self._log_train_at_epoch_end and is_last_batch(trainer)
        if not (writes or monitored):
            return
        metrics = {"train/loss": loss.detach()}
        if trainer.optimizers and trainer.optimizers[0].param_groups:  # none: a least-squares body
            metrics["train/lr"] = torch.tensor(trainer.optimizers[0].param_groups[0]["lr"])
        publish_train_metrics(trainer, metrics, prog_bar=("train/loss",), to_loggers=writes)

    def on_before_optimizer_step(self, optimizer):
        """Skip a step whose gradients are not finite (an overflowing loss), in every precision.

        ``16-mixed``'s GradScaler already skips such steps (and lowers its scale); for the other precisions, on an
        accelerator, a fused Adam / AdamW gets the check's flag as ``found_inf`` and skips inside its step (nothing
        is read on the host); on the CPU and for any other optimizer the flag is read and the gradients dropped:
        either way the weights and the optimizer's state stay untouched. Under DDP the gradients are already
        averaged here, so every rank takes the same decision.
        """
        scaler = getattr(self.trainer.precision_plugin, "scaler", None)
        if scaler is not None:
            return
        # the optimizer's own parameter list: what it is about to step, and cheaper than walking the modules
        params = [p for group in optimizer.param_groups for p in group["params"] if p.grad is not None]
        if not params:
            return
        # no read on the host with a fused optimizer on an accelerator: the CPU keeps queueing its kernels
        found_inf = non_finite_flag([p.grad for p in params]) if _skips_by_flag(optimizer, params[0]) else None
        if found_inf is not None:
            optimizer.found_inf = found_inf  # the fused step leaves weights and moments alone where it is 1
            counted = self.__dict__.get("_skipped_on_device")
            self.__dict__["_skipped_on_device"] = found_inf if counted is None else counted + found_inf
            return
        if getattr(optimizer, "found_inf", None) is not None:
            optimizer.found_inf = None  # a flag of an earlier step must not skip this one
        if not all_finite([p.grad for p in params]):  # one kernel
            for p in params:
                p.grad = None
            self.__dict__["_skipped_counted"] += 1

    def optimizer_zero_grad(self, epoch, batch_idx, optimizer):
        """Lightning's hook before each step's backward: the gradients set to None, which is what a torch
        optimizer's own ``zero_grad()`` does, in one pass over its parameters (without torch's profiler range
        around it). An optimizer with a ``zero_grad`` of its own runs that."""
        if type(optimizer).zero_grad is not torch.optim.Optimizer.zero_grad:
            optimizer.zero_grad()
            return
        for group in optimizer.param_groups:
            for param in group["params"]:
                param.grad = None

    def configure_gradient_clipping(self, optimizer, gradient_clip_val=None, gradient_clip_algorithm=None):
        """Lightning's clipping, called before every optimizer step; with no ``gradient_clip_val`` (here or on the
        Trainer) there is nothing to clip and it returns at once, without Lightning's checks of the arguments."""
        if gradient_clip_val or self._fabric is not None or self.trainer.gradient_clip_val:
            super().configure_gradient_clipping(optimizer, gradient_clip_val, gradient_clip_algorithm)

    def on_train_start(self):
        self.skipped_steps = 0
        self._minibatch_affine = self.normalizer.affine()  # the normalizer is set (setup) and on this device
        self._log_train_at_epoch_end = monitors_train_metrics(self.trainer)
        remember_batch_hook_owners(self.trainer)
        if self.trainer.world_size > 1:
            # seed_everything gives every rank the same seed (identical initial weights); the draws inside the
            # loss (diffusion t and noise, the VAE's sample) must differ between ranks, or every rank would
            # pair its shard with the same noise. Deterministic: the seed plus the rank. (A resumed DDP fit
            # therefore restarts these streams; a single-process fit continues the checkpoint's.)
            torch.manual_seed(torch.initial_seed() + self.global_rank)

    def on_train_end(self):
        self._minibatch_affine = None

    def _train_split_normalized(self):
        """(q_n, x_n) of the data module's whole train split on this device, or None (no data module)."""
        datamodule = getattr(self.trainer, "datamodule", None)
        if datamodule is None or getattr(datamodule, "splits", None) is None:
            return None
        q, x = datamodule.splits["train"]
        return self._normalized((q.to(self.device), x.to(self.device)))

    def on_train_epoch_end(self):
        if EPOCH_HOOK not in self.capabilities:
            return
        split = self._train_split_normalized()
        if split is not None:
            self.on_epoch_trained(*split)

    def _refresh_derived_state(self) -> bool:
        """Run the declared ``refresh_from_train_split`` during a fit; True when it ran."""
        if REFRESHES_DERIVED_STATE not in self.capabilities or not is_fitting(self._trainer):
            return False
        split = self._train_split_normalized()
        if split is not None:
            self.refresh_from_train_split(*split)
        return split is not None

    def on_validation_epoch_start(self):
        self._refresh_derived_state()

    def _common_step(self, batch, stage: str):
        q_n, x_n = self._normalized(batch)
        loss, logs = self.training_loss(q_n, x_n)
        self.log(f"{stage}/loss", loss, prog_bar=stage == "val", sync_dist=True)
        for name, value in logs.items():
            self.log(f"{stage}/{name}", value, sync_dist=True)
        # every rank validates the whole held-out split (a few ms): medians do not average across shards;
        # sync_dist reduces the (then equal) figures so every rank's callbacks see the same
        for name, value in self.physical_errors(batch[0], batch[1]).items():
            self.log(f"{stage}/{name}", value, prog_bar=name == "eq_residual_N_m" and stage == "val", sync_dist=True)
        return loss

    def validation_step(self, batch, batch_idx):
        return self._common_step(batch, "val")

    def test_step(self, batch, batch_idx):
        return self._common_step(batch, "test")

    def predict_step(self, batch, batch_idx):
        l_motor, f = self.infer(batch[0])
        return {"q": batch[0].cpu().numpy(), "l_motor": l_motor, "f": f}

    def on_save_checkpoint(self, checkpoint):
        before = {name: buf.detach().clone() for name, buf in self.named_buffers()}
        if self._refresh_derived_state():  # Lightning took the state_dict before this hook: update the buffers the
            state = checkpoint.get("state_dict", {})  # refresh changed (others may hold a weight average's values)
            state.update({name: buf.detach().clone() for name, buf in self.named_buffers()
                          if name in state and not torch.equal(buf, before[name])})
        # minibatch order and diffusion noise come from torch's global RNG: a resumed fit must continue
        # the same stream to end with the same weights as an uninterrupted one
        checkpoint["torch_rng_state"] = torch.get_rng_state()
        if torch.cuda.is_available() and torch.cuda.is_initialized():
            checkpoint["torch_cuda_rng_state"] = torch.cuda.get_rng_state_all()

    def on_load_checkpoint(self, checkpoint):
        if "torch_rng_state" in checkpoint:
            torch.set_rng_state(checkpoint["torch_rng_state"])
        cuda_states = checkpoint.get("torch_cuda_rng_state")
        if cuda_states is not None and torch.cuda.is_available() and len(cuda_states) == torch.cuda.device_count():
            torch.cuda.set_rng_state_all(cuda_states)
        drop_checkpoint_callback_state_unless_fitting(self._trainer, checkpoint)


# devices where the non-finite flag is read on the host: the CPU's read costs nothing, and there a fused step without
# a flag is the cheaper one; on an accelerator a read would stall its queue of asynchronous kernels
HOST_READ_DEVICES = frozenset({"cpu"})


def _skips_by_flag(optimizer, param: torch.Tensor) -> bool:
    """Skip a non-finite step by the flag: ``optimizer`` skips its own step where ``optimizer.found_inf`` is 1 (a
    fused Adam / AdamW, as under a GradScaler) and ``param`` lies on no device of ``HOST_READ_DEVICES``. Otherwise
    the flag is read on the host and the gradients dropped."""
    return (param.device.type not in HOST_READ_DEVICES and type(optimizer) in (torch.optim.Adam, torch.optim.AdamW)
            and bool(optimizer.defaults.get("fused")))
