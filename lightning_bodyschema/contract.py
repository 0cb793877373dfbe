"""What an architecture provides: the body-schema contract and the capabilities a schema class declares.

A body schema maps a target posture q [rad] to a command x = [l_motor [m], f [N]] and adapts that command to faults
without retraining. ``schemas.BodySchema`` (a LightningModule) supplies everything shared — normalization, the
training step, validation in physical units, checkpoints, ``adapt``/``adapter`` — and an architecture supplies:

* ``training_loss(q_n, x_n) -> (loss, logs)``: the loss on one minibatch of normalized postures ``q_n (B, N)`` and
  commands ``x_n (B, 2M)`` (a scalar tensor, and a dict of detached scalars logged beside it). Required.
* the healthy command: ``generate(q_n) -> x_n (B, 2M)`` on normalized tensors, which the base class's
  ``infer(q) -> (l_motor_m, f_n)`` (numpy, SI) decodes; an architecture that works in SI units overrides ``infer``
  itself. Required (one of the two).
* how it adapts, declared as ONE of two capabilities (``Adapter`` dispatches on the declaration):

  - ``ADAPTS_NORMALIZED``: ``adapt_normalized(q_n, penalty, variant, **options) -> x_n (B, 2M)`` on normalized
    tensors, minimizing ``penalty`` (a ``faults.penalty.BoxPenalty``: call it for L_adapt, ``grad``/``residual``
    for its gradient) per case; for generative schemas (AE, VAE, diffusion). The penalty is built once per fault
    set from ``penalty_builder(variant)``; ``fault_projection`` may add a projection the sampler takes as an option.
  - ``ADAPTS_IN_SI``: ``adapt_si(q_rad, bounds, variant, **options) -> (l_motor_m, f_n)``, both (B, M)
    float64 tensors or arrays (NaN rows: no command), from postures ``q_rad (B, N)`` [rad] (float64 tensor) and the
    faults' SI bounds (``faults.bounds.FaultBounds``: tension and motor-length bounds, the tension box through the
    spring); for schemas that solve for the command directly (e.g. a QP on a learned body). It may add a third
    output, ``status (B,)`` ``status.Status`` members saying why a row holds no command (its values are then a best
    effort, not sent: ``StructuredSchema``'s ``infeasible_learned``).

  Either way the result goes through the same safe-command step and physics check. A schema declaring neither is
  a plain regressor: ``adapt`` refuses it.
* optional hooks, each declared too: ``EPOCH_HOOK`` — ``on_epoch_trained(q_n, x_n)`` after every training epoch with
  the whole normalized train split; ``REFRESHES_DERIVED_STATE`` — ``refresh_from_train_split(q_n, x_n)`` before
  every validation and checkpoint of a fit (state derived from the weights and the split, e.g. a latent reference).

A class declares what it does in ``capabilities`` (a frozenset of the names below; a subclass inherits its parent's
unless it declares its own). ``check_capabilities`` holds the declaration to the class when the class is defined:
an unknown name, a declared capability whose method is missing, or a capability method defined but not declared is
a ``TypeError`` then, never a surprise at a controller's first call. Nothing here imports Lightning or torch.
"""
from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

ADAPTS_NORMALIZED = "adapts_normalized"
ADAPTS_IN_SI = "adapts_in_si"
EPOCH_HOOK = "epoch_hook"
REFRESHES_DERIVED_STATE = "refreshes_derived_state"
# capability -> the method a class declaring it implements
CAPABILITY_METHODS = {ADAPTS_NORMALIZED: "adapt_normalized", ADAPTS_IN_SI: "adapt_si",
                      EPOCH_HOOK: "on_epoch_trained", REFRESHES_DERIVED_STATE: "refresh_from_train_split"}
ADAPTATION_CAPABILITIES = frozenset({ADAPTS_NORMALIZED, ADAPTS_IN_SI})


@runtime_checkable
class SchemaContract(Protocol):
    """What ``adaptation.Adapter``, the callbacks and the tools read from a schema (``BodySchema`` provides it all).

    n_joints, n_muscles: N and M. spring: the robot's ``SpringParams``. robot_model: a ``sim.robot.RobotModel``.
    normalizer: the ``data.Normalizer`` between SI and normalized tensors. VARIANTS: the adaptation variants it
    accepts. capabilities: what it declares (module docstring).
    """

    capabilities: frozenset
    VARIANTS: tuple
    n_joints: int
    n_muscles: int
    spring: Any
    robot_model: Any
    normalizer: Any

    def training_loss(self, q_n, x_n) -> tuple[Any, dict]: ...

    def generate(self, q_n): ...

    def infer(self, q) -> tuple[Any, Any]: ...

    def encode_q(self, q): ...

    def decode(self, x_n): ...

    def penalty_builder(self, variant: str): ...

    def fault_projection(self, variant: str, penalty, inpaint=None): ...

    def adapt_normalized(self, q_n, penalty, variant: str, **options): ...

    def adapt_si(self, q_rad, bounds, variant: str, **options) -> tuple: ...


def check_capabilities(cls: type, base: type) -> None:
    """Refuse (``TypeError``) a class whose ``capabilities`` do not match its methods (module docstring); ``base``
    is the class holding the unimplemented defaults (``BodySchema``)."""
    declared = cls.capabilities
    if not isinstance(declared, frozenset):
        raise TypeError(f"{cls.__qualname__}.capabilities = {declared!r}; give a frozenset of "
                        f"{sorted(CAPABILITY_METHODS)}")
    unknown = sorted(declared - CAPABILITY_METHODS.keys())
    if unknown:
        raise TypeError(f"{cls.__qualname__}.capabilities names {unknown}; known: {sorted(CAPABILITY_METHODS)}")
    if declared >= ADAPTATION_CAPABILITIES:
        raise TypeError(f"{cls.__qualname__} declares both {ADAPTS_NORMALIZED!r} and {ADAPTS_IN_SI!r}; an "
                        "architecture adapts one way")
    for capability, method in CAPABILITY_METHODS.items():
        implemented = getattr(cls, method, None) is not getattr(base, method, None)
        if capability in declared and not implemented:
            raise TypeError(f"{cls.__qualname__} declares {capability!r} but defines no {method}")
        if implemented and capability not in declared:
            raise TypeError(f"{cls.__qualname__} defines {method} but does not declare {capability!r}: add it to the "
                            f"class's `capabilities` (e.g. `capabilities = frozenset({{{capability!r}}})`)")
