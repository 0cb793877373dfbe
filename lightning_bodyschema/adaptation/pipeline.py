"""``Adapter``: ``BodySchema.adapt`` for one fault set, prepared once and called every control tick."""
from __future__ import annotations

from contextlib import nullcontext

import numpy as np
import torch

from .._numpy import to_numpy
from ..contract import ADAPTATION_CAPABILITIES, ADAPTS_IN_SI
from ..errors import BodySchemaInputError
from ..faults.bounds import FaultBounds
from ..status import Status
from .command import AdaptationResult, motor_length_range, safe_command
from ..variants import check_variant
from .physics import flag_infeasible, mark_unchecked


def real_array(value, name: str) -> np.ndarray:
    """``value`` as a float64 array; strings, None, objects, complex numbers and bools are refused by name."""
    try:
        array = np.asarray(value.detach().cpu().numpy() if torch.is_tensor(value) else value)
    except (ValueError, TypeError):  # ragged nesting
        array = np.asarray(None)
    if array.dtype.kind not in "fiu":
        shown = repr(value) if len(repr(value)) <= 80 else f"a {type(value).__name__}"
        raise BodySchemaInputError(f"{name} = {shown} is not an array of real numbers ({array.dtype}); "
                                   "give postures [rad] as numbers, shape (B, N)")
    return array.astype(np.float64)


def check_postures(schema, q_ref, n_cases: int) -> np.ndarray:
    """q_ref as a (B, N) float64 array inside the joint ranges, one row per fault case."""
    q = schema.robot_model.check_q(real_array(q_ref, "q_ref"), within_range=True)
    if n_cases != len(q):
        raise BodySchemaInputError(f"{len(q)} postures but {n_cases} fault rows; give one row per case")
    return q


class Adapter:
    """Prepare once, then per call ``adapter(q_ref (B, N))`` [rad] -> ``AdaptationResult``.

    The schema (a ``contract.SchemaContract``) declares how it adapts, and the adapter dispatches on it:
    ``adapts_normalized``: prepare the penalty L_adapt of eq:latent-opt (and the variant's fault projection); per call
    check postures -> encode -> ``adapt_normalized`` -> decode. ``adapts_in_si`` (``StructuredSchema``'s QP on its
    learned body, a user's SI schema): the faults' SI bounds (``FaultBounds``, prepared either way); per call check
    postures -> ``adapt_si`` on q [rad]; where it also says why a row holds no command (a third output, ``Status``
    members), that status stays and the row's best effort goes to ``diagnostics`` (``qp_l_motor_m``, ``qp_f_n``);
    a schema with ``path_switches(q)`` (``StructuredSchema``) adds its dict of per-row diagnostics
    (``near_path_switch``: the posture is within reach of a learned path switch, the command not exact there).
    Then, either way, ``safe_command`` -> ``flag_infeasible`` (when ``check_physics``; ``mark_unchecked`` when the
    robot has no model to check on; the physical reason wins over the schema's own).

    Lifetime: the penalty is built from the schema's normalizer, dtype and device as they are now; the networks
    are the schema's current weights at each call (through its inference cache). Build a new adapter after
    training further or moving the schema to another dtype or device.
    """

    def __init__(self, schema, faults, variant: str = "default", check_physics: bool = True, options: dict = None):
        check_variant(schema, variant, "adaptation variant")
        faults.validate(schema.n_muscles, schema.spring.f_max_n)
        if not schema.capabilities & ADAPTATION_CAPABILITIES:
            raise NotImplementedError(f"{type(schema).__name__} does not implement adaptation (its capabilities "
                                      f"declare none of {sorted(ADAPTATION_CAPABILITIES)})")
        self.schema, self.faults, self.variant = schema, faults, variant
        self.check_physics, self.options = check_physics, dict(options or {})
        self.in_si = ADAPTS_IN_SI in schema.capabilities
        self.f_limit_n = faults.f_limit(schema.spring.f_max_n)
        # the faults' SI bounds, once (numpy: the safe command's and the QP's)
        self.bounds = FaultBounds.from_faults(faults, schema.spring.f_max_n, schema.spring)
        self.l_range_m = motor_length_range(schema.normalizer.x_mean, schema.normalizer.x_std, schema.n_muscles)
        if not self.in_si:
            self._prepare_penalty(schema, faults, variant)

    def _prepare_penalty(self, schema, faults, variant: str) -> None:
        # Lightning's val/test/predict loops run under inference_mode: the penalty must be an ordinary tensor
        with torch.inference_mode(False), torch.no_grad():
            self.penalty = schema.penalty_builder(variant)(faults.constraints(schema.spring.f_max_n))
            projection = schema.fault_projection(variant, self.penalty, self.options.get("inpaint"))
        if projection is not None:  # built once with the penalty; the sampler takes it as a value
            self.options["projection"] = projection

    def __call__(self, q_ref) -> AdaptationResult:
        q = check_postures(self.schema, q_ref, len(self.faults))
        if self.in_si:
            return self._si_result(q)
        return self._checked(safe_command(self._adapted_normalized(q), self.bounds, l_range_m=self.l_range_m), q)

    def _adapted_normalized(self, q: np.ndarray) -> torch.Tensor:
        """The schema's adapted command [l_motor, f] (B, 2M) in SI units, float64."""
        schema = self.schema
        with torch.inference_mode(False), torch.no_grad():  # a sampler may need ordinary tensors
            q_n = schema.encode_q(torch.as_tensor(q, device=schema.device))
            return schema.decode(schema.adapt_normalized(q_n, self.penalty, self.variant, **self.options))

    def _si_result(self, q: np.ndarray) -> AdaptationResult:
        """``adapts_in_si``: ``adapt_si``'s command through ``safe_command`` and the physics check, with the schema's
        own status where it gave one (class docstring)."""
        schema = self.schema
        # ordinary tensors (no_grad; inference mode left only where it is on: a controller's tick is outside it)
        leave = torch.inference_mode(False) if torch.is_inference_mode_enabled() else nullcontext()
        with leave, torch.no_grad():  # on the schema's device until here
            answer = schema.adapt_si(torch.as_tensor(q, device=schema.device), self.bounds, self.variant,
                                     **self.options)
        l_motor, f = to_numpy(answer[0], np.float64), to_numpy(answer[1], np.float64)
        why = np.asarray(answer[2], dtype=object) if len(answer) > 2 else np.full(len(q), Status.OK, dtype=object)
        refused = why != Status.OK
        result = safe_command(np.where(refused[:, None], np.nan, np.concatenate([l_motor, f], 1)), self.bounds,
                              l_range_m=self.l_range_m)
        result.status[refused] = why[refused]
        if len(answer) > 2:
            result.diagnostics.update(qp_l_motor_m=l_motor, qp_f_n=f)
        result = self._checked(result, q)
        if hasattr(schema, "path_switches"):  # near a learned path's switch a command is not exact: flagged
            result.diagnostics.update(schema.path_switches(q))
        if self.check_physics and schema.has_physics:  # the physical reason wins over the schema's own
            result.status[~result.diagnostics["feasible"] & refused] = Status.INFEASIBLE
        return result

    def _checked(self, result: AdaptationResult, q: np.ndarray) -> AdaptationResult:
        """``result`` with the physics check's verdict (``check_physics``), or ``unchecked`` where there is no model."""
        if not self.check_physics:
            return result
        if not self.schema.has_physics:
            return mark_unchecked(result)
        return flag_infeasible(result, self.schema.robot_model, q, self.faults, self.schema.spring)
