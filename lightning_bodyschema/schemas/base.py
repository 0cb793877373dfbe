"""``BodySchema``: the base class every architecture subclasses (paper section II).

A schema maps a target posture q to a command (l_motor [m], f [N]) and can adapt that command to faults without
retraining. Subclasses provide the maths the contract names (``lightning_bodyschema/contract.py``:
``training_loss``, the healthy command, and how it adapts, declared in ``capabilities``).

This class holds what is shared: the robot and its normalization, ``infer``/``adapt``/``adapter`` in SI units,
the penalty L_adapt's units, the inference cache's lifetime and what a checkpoint records. The Lightning loops
(training step, validation in physical units, optimizer, RNG state) come from ``training.SchemaLightningModule``.
"""
from __future__ import annotations

from typing import Optional

import numpy as np
import torch

from .._numpy import to_numpy
from ..adaptation import AdaptationResult, Adapter
from ..adaptation.targets import adapt_to_target
from ..contract import ADAPTATION_CAPABILITIES, check_capabilities
from ..data.normalizer import Normalizer
from ..errors import BodySchemaInputError
from ..faults import AdaptWeights
from ..sim import SpringParams, elongation_from_tension
from ..sim.robot import robot_model_from_dict
from ..training.lightning_module import SchemaLightningModule
from ..diagnosis import diagnose
from ..diagnosis.log import check_log_names
from ..diagnosis.noise import BodyError, check_noise
from .cache import InferenceCache
from .diagnosis import held_out_samples, implied_body, measure_body_error
from .registry import CHECKPOINT_FORMAT, SCHEMA_CLASSES, register, register_root, schema_class_path  # noqa: F401


@register_root
class BodySchema(SchemaLightningModule):
    """Base LightningModule of all body schemas.

    Args:
        robot: what the data module's ``robot`` property gives (model XML, muscles, spring; or, for recorded
            data, joint and muscle names, limits and spring with no model); the CLI links it automatically. It is
            saved with the hyperparameters, so a checkpoint rebuilds the robot on any machine.
        lr: Adam learning rate (the default optimizer; the CLI's ``--optimizer`` replaces it).
        lr_final: learning rate reached at the last epoch by cosine annealing (None: constant).
        batch_size: minibatch size per optimizer step and process, recorded in the checkpoint; the data module
            serves the batches and must have the same ``batch_size`` (the CLI links ``--model.batch_size`` to it).
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
        self.robot_model = robot_model_from_dict(robot)  # a sim.robot.RobotModel
        self.spring = SpringParams(**robot["spring"])
        self.n_joints, self.n_muscles = self.robot_model.n_joints, self.robot_model.n_muscles
        self.x_dim = 2 * self.n_muscles
        self.normalizer = Normalizer(self.x_dim, self.n_joints)
        self._physics_cache: dict = {}
        self.inference_cache = InferenceCache(self)  # frozen networks, sampling plans, ...: see schemas/cache.py

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        check_capabilities(cls, BodySchema)
        register(cls)

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

    def adapt_si(self, q_rad: torch.Tensor, bounds, variant: str, **options):
        """Adapted ``(l_motor_m, f_n)`` (B, M) float64 tensors or arrays at postures ``q_rad (B, N)`` [rad] under the
        faults' SI ``bounds`` (``faults.bounds.FaultBounds``), optionally with a (B,) ``Status`` per row (contract.py);
        capability ``adapts_in_si``."""
        raise NotImplementedError(f"{type(self).__name__} does not implement adaptation")

    @property
    def has_physics(self) -> bool:
        """True when the robot comes with a model (MJCF): the physics check, kinematics and evaluation can run.
        A schema trained on recorded data alone has none; its ``adapt`` reports ``unchecked`` instead of ``ok``."""
        return self.robot_model.has_physics

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
        check_physics: also ask the robot's true physics (MuJoCo + a QP per case) whether any command
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

    # ------------------------------------------------------------------ diagnosis (lightning_bodyschema/diagnosis)
    def learned_body_si(self, q_rad) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The learned body at postures ``q_rad (B, N)`` [rad]: ``l_geo (B, M)`` [m], ``G (B, M, N)`` [m/rad], ``tau
        (B, N)`` [N m] float64 arrays, ``-G^T f = tau`` at rest. Here the body the healthy commands imply
        (``schemas.diagnosis.implied_body``); a schema with an explicit body answers with it."""
        return implied_body(self, to_numpy(q_rad).astype(np.float64))

    def body_error(self) -> BodyError:
        """The learned body's own error (``diagnosis.BodyError``), measured once on held-out healthy samples (the
        fit's or the loaded checkpoint's validation split) and kept until the weights change."""
        return self.inference_cache.get("body_error", lambda: measure_body_error(
            self.learned_body_si, self.spring, *held_out_samples(self)))

    def calibrate_body_error(self, q_rad, l_motor_m, f_n) -> BodyError:
        """Measure ``body_error`` on these held-out healthy samples (SI, (S, N), (S, M), (S, M)) instead."""
        error = measure_body_error(self.learned_body_si, self.spring, to_numpy(q_rad), to_numpy(l_motor_m),
                                   to_numpy(f_n))
        self.inference_cache.put("body_error", error)
        return error

    def diagnose(self, log, noise=None, thresholds=None, body_error=None):
        """Which muscles failed in each log of ``log`` (a ``diagnosis.SensorLog``; ``diagnosis.read_sensor_log``
        reads the file format), and how: a ``diagnosis.Diagnosis`` whose ``faults`` go to ``adapt``. ``noise``: the
        sensors' (``diagnosis.SensorNoise``, documented defaults); ``body_error``: None measures the learned body's
        own (``body_error``)."""
        check_log_names(log, self.robot_model)
        return diagnose(log, self.learned_body_si, self.spring, check_noise(noise),
                        body_error or self.body_error(), thresholds)

    def monitor(self, noise=None, thresholds=None, window: int = 5, confirm: int = 3, load_cells=None,
                reuse_rad: float = 5e-3):
        """A ``diagnosis.Monitor`` for a controller: ``monitor.update(cmd, reading)`` each tick returns the
        ``Diagnosis`` of the last ``window`` ticks, a fault declared after ``confirm`` consecutive ticks agree."""
        from ..diagnosis.monitor import Monitor

        return Monitor(self, check_noise(noise), thresholds, window, confirm, load_cells, reuse_rad)

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

    # ------------------------------------------------------------------ optional hooks (declare them: contract.py)
    def on_epoch_trained(self, q_n, x_n):
        """Hook after each epoch's updates with the whole (normalized) train split, the same on every rank
        (e.g. refresh a latent reference now and then); default: nothing."""

    def refresh_from_train_split(self, q_n, x_n) -> None:
        """Bring state derived from the weights and the train split up to date (e.g. a latent reference).

        Called during fit before every validation and before every checkpoint is written, so what is validated
        and what is saved match the weights (Lightning validates and saves before ``on_train_epoch_end``, and
        EarlyStopping may end a fit right after a validation); default: nothing."""

    # ------------------------------------------------------------------ checkpoints
    def on_save_checkpoint(self, checkpoint):
        super().on_save_checkpoint(checkpoint)
        checkpoint["bodyschema"] = {"class_path": schema_class_path(type(self)),
                                    "model_xml_sha256": self.robot_model.xml_hash, "format": CHECKPOINT_FORMAT}

    def checkpoint_refusal(self, meta: dict) -> Optional[str]:
        """Why this schema, built from a checkpoint's hyperparameters, must not take its weights (a fix since the
        checkpoint's ``meta["format"]`` changed what they mean), or None; default: None."""
        return None

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
        return load_schema(str(checkpoint_path), cls=None if cls is BodySchema else cls, overrides=kwargs,
                           map_location=map_location)

    # ------------------------------------------------------------------ inference in SI units
    @torch.no_grad()
    def infer(self, q) -> tuple[np.ndarray, np.ndarray]:
        """Healthy command at postures ``q (B, N)`` [rad]: ``l_motor (B, M)`` [m], ``f (B, M)`` [N]."""
        q = torch.as_tensor(self.robot_model.check_q(to_numpy(q) if torch.is_tensor(q) else q), device=self.device)
        x = to_numpy(self.decode(self.generate(self.encode_q(q))))
        return x[:, : self.n_muscles], x[:, self.n_muscles:]

    def encode_q(self, q: torch.Tensor) -> torch.Tensor:
        return self.normalizer.encode_q(q.to(self.device, torch.float64)).to(self.dtype)

    def decode(self, x_n: torch.Tensor) -> torch.Tensor:
        """Normalized x -> SI [l_motor, f] in float64."""
        return self.normalizer.decode_x(x_n.to(torch.float64))

    def physical_errors(self, q: torch.Tensor, x_true: torch.Tensor) -> dict[str, float]:
        """Healthy-command quality in physical units at postures q (medians over the batch)."""
        l_motor, f = self.infer(q)
        x_true = to_numpy(x_true)
        errors = {"l_motor_err_mm": 1e3 * float(np.median(np.abs(l_motor - x_true[:, : self.n_muscles]))),
                  "f_err_n": float(np.median(np.abs(f - x_true[:, self.n_muscles:])))}
        if not self.has_physics:  # recorded data, no model: only the distance to the recorded commands
            return errors
        l_geo, G, tau_bias = self._physics(to_numpy(q))
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
