"""The exported package's modules: the prepared adapter of a schema as one tensor-only ``nn.Module`` that
``torch.export`` can trace, for the diffusion schema (``AdapterModule``) and the structured schema
(``deploy.structured.StructuredAdapterModule``), with ONE signature.

Every input is a tensor, the faults included, so ONE exported program serves every fault set: the faults become a
``faults.bounds.FaultBounds`` inside the graph, and the answer goes through ``adaptation.command.command_status``,
the safe command every Python adapter uses.

forward(q_ref, cut, jam, l_fixed_m, f_weak_n, band_lo_m, band_hi_m, seed) -> (l_motor_m, f_n, status)

* ``q_ref (B, N)`` float64 [rad], the free joints in the model's order, inside their ranges.
* ``cut``, ``jam (B, M)`` float64 masks, 1.0 where the muscle is cut / jammed, else 0.0.
* ``l_fixed_m (B, M)`` float64 [m]: a jammed motor's length, NaN (ignored) where not jammed.
* ``f_weak_n (B, M)`` float64 [N]: a weakened muscle's tension limit, NaN where not weakened.
* ``band_lo_m``, ``band_hi_m (B, M)`` float64 [m]: a motor's length band, NaN where free.
* ``seed ()`` int64: the diffusion package picks x_T among the draws baked at export (``seeds``; the schema's
  ``sample_seed`` first); the structured package accepts its one seed (0) only.
* returns ``l_motor_m``, ``f_n (B, M)`` float64 [m], [N] (NaN rows unless ok) and ``status (B,)`` int32
  (``status.Status`` codes). A row whose input breaks a rule (``faults.fault_rules``, a mask neither 0 nor 1, a
  posture NaN or outside its range, an unknown seed) is ``bad_input``.

Numbers: those of ``schema.adapter(faults, n_steps=k, check_physics=False)(q_ref)`` (diffusion, variant
``"default"``; to float32 rounding) and ``schema.adapter(faults, check_physics=False)(q_ref)`` (structured).
Only ``DiffusionSchema`` (the MLP eps-model with a ``FrozenMLP`` snapshot) and ``StructuredSchema`` are supported.
"""
from __future__ import annotations

import numpy as np
import torch
from torch import nn

from ..adaptation.command import FAULT_TOL_M, FAULT_TOL_N, command_status, motor_length_range  # noqa: F401
from ..errors import BodySchemaInputError
from ..faults.bounds import FaultBounds
from ..faults.penalty import BoundsPenalty
from ..faults.projection import FaultProjection
from ..networks.arrays import encode_q
from ..status import STATUS_CODES  # noqa: F401  (re-exported: the package's codes are the vocabulary's)

VARIANT = "default"


def sampler_bridge(schema, n_steps: int, c_w: float):
    """(frozen eps-net, guidance, run): ``run(q_n (B, N), x_T (B, D), penalty, projection) -> x0_n (B, D)`` is the
    schema's fast guided loop of variant ``"default"`` over ``n_steps`` strided steps, with traceable ops, on the
    schema's public plan (``DiffusionSchema.denoising_plan``, ``c_w`` folded in as ``_denoise`` does). The plan is
    built here, outside any trace."""
    from ..samplers.guided import guided_loop

    preset = schema.sampler_preset(VARIANT, n_steps)
    steps, guidance = schema.timesteps(n_steps, preset.spacing), preset.guidance
    frozen = schema.eps_model.frozen()
    plan = schema.denoising_plan(steps, preset.eta, guidance, c_w, True)

    def run(q_n, x_t, penalty, projection):
        biases = schema.eps_model.step_biases(frozen, q_n, steps)
        inpaint = projection if guidance.inpaint != "none" else None
        return guided_loop(plan.steps, biases.unbind(0), x_t, penalty, frozen, frozen.traceable, inpaint)
    return frozen, guidance, run


def check_supported(schema) -> None:
    """Refuse, in one line, a schema the exported adapter cannot reproduce."""
    from ..schemas import DiffusionSchema, StructuredSchema

    diffusion = isinstance(schema, DiffusionSchema) and schema.eps_model.frozen() is not None
    if not (diffusion or isinstance(schema, StructuredSchema)):
        raise BodySchemaInputError(f"export supports the diffusion schema (with a SiLU/Tanh eps-MLP) and the "
                                   f"structured schema only; got {type(schema).__name__}")
    joint_map = getattr(schema.robot_model, "joint_map", None)  # the structured body needs no model: free joints
    if diffusion and joint_map is not None and len(joint_map.names) != schema.n_joints:
        raise BodySchemaInputError("the diffusion export supports robots without locked or coupled joints only")


def _one_weight(builder) -> float:
    """The one weight w2 = 2 c (s_x / scale)^2 every term of the variant's L_adapt has (the default variant's:
    unit weights in spreads of the data); refuse weights that differ (the literal variant's)."""
    w, r2, m = builder.weights, builder.ratio2, builder.m
    every = np.concatenate([2.0 * w.c_fix * r2[:m], 2.0 * w.c_band * r2[:m], 2.0 * w.c_cut * r2[m:],
                            2.0 * w.c_fmin * r2[m:], 2.0 * w.c_fmax * r2[m:]])
    if not (every == every[0]).all():
        raise BodySchemaInputError("export supports adaptation losses with one weight for every term only")
    return float(every[0])


class PackageModule(nn.Module):
    """What every package module shares: the limits (buffers), the input check, the faults as ``FaultBounds`` and
    the safe command. ``seeds``: the values the ``seed`` input may take."""

    def __init__(self, schema, seeds):
        super().__init__()
        check_supported(schema)
        self.m, self.seeds = schema.n_muscles, [int(s) for s in seeds]
        m, f64 = self.m, dict(dtype=torch.float64)
        q_range = np.asarray(schema.robot_model.q_range, float)
        l_range = motor_length_range(schema.normalizer.x_mean, schema.normalizer.x_std, m)
        as_m = lambda v: np.broadcast_to(np.asarray(v, float), (m,)).copy()  # noqa: E731
        for name, value in (("q_lo", q_range[:, 0]), ("q_hi", q_range[:, 1]), ("f_max_n", as_m(schema.spring.f_max_n)),
                            ("k_n", as_m(schema.spring.k_n)), ("alpha_per_m", as_m(schema.spring.alpha_per_m)),
                            ("l_lo_m", np.maximum(l_range[0], 0.0)), ("l_hi_m", l_range[1])):
            self.register_buffer(name, torch.as_tensor(value, **f64))
        self.register_buffer("q_norm_lo", schema.normalizer.q_lo.detach().to(torch.float64).clone())
        self.register_buffer("q_norm_hi", schema.normalizer.q_hi.detach().to(torch.float64).clone())
        self.register_buffer("seed_table", torch.as_tensor(self.seeds, dtype=torch.int64))

    def faults(self, q, cut, jam, l_fixed, f_weak, band_lo, band_hi, seed):
        """``(bad (B,), q, bounds)``: the rows whose input is refused, the postures with those rows moved to the
        middle of the joint ranges (harmless inputs; their answer is NaN), and the faults of the others."""
        def is_mask(a):
            return (a == 0.0) | (a == 1.0)
        bounds = FaultBounds.from_tensors(cut, jam, l_fixed, f_weak, band_lo, band_hi, self.f_max_n)
        bad = ~(torch.isfinite(q) & (q >= self.q_lo) & (q <= self.q_hi)).all(1)
        bad = bad | ~(is_mask(cut) & is_mask(jam)).all(1) | bounds.invalid(self.f_max_n)
        bad = bad | ~(self.seed_table == seed).any()
        keep = ~bad[:, None]
        nan = torch.full_like(f_weak, float("nan"))
        bounds = FaultBounds.from_tensors(keep & bounds.cut, keep & bounds.jam, l_fixed, torch.where(keep, f_weak, nan),
                                          torch.where(keep, band_lo, nan), torch.where(keep, band_hi, nan),
                                          self.f_max_n, self.k_n, self.alpha_per_m)
        return bad, torch.where(keep, q, 0.5 * (self.q_lo + self.q_hi)), bounds

    def normalized_q(self, q, dtype):
        """Postures [rad] -> the schema's normalized postures (``Normalizer.encode_q``) in ``dtype``."""
        return encode_q(q, self.q_norm_lo, self.q_norm_hi).to(dtype)

    def safe(self, x_si, bounds, bad):
        """``command_status`` (the Python adapters' safe command): ``(l_motor_m, f_n, status)``."""
        l_motor, f, status, _ = command_status(x_si, bounds, self.l_lo_m, self.l_hi_m, bad)
        return l_motor, f, status

    def example_inputs(self, batch: int = 1):
        """Healthy inputs of ``batch`` cases at the middle of the joint ranges (what export traces with)."""
        n, m = self.q_lo.shape[0], self.m
        nan = torch.full((batch, m), float("nan"), dtype=torch.float64)
        zero = torch.zeros((batch, m), dtype=torch.float64)
        q = (0.5 * (self.q_lo + self.q_hi)).expand(batch, n).clone()
        return (q, zero, zero.clone(), nan, nan.clone(), nan.clone(), nan.clone(),
                torch.tensor(self.seeds[0], dtype=torch.int64))


class AdapterModule(PackageModule):
    """The tensor-only adapter of a trained ``DiffusionSchema`` (see the module doc); ``seeds``: the x_T draws
    the ``seed`` input may pick (default: the schema's ``sample_seed`` only)."""

    kind = "diffusion"

    def __init__(self, schema, n_steps: int = 20, seeds=None):
        from ..schemas import DiffusionSchema

        if not isinstance(schema, DiffusionSchema):
            raise BodySchemaInputError(f"AdapterModule exports the diffusion schema; got {type(schema).__name__} "
                                       "(deploy.structured.StructuredAdapterModule exports the structured schema)")
        super().__init__(schema, [int(schema.hparams.sample_seed)] if seeds is None else seeds)
        self.n_steps, self.dtype = int(n_steps), schema.dtype
        builder = schema.penalty_builder(VARIANT)
        self._mean_np, self._std_np, self.spring = builder.mean, builder.std, schema.spring
        self.register_buffer("x_mean", torch.as_tensor(self._mean_np, dtype=torch.float64))
        self.register_buffer("x_std", torch.as_tensor(self._std_np, dtype=torch.float64))
        self.c_w = _one_weight(builder)
        self.frozen, self.guidance, self._run = sampler_bridge(schema, self.n_steps, self.c_w)
        draws = [torch.randn(schema.x_dim, generator=torch.Generator().manual_seed(s), dtype=torch.float64)
                 for s in self.seeds]  # as DiffusionSchema.initial_noise: one float64 draw, cast
        self.register_buffer("x_T_table", torch.stack(draws).to(self.dtype))

    def forward(self, q_ref, cut, jam, l_fixed_m, f_weak_n, band_lo_m, band_hi_m, seed):
        bad, q, bounds = self.faults(q_ref, cut, jam, l_fixed_m, f_weak_n, band_lo_m, band_hi_m, seed)
        penalty = BoundsPenalty(bounds, self.x_mean, self.x_std, self.c_w, self.dtype)
        mode = self.guidance.inpaint if self.guidance.inpaint != "none" else "box"
        projection = FaultProjection.from_normalized_box(penalty.both[0], penalty.both[1], self._mean_np,
                                                         self._std_np, self.spring.k_n, self.spring.alpha_per_m, mode)
        pick = (self.seed_table == seed).to(self.dtype)
        x_t = (pick / pick.sum().clamp_min(1.0)) @ self.x_T_table
        x_t = x_t.expand(q.shape[0], -1).clone()
        x_n = self._run(self.normalized_q(q, self.dtype), x_t, penalty, projection)
        return self.safe(x_n.to(torch.float64) * self.x_std + self.x_mean, bounds, bad)
