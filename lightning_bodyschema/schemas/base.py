"""``BodySchema``: the one interface every architecture implements (paper section II).

A schema maps a target posture q to a command (l_motor [m], f [N]) and can adapt that command to
faults without retraining. Subclasses provide only the maths:

* ``training_loss(q_n, x_n) -> (loss, logs)``   on normalized q and x = [l_motor, f]
* ``generate(q_n) -> x_n``                       the healthy (unadapted) normalized estimate

Everything else is shared: normalization, minibatching inside one Lightning step per epoch (fast on
this tiny data), validation in physical units, checkpoints that carry the robot, ``infer``/``adapt``.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Optional

import lightning as L
import numpy as np
import torch

from ..data.normalizer import Normalizer
from ..errors import BodySchemaInputError
from ..faults import AdaptWeights, adaptation_loss
from ..evaluation.feasibility import feasible_tensions
from ..optim import LeanFusedAdam
from ..sim import MusculoskeletalModel, SpringParams, elongation_from_tension


@dataclass
class AdaptationResult:
    """What ``adapt`` returns. Only cases whose ``status`` is ``"ok"`` carry a command to send.

    l_motor_m, f_n: (B, M) commands in SI units; a case that is not ``ok`` has NaN there, never
    numbers that look like a command. status: (B,) strings (``ok``, ``non_finite``, ``infeasible``,
    ``not_converged``, ...). diagnostics: per-case arrays (final loss, steps, ...).
    """

    l_motor_m: np.ndarray
    f_n: np.ndarray
    status: np.ndarray
    diagnostics: dict[str, Any] = field(default_factory=dict)

    @property
    def ok(self) -> np.ndarray:
        return self.status == "ok"


class Adapter:
    """``BodySchema.adapt`` for a fixed fault set, prepared once (see ``BodySchema.adapter``).

    Call it with ``q_ref (B, N)`` [rad], one row per fault row; returns an ``AdaptationResult``.
    """

    def __init__(self, schema: "BodySchema", faults, variant: str, check_physics: bool, options: dict):
        if variant not in schema.VARIANTS:
            raise BodySchemaInputError(f"unknown adaptation variant {variant!r}; allowed: {list(schema.VARIANTS)}")
        faults.validate(schema.n_muscles)
        self.schema, self.faults, self.variant = schema, faults, variant
        self.check_physics, self.options = check_physics, dict(options)
        self.f_max = faults.f_limit(schema.spring.f_max_n)
        # Lightning's val/test/predict loops run under inference_mode, whose tensors cannot enter autograd
        with torch.inference_mode(False), torch.no_grad():
            self.constraints = faults.constraints(schema.spring.f_max_n, dtype=schema.dtype, device=schema.device)
            self.loss_fn = schema.adaptation_loss_fn(self.constraints, variant)

    def __call__(self, q_ref) -> AdaptationResult:
        schema, faults = self.schema, self.faults
        q = schema.robot_model.check_q(q_ref.cpu().numpy() if torch.is_tensor(q_ref) else q_ref, within_range=True)
        if len(faults) != len(q):
            raise BodySchemaInputError(f"{len(q)} postures but {len(faults)} fault rows; give one row per case")
        with torch.inference_mode(False), torch.no_grad():
            x_n = schema.adapt_normalized(schema.encode_q(torch.as_tensor(q)), self.loss_fn, self.variant,
                                          **self.options)
        result = schema._command(schema.decode(x_n), faults, self.f_max)
        return schema._flag_infeasible(result, q, faults) if self.check_physics else result


class BodySchema(L.LightningModule):
    """Base LightningModule of all body schemas.

    Args:
        robot: what the data module's ``robot`` property gives (model XML, muscles, spring); the CLI
            links it automatically. It is saved with the hyperparameters, so a checkpoint rebuilds
            the robot on any machine.
        lr: Adam learning rate.
        lr_final: learning rate reached at the last epoch by cosine annealing (None: constant).
        batch_size: minibatch size drawn inside each epoch's single Lightning step.
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
        self.automatic_optimization = False  # several minibatch updates per Lightning step (one per epoch)
        self.robot_model = MusculoskeletalModel(robot["model_xml"], muscles=robot["muscles"])
        self.spring = SpringParams(**robot["spring"])
        self.n_joints, self.n_muscles = self.robot_model.n_joints, self.robot_model.n_muscles
        self.x_dim = 2 * self.n_muscles
        self.normalizer = Normalizer(self.x_dim, self.n_joints)
        self._physics_cache: dict = {}

    # ------------------------------------------------------------------ what subclasses implement
    def training_loss(self, q_n: torch.Tensor, x_n: torch.Tensor) -> tuple[torch.Tensor, dict]:
        raise NotImplementedError

    def generate(self, q_n: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    def adapt_normalized(self, q_n: torch.Tensor, loss_fn, variant: str, **options) -> torch.Tensor:
        """Adapted normalized x (B, D) minimizing ``loss_fn`` per case; what each architecture implements."""
        raise NotImplementedError(f"{type(self).__name__} does not implement adaptation")

    # ------------------------------------------------------------------ adaptation (paper section III)
    VARIANTS = ("default", "literal")

    @property
    def supports_adaptation(self) -> bool:
        """True when the architecture implements ``adapt_normalized`` (a plain regressor need not)."""
        return type(self).adapt_normalized is not BodySchema.adapt_normalized

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
            and turns it off.
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

    def _flag_infeasible(self, result: AdaptationResult, q: np.ndarray, faults) -> AdaptationResult:
        """Status ``infeasible`` (NaN row) where no command can hold q under the faults (jammed wires pull)."""
        feasible, _ = feasible_tensions(self.robot_model, q, faults, self.spring)
        bad = ~feasible & (result.status == "ok")
        result.diagnostics.update(feasible=feasible, best_effort_l_motor_m=result.l_motor_m.copy(),
                                  best_effort_f_n=result.f_n.copy())
        result.status[bad] = "infeasible"
        result.l_motor_m[bad], result.f_n[bad] = np.nan, np.nan
        return result

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
        twin = self.kinematic_twin()
        target = twin._check_target(target_xyz).numpy()
        faults.validate(self.n_muscles)
        if len(faults) != len(target):
            raise BodySchemaInputError(f"{len(target)} targets but {len(faults)} fault rows; give one row per case")
        if variant not in self.VARIANTS:  # refuse before spending time on the inverse kinematics
            raise BodySchemaInputError(f"unknown adaptation variant {variant!r}; allowed: {list(self.VARIANTS)}")
        with torch.inference_mode(False):
            q = twin.inverse_kinematics(target, site=site, tol_m=tol_m, **(ik_options or {})).q.numpy()
        error = np.linalg.norm(self.robot_model.site_position(q, site) - target, axis=1)
        reached = error <= tol_m
        n, m = len(target), self.n_muscles
        out = AdaptationResult(np.full((n, m), np.nan), np.full((n, m), np.nan),
                               np.full(n, "unreachable", dtype="<U16"), {})
        if reached.any():
            inner = self.adapt(q[reached], faults.take(reached), variant, **options)
            out.l_motor_m[reached], out.f_n[reached], out.status[reached] = inner.l_motor_m, inner.f_n, inner.status
            for name, value in inner.diagnostics.items():
                value = np.asarray(value)
                full = np.full((n,) + value.shape[1:], np.nan if value.dtype.kind == "f" else 0, value.dtype)
                full[reached] = value
                out.diagnostics[name] = full
        out.diagnostics.update(q_ref=np.where(reached[:, None], q, np.nan), q_closest=q, target_error_m=error)
        return out

    def kinematic_twin(self):
        """The robot's ``TorchKinematicTwin`` (built once, on first use: pytorch-kinematics IK and frames)."""
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

    def adaptation_loss_fn(self, constraints, variant: str):
        """L_adapt on normalized x (eq:latent-opt), in the units of ``adaptation_units``."""
        m = self.n_muscles
        std = self.normalizer.x_std.to(self.dtype)
        weights, l_scale, f_scale = self.adaptation_units(variant, std)

        def loss_fn(x_n):
            x = self.normalizer.decode_x(x_n)
            return adaptation_loss(constraints, weights, x[:, :m], x[:, m:], l_scale, f_scale)

        return loss_fn

    def _command(self, x: torch.Tensor, faults, f_max: np.ndarray) -> AdaptationResult:
        """Safe command: non-finite rows become NaN with status ``non_finite``; f clipped into its bounds.

        ``f_max`` (B, M): the tension limits, ``faults.f_limit(spring.f_max_n)`` (a weakened muscle's own)."""
        x = x.cpu().numpy()
        l_motor, f = x[:, : self.n_muscles], x[:, self.n_muscles:]
        finite = np.isfinite(x).all(1)
        # non-finite rows are replaced by NaN below, so NaN/inf may pass through clip and the diagnostics
        f_safe = np.clip(f, 0.0, f_max)
        status = np.where(finite, "ok", "non_finite").astype("<U16")
        band, (lo, hi) = faults.band, (np.zeros((2,) + f.shape) if faults.l_band_m is None
                                       else np.moveaxis(faults.l_band_m, -1, 0))  # NaN off the band: masked
        with np.errstate(invalid="ignore"):
            diagnostics = {"f_clipped_n": np.where(finite, np.abs(f_safe - f).max(1), np.nan),
                           "cut_violation_n": np.where(finite, np.where(faults.cut, np.abs(f_safe), 0.0).max(1), np.nan),
                           "jam_violation_m": np.where(finite, np.where(faults.fix, np.maximum(
                               0.0, l_motor - faults.l_fixed_m), 0.0).max(1), np.nan),
                           # before clipping: how far the adapted tension overshot a weakened muscle's limit
                           "weak_violation_n": np.where(finite, np.where(faults.weak, np.maximum(
                               0.0, f - f_max), 0.0).max(1), np.nan),
                           "band_violation_m": np.where(finite, np.where(band, np.maximum(
                               np.maximum(lo - l_motor, l_motor - hi), 0.0), 0.0).max(1), np.nan)}
        l_motor = np.where(finite[:, None], l_motor, np.nan)
        f_safe = np.where(finite[:, None], f_safe, np.nan)
        return AdaptationResult(l_motor, f_safe, status, diagnostics)

    # ------------------------------------------------------------------ Lightning plumbing
    def setup(self, stage: str):
        datamodule = getattr(self.trainer, "datamodule", None) if self._trainer is not None else None
        if datamodule is not None and stage == "fit":
            if datamodule.robot_model.xml_hash != self.robot_model.xml_hash:
                raise BodySchemaInputError("the schema's robot differs from the data module's robot")
            self.normalizer.load_state_dict(datamodule.normalizer.state_dict())

    def configure_optimizers(self):
        # fused Adam: ~25 % faster per step than the default on this tiny CPU workload (measured); the lean
        # variant calls the same kernels with ~115 us less Python per step (optim/lean_adam.py)
        optimizer = LeanFusedAdam(self.parameters(), lr=self.hparams.lr)
        if self.hparams.lr_final is None:
            return optimizer
        epochs = max(1, int(self.trainer.max_epochs or 1))
        schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, T_max=epochs, eta_min=self.hparams.lr_final)
        return {"optimizer": optimizer, "lr_scheduler": schedule}

    def _normalized(self, batch):
        q, x = batch
        dtype = self.dtype
        return self.normalizer.encode_q(q).to(dtype), self.normalizer.encode_x(x).to(dtype)

    def training_step(self, batch, batch_idx):
        q_n, x_n = self._normalized(batch)
        optimizer = self.optimizers()
        minibatches = torch.randperm(len(q_n), device=q_n.device).split(self.hparams.batch_size)
        total = 0.0
        plain = self._plain_backward_ok()
        for i, idx in enumerate(minibatches):
            last = i == len(minibatches) - 1
            loss, _ = self.training_loss(q_n[idx], x_n[idx])
            optimizer.zero_grad(set_to_none=True)
            # Lightning's backward runs every callback's on_before/after_backward hooks (~0.2 ms per call,
            # ~10 % of an epoch here) and its optimizer wrapper costs ~0.1 ms, so on one device in 32-bit the
            # inner steps use torch directly and the last one Lightning's: hooks fire and global_step counts
            # once per epoch. Other strategies (DDP's reducer) and precisions (scaling) always go through Lightning.
            if plain and not last:
                loss.backward()
            else:
                self.manual_backward(loss)
            (optimizer if last else optimizer.optimizer).step()
            total += loss.detach()
        n_batches = len(minibatches)
        scheduler = self.lr_schedulers()
        if scheduler is not None:
            scheduler.step()
        # Lightning's logger writes every log_every_n_steps epochs; a self.log call costs ~0.3 ms (a quarter of
        # Lightning's per-epoch overhead here, measured), so only call it when it will be written
        every = max(1, int(getattr(self.trainer, "log_every_n_steps", 1) or 1))
        if (self.current_epoch + 1) % every == 0 or self.current_epoch + 1 == self.trainer.max_epochs:
            self.log("train/loss", total / n_batches, prog_bar=True)
            self.log("train/lr", optimizer.param_groups[0]["lr"])
        self.on_epoch_trained(q_n, x_n)

    def _plain_backward_ok(self) -> bool:
        """True when ``loss.backward()`` is all Lightning's backward would do: one device, 32-bit precision."""
        from lightning.pytorch.strategies import SingleDeviceStrategy

        trainer = self.trainer
        return type(trainer.strategy) is SingleDeviceStrategy and trainer.precision == "32-true"

    def on_epoch_trained(self, q_n, x_n):
        """Hook after each epoch's updates (e.g. refresh a latent reference); default: nothing."""

    def _common_step(self, batch, stage: str):
        q_n, x_n = self._normalized(batch)
        loss, logs = self.training_loss(q_n, x_n)
        self.log(f"{stage}/loss", loss, prog_bar=stage == "val")
        for name, value in logs.items():
            self.log(f"{stage}/{name}", value)
        for name, value in self.physical_errors(batch[0], batch[1]).items():
            self.log(f"{stage}/{name}", value, prog_bar=name == "eq_residual_nm" and stage == "val")
        return loss

    def validation_step(self, batch, batch_idx):
        return self._common_step(batch, "val")

    def test_step(self, batch, batch_idx):
        return self._common_step(batch, "test")

    def predict_step(self, batch, batch_idx):
        l_motor, f = self.infer(batch[0])
        return {"q": batch[0].cpu().numpy(), "l_motor": l_motor, "f": f}

    def on_save_checkpoint(self, checkpoint):
        checkpoint["bodyschema"] = {"class_path": f"{type(self).__module__}.{type(self).__qualname__}",
                                    "model_xml_sha256": self.robot_model.xml_hash}
        # minibatch order and diffusion noise come from torch's global RNG: a resumed fit must continue
        # the same stream to end with the same weights as an uninterrupted one
        checkpoint["torch_rng_state"] = torch.get_rng_state()

    def on_load_checkpoint(self, checkpoint):
        if "torch_rng_state" in checkpoint:
            torch.set_rng_state(checkpoint["torch_rng_state"])

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
        l_geo, G, tau_bias = self._physics(q.cpu().numpy())
        eq = np.linalg.norm(np.einsum("bmn,bm->bn", -G, f) - tau_bias, axis=1)
        length = np.abs(l_motor + elongation_from_tension(f, self.spring) - l_geo)
        x_true = x_true.cpu().numpy()
        return {"eq_residual_nm": float(np.median(eq)),
                "length_residual_mm": 1e3 * float(np.median(length)),
                "l_motor_err_mm": 1e3 * float(np.median(np.abs(l_motor - x_true[:, : self.n_muscles]))),
                "f_err_n": float(np.median(np.abs(f - x_true[:, self.n_muscles:])))}

    def _physics(self, q: np.ndarray):
        """MuJoCo kinematics at q, cached: validation postures are the same every time."""
        key = (q.shape, hash(q.tobytes()))
        if key not in self._physics_cache:
            self._physics_cache = {key: self.robot_model.kinematics(q)}
        return self._physics_cache[key]
