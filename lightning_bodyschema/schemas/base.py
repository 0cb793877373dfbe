"""``BodySchema``: the one interface every architecture implements (paper section II).

A schema maps a target posture q to a command (l_motor [m], f [N]) and can adapt that command to
faults without retraining. Subclasses provide only the maths:

* ``training_loss(q_n, x_n) -> (loss, logs)``   on normalized q and x = [l_motor, f]
* ``generate(q_n) -> x_n``                       the healthy (unadapted) normalized estimate

Everything else is shared: normalization, one Lightning training step per minibatch (automatic
optimization: precision, clipping, accumulation and DDP as Lightning documents them), validation in
physical units, checkpoints that carry the robot, ``infer``/``adapt``.
"""
from __future__ import annotations

import math
from typing import Optional

import lightning as L
import numpy as np
import torch
from lightning.pytorch.plugins.precision import HalfPrecision
from lightning.pytorch.trainer.states import TrainerFn

from ..adaptation import AdaptationResult, Adapter
from ..adaptation.targets import adapt_to_target
from ..contract import ADAPTATION_CAPABILITIES, EPOCH_HOOK, REFRESHES_DERIVED_STATE, check_capabilities
from ..data.normalizer import Normalizer
from ..data.recorded import robot_model_from_dict
from ..errors import BodySchemaInputError
from ..faults import AdaptWeights
from ..sim import MusculoskeletalModel, SpringParams, elongation_from_tension
from .cache import InferenceCache
from .finite import all_finite

# class path -> schema class, filled by subclassing: the classes a checkpoint may name (schemas/loading.py). A class
# is known once the user's code has defined (imported) it; a checkpoint never makes anything get imported.
SCHEMA_CLASSES: dict[str, type] = {}


def schema_class_path(cls) -> str:
    """``module.QualName``: how checkpoints name a schema class."""
    return f"{cls.__module__}.{cls.__qualname__}"


# renamed metrics: new name -> old name, still logged beside it (deprecated; see CHANGELOG.md)
DEPRECATED_METRIC_NAMES = {"eq_residual_N_m": "eq_residual_nm"}


def fit_ends_with_this_epoch(trainer) -> bool:
    """True at a validation (or an epoch's training end) after which the fit stops: the last batch of the last
    epoch of ``max_epochs`` (not a validation earlier in that epoch), ``max_steps`` reached (also inside an epoch),
    or a stop already requested. ``max_epochs=-1`` (endless) never ends by epochs. A stop that EarlyStopping
    requests after this validation is caught by ``on_train_end`` of the callbacks that ask."""
    last_batch = trainer.fit_loop.epoch_loop.batch_progress.is_last_batch
    by_epochs = last_batch and trainer.max_epochs is not None and 0 < trainer.max_epochs <= trainer.current_epoch + 1
    by_steps = trainer.max_steps is not None and trainer.max_steps > 0 and trainer.global_step >= trainer.max_steps
    return bool(by_epochs or by_steps or trainer.should_stop)


def limited_batches(trainer, batches: int) -> int:
    """The training batches of an epoch as Lightning runs them: ``limit_train_batches`` is a count or a fraction."""
    limit = trainer.limit_train_batches
    return min(batches, limit) if isinstance(limit, int) else max(1, int(batches * limit))


def check_val_check_interval(trainer, batches_per_epoch: int) -> None:
    """An int ``val_check_interval`` counts batches within an epoch (unless ``check_val_every_n_epoch`` is None):
    refuse one longer than the epoch in one line (the CLI before anything is written), not with Lightning's
    ValueError once the fit loop starts."""
    interval = trainer.val_check_interval
    if not isinstance(interval, int) or isinstance(interval, bool) or trainer.check_val_every_n_epoch is None:
        return
    batches = limited_batches(trainer, batches_per_epoch)
    if interval > batches:
        raise BodySchemaInputError(
            f"--trainer.val_check_interval={interval} is more than the {batches} training batches of an epoch; give "
            f"at most {batches}, a fraction of an epoch (e.g. 0.5), or --trainer.check_val_every_n_epoch=null to "
            f"count {interval} steps across epochs")


def _monitors_train_metrics(trainer) -> bool:
    """Does a callback or a scheduler monitor a ``train/*`` metric (which then must be fresh at every epoch end)?"""
    monitors = [getattr(cb, "monitor", None) for cb in trainer.callbacks]
    monitors += [config.monitor for config in trainer.lr_scheduler_configs]
    return any(isinstance(m, str) and m.startswith("train/") for m in monitors)


def half_precision_refusal(precision) -> str:
    """Why ``16-true`` / ``bf16-true`` are refused (Lightning casts every input batch to that dtype first)."""
    return (f"--trainer.precision={precision} casts the SI data themselves (lengths in m, tensions in N) to a "
            "16-bit float before the schema sees them (bfloat16 keeps ~3 digits: 0.5 mm steps on a 0.15 m "
            "length); use 16-mixed or bf16-mixed (float32 weights and data, 16-bit matmuls), 32-true or 64-true")


def _drop_checkpoint_callback_state_unless_fitting(trainer, checkpoint: dict) -> None:
    """Forget the saved ``ModelCheckpoint`` state when a checkpoint is only evaluated (validate / test).

    That state (best score, best paths) matters only to a resumed fit. A ``bodyschema test`` logs into a new
    version folder, so Lightning would find another dirpath and warn that best_model_score "won't be reloaded",
    which is right and irrelevant there. The weights, hyperparameters and RNG state are untouched.
    """
    if trainer is None or trainer.state.fn in (None, TrainerFn.FITTING) or "callbacks" not in checkpoint:
        return
    checkpoint["callbacks"] = {key: state for key, state in checkpoint["callbacks"].items()
                               if not str(key).startswith("ModelCheckpoint")}


class BodySchema(L.LightningModule):
    """Base LightningModule of all body schemas.

    Args:
        robot: what the data module's ``robot`` property gives (model XML, muscles, spring; or, for recorded
            data, joint and muscle names, limits and spring with no model); the CLI links it automatically. It is
            saved with the hyperparameters, so a checkpoint rebuilds the robot on any machine.
        lr: Adam learning rate (the default optimizer; the CLI's ``--optimizer`` replaces it).
        lr_final: learning rate reached at the last epoch by cosine annealing (None: constant).
        batch_size: minibatch size per optimizer step and process (the data module serves batches of it).
    """

    def __init__(self, robot: Optional[dict] = None, lr: float = 1e-3, lr_final: Optional[float] = 1e-5,
                 batch_size: int = 64):
        super().__init__()
        if robot is None:
            raise BodySchemaInputError(
                "a schema needs `robot` (EquilibriumDataModule(...).robot); the CLI links it from the data")
        if batch_size <= 0:
            raise BodySchemaInputError(f"batch_size={batch_size!r} must be a positive integer")
        if not (0.0 < lr < float("inf")) or (lr_final is not None and not 0.0 <= lr_final < float("inf")):
            raise BodySchemaInputError(f"lr={lr!r}, lr_final={lr_final!r}: need lr > 0 and lr_final >= 0 (or None)")
        self.skipped_steps = 0  # optimizer steps skipped for non-finite gradients in this fit
        self._log_train_at_epoch_end = False  # set when a fit starts: log train/* at every epoch end too
        self.robot_model = robot_model_from_dict(robot)  # a MusculoskeletalModel, or a ModelFreeRobot
        self.spring = SpringParams(**robot["spring"])
        self.n_joints, self.n_muscles = self.robot_model.n_joints, self.robot_model.n_muscles
        self.x_dim = 2 * self.n_muscles
        self.normalizer = Normalizer(self.x_dim, self.n_joints)
        self._physics_cache: dict = {}
        self.inference_cache = InferenceCache(self)  # frozen networks, sampling plans, ...: see schemas/cache.py

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        check_capabilities(cls, BodySchema)
        SCHEMA_CLASSES[schema_class_path(cls)] = cls

    # ------------------------------------------------------------------ what subclasses implement (see contract.py)
    # what the architecture does beyond training_loss and generate: ``contract`` capability names
    capabilities: frozenset = frozenset()

    def training_loss(self, q_n: torch.Tensor, x_n: torch.Tensor) -> tuple[torch.Tensor, dict]:
        raise NotImplementedError

    def generate(self, q_n: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    def adapt_normalized(self, q_n: torch.Tensor, penalty, variant: str, **options) -> torch.Tensor:
        """Adapted normalized x (B, D) minimizing ``penalty`` per case (L_adapt of eq:latent-opt on normalized x, a
        ``faults.penalty.BoxPenalty``: call it for the loss, ``grad``/``residual`` for its gradient); capability
        ``adapts_normalized``."""
        raise NotImplementedError(f"{type(self).__name__} does not implement adaptation")

    def adapt_si(self, q_rad: torch.Tensor, constraints: list, variant: str, **options):
        """Adapted ``(l_motor_m, f_n)`` (B, M) float64 tensors at postures ``q_rad (B, N)`` [rad] under the faults'
        SI ``constraints`` (``Faults.constraints``); capability ``adapts_in_si``."""
        raise NotImplementedError(f"{type(self).__name__} does not implement adaptation")

    @property
    def has_physics(self) -> bool:
        """True when the robot comes with a model (MJCF): the physics check, kinematics and evaluation can run.
        A schema trained on recorded data alone has none; its ``adapt`` reports ``unchecked`` instead of ``ok``."""
        return isinstance(self.robot_model, MusculoskeletalModel)

    # ------------------------------------------------------------------ adaptation (paper section III)
    VARIANTS = ("default", "literal")

    def fault_projection(self, variant: str, penalty, inpaint: Optional[str] = None):
        """The projection onto the faults' feasible set a variant's sampler uses (``faults.projection``); None: the
        architecture's adaptation uses none (the default)."""
        return None

    @property
    def supports_adaptation(self) -> bool:
        """True when the architecture declares a way to adapt (a plain regressor need not)."""
        return bool(self.capabilities & ADAPTATION_CAPABILITIES)

    def adapt(self, q_ref, faults, variant: str = "default", check_physics: bool = True,
              **options) -> AdaptationResult:
        """Commands at postures ``q_ref (B, N)`` [rad] that respect ``faults`` (a ``faults.Faults``, one row per case:
        cut, jammed, weakened and length-banded muscles; see ``adapt_to_target`` for hand targets instead of q_ref).

        variant ``"literal"``: the paper's loss in SI units with its weights and learning rate.
        variant ``"default"``: every residual measured in spreads of the healthy data (z-score units), unit
        weights, and a step that is stable at every noise level (see the schema's ``ADAPT`` table).
        check_physics: also ask the robot's true physics (MuJoCo + a QP, ~60 us per case) whether any command
            can hold q_ref under these faults; where none can, the status is ``infeasible`` and the row NaN
            (the schema's best effort stays in ``diagnostics``). The paper's benchmark scores every command
            and turns it off. A schema without a model (recorded data) cannot run the check: its commands get
            status ``unchecked`` unless the caller turns the check off (``check_physics=False``).
        ``options`` override the variant's settings (e.g. ``lr=``, ``n_steps=``).
        Cases are adapted together in one batch; each case gets a status, and only ``ok`` rows hold a command.
        """
        return self.adapter(faults, variant, check_physics, **options)(q_ref)

    def adapter(self, faults, variant: str = "default", check_physics: bool = True, **options) -> "Adapter":
        """``adapt`` prepared for one fault set: ``adapter(faults, ...)(q_ref)`` equals ``adapt(q_ref, faults, ...)``.

        A fault persists while a controller keeps asking for commands, so everything that depends only on the
        faults (validation, constraints, the loss and its analytic gradient) is done here once; each call then
        pays for the posture check, the sampler and the safe-command bookkeeping only (BENCHMARKS.md has the
        per-call saving at batch 1). The adapter holds the schema's weights as they are now: build a new one
        after training further or changing dtype.
        """
        return Adapter(self, faults, variant, check_physics, options)

    def adapt_to_target(self, target_xyz, faults, site: str = "hand", variant: str = "default",
                        tol_m: float = 1e-4, ik_options: Optional[dict] = None, **options) -> AdaptationResult:
        """Commands that put ``site`` on the task-space targets ``target_xyz (B, 3)`` [m] under ``faults``.

        q_ref comes from inverse kinematics inside the joint limits (``TorchKinematicTwin``: damped least
        squares from seeded random starts; ``ik_options`` go to ``inverse_kinematics``, e.g. ``n_restarts``,
        ``max_iter``, ``seed``, ``q0``), and the reach is checked on MuJoCo, the source of truth. A target the
        site cannot reach within ``tol_m`` gets status ``"unreachable"`` and NaN rows: no command. The
        reached cases are then adapted together by ``adapt(q_ref, faults, variant, **options)``.

        ``diagnostics`` gains ``q_ref (B, N)`` (NaN where unreachable), ``q_closest (B, N)`` (the IK
        posture, the closest found for unreachable targets) and ``target_error_m (B,)`` (MuJoCo distance
        from the site at q_closest to the target).
        """
        return adapt_to_target(self, target_xyz, faults, site, variant, tol_m, ik_options, **options)

    def kinematic_twin(self):
        """The robot's ``TorchKinematicTwin`` (built once, on first use: pytorch-kinematics IK and frames)."""
        if not self.has_physics:
            raise BodySchemaInputError(f"this schema was trained without a robot model ({self.robot_model}): "
                                       "kinematics and hand targets need an MJCF")
        if getattr(self, "_twin", None) is None:
            from ..sim.twin import TorchKinematicTwin

            self._twin = TorchKinematicTwin(self.robot_model)  # a plain attribute: not in the state dict
        return self._twin

    def adaptation_units(self, variant: str, x_std):
        """(weights, l_scale, f_scale) of L_adapt: the paper's weights in SI units (``literal``), or unit weights
        with every residual in spreads of the healthy data, ``x_std`` (``default``). The one place both live."""
        if variant == "literal":
            return AdaptWeights(), 1.0, 1.0
        m = self.n_muscles
        return AdaptWeights(1.0, 1.0, 1.0, 1.0, c_band=1.0), x_std[:m], x_std[m:]

    def penalty_builder(self, variant: str):
        """The ``faults.PenaltyBuilder`` of ``variant`` for this schema's normalizer, dtype and device (cached)."""
        from ..faults.penalty import PenaltyBuilder

        def build():
            mean, std = self.normalizer.x_mean, self.normalizer.x_std
            return PenaltyBuilder(*self.adaptation_units(variant, std), mean, std, self.dtype, self.device)
        return self.inference_cache.get(("penalty_builder", variant), build)

    # ------------------------------------------------------------------ the cache's lifetime (schemas/cache.py)
    def clear_caches(self) -> None:
        """Drop everything derived from the weights (frozen networks, sampling plans, ...): call it after editing
        weights by hand in eval mode. Mode switches, ``load_state_dict`` and dtype/device moves do it themselves."""
        self.inference_cache.clear()

    def train(self, mode: bool = True):
        self.inference_cache.clear()
        return super().train(mode)

    def _apply(self, fn, *args, **kwargs):
        if "inference_cache" in self.__dict__:  # nn.Module may move tensors before __init__ has run to the end
            self.inference_cache.clear()
        return super()._apply(fn, *args, **kwargs)

    def load_state_dict(self, *args, **kwargs):
        self.inference_cache.clear()
        return super().load_state_dict(*args, **kwargs)

    # ------------------------------------------------------------------ Lightning plumbing
    # Lightning sets ``_current_fx_name`` twice around every hook it calls (~20 per optimizer step), and
    # nn.Module.__setattr__ spends ~10 us each checking whether a string is a parameter, buffer or module
    # (profiled: ~9 % of a training step here, ~15 % of Lightning's overhead). A plain string can be none of these.
    _PLAIN_ATTRIBUTES = frozenset({"_current_fx_name"})

    def __setattr__(self, name, value):
        if name in BodySchema._PLAIN_ATTRIBUTES and (value is None or isinstance(value, str)):
            object.__setattr__(self, name, value)
        else:
            super().__setattr__(name, value)

    def setup(self, stage: str):
        if self._trainer is not None and isinstance(self.trainer.precision_plugin, HalfPrecision):
            raise BodySchemaInputError(half_precision_refusal(self.trainer.precision))
        datamodule = getattr(self.trainer, "datamodule", None) if self._trainer is not None else None
        if datamodule is not None and stage == "fit":
            if datamodule.robot_model.xml_hash != self.robot_model.xml_hash:
                raise BodySchemaInputError("the schema's robot differs from the data module's robot")
            self.normalizer.load_state_dict(datamodule.normalizer.state_dict())
            self.clear_caches()  # the penalty builder depends on the normalizer
            if hasattr(datamodule, "train_batches_per_epoch"):
                check_val_check_interval(self.trainer, datamodule.train_batches_per_epoch(
                    self.hparams.get("batch_size", 64), self.trainer.world_size))

    def configure_optimizers(self):
        """Adam (fused: ~25 % faster per step than the default on this tiny CPU workload, measured) with the
        cosine schedule from ``lr`` to ``lr_final`` over the fit's epochs, stepped once per epoch. The CLI's
        ``--optimizer`` / ``--lr_scheduler`` replace both (LightningCLI's own mechanism)."""
        # under a GradScaler (16-mixed) not fused: a fused Adam unscales inside its own step, so Lightning could
        # neither clip (it refuses) nor show the hooks unscaled gradients
        scaler = getattr(self.trainer.precision_plugin, "scaler", None) if self._trainer is not None else None
        optimizer = torch.optim.Adam(self.parameters(), lr=self.hparams.lr, fused=scaler is None)
        if self.hparams.lr_final is None:
            return optimizer
        schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, T_max=self._epochs_of_fit(),
                                                              eta_min=self.hparams.lr_final)
        return {"optimizer": optimizer, "lr_scheduler": schedule}

    def _epochs_of_fit(self) -> int:
        """Epochs this fit will run: ``max_epochs``, or fewer when ``max_steps`` ends it first."""
        trainer = self.trainer
        epochs = int(trainer.max_epochs) if trainer.max_epochs not in (None, -1) else None
        if trainer.max_steps not in (None, -1):
            batches = trainer.num_training_batches
            if batches in (None, float("inf")) or batches == 0:  # not known yet when optimizers are configured
                batches = limited_batches(
                    trainer, len(trainer.datamodule.train_dataloader()) if trainer.datamodule is not None else 1)
            steps_per_epoch = max(1, math.ceil(batches / trainer.accumulate_grad_batches))
            by_steps = math.ceil(trainer.max_steps / steps_per_epoch)
            epochs = by_steps if epochs is None else min(epochs, by_steps)
        return max(1, epochs or 1)

    def _normalized(self, batch):
        q, x = batch
        dtype = self.dtype
        return self.normalizer.encode_q(q).to(dtype), self.normalizer.encode_x(x).to(dtype)

    def training_step(self, batch, batch_idx):
        """One minibatch: Lightning runs the backward, the precision plugin (scaling, unscaling, inf checks),
        gradient clipping and accumulation, DDP's gradient averaging and the optimizer step."""
        q_n, x_n = self._normalized(batch)
        loss, _ = self.training_loss(q_n, x_n)
        # a self.log call costs ~0.3 ms, a quarter of a minibatch step here (measured): call it only on the
        # steps the logger writes (Lightning's own test, so log_every_n_steps means what it documents), and at
        # each epoch's last batch when a monitor (EarlyStopping, ModelCheckpoint, ReduceLROnPlateau) reads train/*
        trainer = self.trainer
        if trainer._logger_connector.should_update_logs or (
                self._log_train_at_epoch_end and trainer.fit_loop.epoch_loop.batch_progress.is_last_batch):
            self.log("train/loss", loss.detach(), prog_bar=True)
            self.log("train/lr", trainer.optimizers[0].param_groups[0]["lr"])
        return loss

    def on_before_optimizer_step(self, optimizer):
        """Skip a step whose gradients are not finite (an overflowing loss), in every precision.

        ``16-mixed``'s GradScaler already skips such steps (and lowers its scale); for the other precisions
        the gradients are dropped, so the optimizer leaves the weights and its state untouched. Under DDP
        the gradients are already averaged here, so every rank takes the same decision.
        """
        scaler = getattr(self.trainer.precision_plugin, "scaler", None)
        if scaler is not None:
            return
        # the optimizer's own parameter list: what it is about to step, and cheaper than walking the modules
        params = [p for group in optimizer.param_groups for p in group["params"] if p.grad is not None]
        if not params:
            return
        if not all_finite([p.grad for p in params]):  # one kernel
            for p in params:
                p.grad = None
            self.skipped_steps += 1

    def on_train_start(self):
        self.skipped_steps = 0
        self._log_train_at_epoch_end = _monitors_train_metrics(self.trainer)
        if self.trainer.world_size > 1:
            # seed_everything gives every rank the same seed (identical initial weights); the draws inside the
            # loss (diffusion t and noise, the VAE's sample) must differ between ranks, or every rank would
            # pair its shard with the same noise. Deterministic: the seed plus the rank. (A resumed DDP fit
            # therefore restarts these streams; a single-process fit continues the checkpoint's.)
            torch.manual_seed(torch.initial_seed() + self.global_rank)

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

    def on_epoch_trained(self, q_n, x_n):
        """Hook after each epoch's updates with the whole (normalized) train split, the same on every rank
        (e.g. refresh a latent reference now and then); default: nothing."""

    def refresh_from_train_split(self, q_n, x_n) -> None:
        """Bring state derived from the weights and the train split up to date (e.g. a latent reference).

        Called during fit before every validation and before every checkpoint is written, so what is validated
        and what is saved match the weights (Lightning validates and saves before ``on_train_epoch_end``, and
        EarlyStopping may end a fit right after a validation); default: nothing."""

    def _refresh_derived_state(self) -> bool:
        if REFRESHES_DERIVED_STATE not in self.capabilities or self._trainer is None or self.trainer.state.fn != TrainerFn.FITTING:
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
        # every rank validates the whole held-out split (160 postures, a few ms): medians do not average
        # across shards; sync_dist reduces the (then equal) figures so every rank's callbacks see the same
        for name, value in self.physical_errors(batch[0], batch[1]).items():
            self.log(f"{stage}/{name}", value, prog_bar=name == "eq_residual_N_m" and stage == "val", sync_dist=True)
            if name in DEPRECATED_METRIC_NAMES:  # old monitors and dashboards keep working for one release
                self.log(f"{stage}/{DEPRECATED_METRIC_NAMES[name]}", value, sync_dist=True)
        return loss

    def validation_step(self, batch, batch_idx):
        return self._common_step(batch, "val")

    def test_step(self, batch, batch_idx):
        return self._common_step(batch, "test")

    def predict_step(self, batch, batch_idx):
        l_motor, f = self.infer(batch[0])
        return {"q": batch[0].cpu().numpy(), "l_motor": l_motor, "f": f}

    def on_save_checkpoint(self, checkpoint):
        if self._refresh_derived_state():  # Lightning took the state_dict before this hook: update its buffers
            state = checkpoint.get("state_dict", {})
            state.update({name: buf.detach().clone() for name, buf in self.named_buffers() if name in state})
        checkpoint["bodyschema"] = {"class_path": schema_class_path(type(self)),
                                    "model_xml_sha256": self.robot_model.xml_hash}
        # minibatch order and diffusion noise come from torch's global RNG: a resumed fit must continue
        # the same stream to end with the same weights as an uninterrupted one
        checkpoint["torch_rng_state"] = torch.get_rng_state()
        if torch.cuda.is_available() and torch.cuda.is_initialized():
            checkpoint["torch_cuda_rng_state"] = torch.cuda.get_rng_state_all()

    @classmethod
    def load_from_checkpoint(cls, checkpoint_path, map_location=None, hparams_file=None, strict=None,
                             weights_only=None, **kwargs):
        """Lightning's convention, through the checked loader: ``MySchema.load_from_checkpoint(path)`` equals
        ``load_schema(path, cls=MySchema)`` (``BodySchema.load_from_checkpoint``: any known schema class), in eval
        mode on the CPU, moved to ``map_location`` if given. ``kwargs`` override hyperparameters and are checked the
        same way. Lightning's own loader would import the ``_instantiator`` a checkpoint names; this one never does.
        """
        from .loading import load_schema

        if hparams_file is not None or strict is False or weights_only is False:
            raise BodySchemaInputError("load_from_checkpoint: hparams_file, strict=False and weights_only=False are "
                                       "not supported (a checkpoint carries its hyperparameters and is checked whole)")
        if map_location is not None and not isinstance(map_location, (str, torch.device)):
            raise BodySchemaInputError(f"load_from_checkpoint: map_location={map_location!r}; give a device "
                                       "('cpu', 'cuda:0', torch.device) or None")
        schema = load_schema(str(checkpoint_path), cls=None if cls is BodySchema else cls, overrides=kwargs)
        return schema if map_location is None else schema.to(map_location)

    def on_load_checkpoint(self, checkpoint):
        if "torch_rng_state" in checkpoint:
            torch.set_rng_state(checkpoint["torch_rng_state"])
        cuda_states = checkpoint.get("torch_cuda_rng_state")
        if cuda_states is not None and torch.cuda.is_available() and len(cuda_states) == torch.cuda.device_count():
            torch.cuda.set_rng_state_all(cuda_states)
        _drop_checkpoint_callback_state_unless_fitting(self._trainer, checkpoint)

    # ------------------------------------------------------------------ inference in SI units
    @torch.no_grad()
    def infer(self, q) -> tuple[np.ndarray, np.ndarray]:
        """Healthy command at postures ``q (B, N)`` [rad]: ``l_motor (B, M)`` [m], ``f (B, M)`` [N]."""
        q = torch.as_tensor(self.robot_model.check_q(q.cpu().numpy() if torch.is_tensor(q) else q))
        x = self.decode(self.generate(self.encode_q(q)))
        return x[:, : self.n_muscles].cpu().numpy(), x[:, self.n_muscles:].cpu().numpy()

    def encode_q(self, q: torch.Tensor) -> torch.Tensor:
        return self.normalizer.encode_q(q.to(self.device, torch.float64)).to(self.dtype)

    def decode(self, x_n: torch.Tensor) -> torch.Tensor:
        """Normalized x -> SI [l_motor, f] in float64."""
        return self.normalizer.decode_x(x_n.to(torch.float64))

    def physical_errors(self, q: torch.Tensor, x_true: torch.Tensor) -> dict[str, float]:
        """Healthy-command quality in physical units at postures q (medians over the batch)."""
        l_motor, f = self.infer(q)
        x_true = x_true.cpu().numpy()
        errors = {"l_motor_err_mm": 1e3 * float(np.median(np.abs(l_motor - x_true[:, : self.n_muscles]))),
                  "f_err_n": float(np.median(np.abs(f - x_true[:, self.n_muscles:])))}
        if not self.has_physics:  # recorded data, no model: only the distance to the recorded commands
            return errors
        l_geo, G, tau_bias = self._physics(q.cpu().numpy())
        eq = np.linalg.norm(np.einsum("bmn,bm->bn", -G, f) - tau_bias, axis=1)
        length = np.abs(l_motor + elongation_from_tension(f, self.spring) - l_geo)
        return {"eq_residual_N_m": float(np.median(eq)),  # newton metres (the old "_nm" read as nanometres)
                "length_residual_mm": 1e3 * float(np.median(length)), **errors}

    def _physics(self, q: np.ndarray):
        """MuJoCo kinematics at q, cached: validation postures are the same every time."""
        key = (q.shape, hash(q.tobytes()))
        if key not in self._physics_cache:
            self._physics_cache = {key: self.robot_model.kinematics(q)}
        return self._physics_cache[key]
