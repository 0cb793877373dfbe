"""``AdapterModule``: the prepared diffusion adapter as one tensor-only ``nn.Module`` that ``torch.export`` can trace.

Every input is a tensor, the faults included, so ONE exported program serves every fault set: the penalty L_adapt
(``faults.penalty``) and the spring-inpainting projection (``faults.projection``) are built inside the graph from
the fault tensors, with the same maths as ``PenaltyBuilder``/``BoxPenalty``/``FaultProjection.from_penalty``.

forward(q_ref, cut, jam, l_fixed_m, f_weak_n, band_lo_m, band_hi_m, seed) -> (l_motor_m, f_n, status)

* ``q_ref (B, N)`` float64 [rad], the free joints in the model's order, inside their ranges.
* ``cut``, ``jam (B, M)`` float64 masks, 1.0 where the muscle is cut / jammed, else 0.0.
* ``l_fixed_m (B, M)`` float64 [m]: a jammed motor's length, NaN (ignored) where not jammed.
* ``f_weak_n (B, M)`` float64 [N]: a weakened muscle's tension limit, NaN where not weakened.
* ``band_lo_m``, ``band_hi_m (B, M)`` float64 [m]: a motor's length band, NaN where free.
* ``seed ()`` int64: picks x_T among the draws baked at export (``seeds``; the schema's ``sample_seed`` first).
* returns ``l_motor_m``, ``f_n (B, M)`` float64 [m], [N] (NaN rows unless ok) and ``status (B,)`` int32
  (``STATUS_CODES``).

Numbers: those of ``schema.adapter(faults, n_steps=k, check_physics=False)(q_ref)`` (variant ``"default"``), to
float32 rounding. Only ``DiffusionSchema`` (the MLP eps-model with a ``FrozenMLP`` snapshot) is supported.
"""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import torch
from torch import nn

from ..adaptation.command import motor_length_range
from ..errors import BodySchemaInputError
from ..faults.projection import FaultProjection

# what the graph can decide per case; a controller sends a command only where the status is 0
STATUS_CODES = {"ok": 0, "non_finite": 1, "out_of_range": 2, "fault_not_met": 3, "bad_input": 4}
FAULT_TOL_M = 1e-5  # a jam or band broken by more than this (after adaptation) is fault_not_met
FAULT_TOL_N = 1e-2  # a cut muscle pulling more than this is fault_not_met
VARIANT = "default"


# ------------------------------------------------------------------------------------------------------------------
# THE ONE DEPENDENCY ON SAMPLER INTERNALS (samplers.guided's plan and fused loop, the schema's step and guidance
# choice). Re-point this function, and nothing else, when samplers/guided.py or schemas/diffusion.py change.
def sampler_bridge(schema, n_steps: int, c_w: float):
    """(frozen eps-net, guidance, run): ``run(q_n (B, N), x_T (B, D), penalty, projection) -> x0_n (B, D)`` is the
    schema's fast guided loop of variant ``"default"`` over ``n_steps`` strided steps, with traceable ops, for a
    penalty whose residual is dL/dx / ``c_w`` (``c_w`` folded into the plan as ``DiffusionSchema._denoise`` does).
    The plan is built here, outside any trace."""
    from ..samplers.guided import guided_loop, plan_denoising

    preset = schema.sampler_preset(VARIANT, n_steps)
    steps, guidance = schema._timesteps(schema._n_steps(n_steps), preset.spacing), preset.guidance
    frozen = schema.eps_model.frozen()
    plan = plan_denoising(frozen, schema.schedule, steps, preset.eta, guidance, c_w, True, schema.prediction)

    def run(q_n, x_t, penalty, projection):
        biases = schema.eps_model.step_biases(frozen, q_n, steps)
        inpaint = projection if guidance.inpaint != "none" else None
        return guided_loop(plan.steps, biases.unbind(0), x_t, penalty, frozen, frozen.traceable, inpaint)
    return frozen, guidance, run
# ------------------------------------------------------------------------------------------------------------------


def check_supported(schema) -> None:
    """Refuse, in one line, a schema the exported adapter cannot reproduce."""
    from ..schemas import DiffusionSchema

    if not isinstance(schema, DiffusionSchema) or schema.eps_model.frozen() is None:
        raise BodySchemaInputError(f"export supports the diffusion schema with a SiLU/Tanh eps-MLP only; got "
                                   f"{type(schema).__name__}")
    joint_map = getattr(schema.robot_model, "joint_map", None)
    if joint_map is not None and len(joint_map.names) != schema.n_joints:
        raise BodySchemaInputError("export supports robots without locked or coupled joints only")


def _one_weight(builder) -> float:
    """The one weight w2 = 2 c (s_x / scale)^2 every term of the variant's L_adapt has (the default variant's:
    unit weights in spreads of the data); refuse weights that differ (the literal variant's)."""
    w, r2, m = builder.weights, builder.ratio2, builder.m
    every = np.concatenate([2.0 * w.c_fix * r2[:m], 2.0 * w.c_band * r2[:m], 2.0 * w.c_cut * r2[m:],
                            2.0 * w.c_fmin * r2[m:], 2.0 * w.c_fmax * r2[m:]])
    if not (every == every[0]).all():
        raise BodySchemaInputError("export supports adaptation losses with one weight for every term only")
    return float(every[0])


class _GraphPenalty:
    """L_adapt's gradient / c as ``guided_loop`` asks for it (``residual``; c, the one weight, is folded into the plan):
    two box terms per element, A (jam on l; cut or tension box on f) and B (band on l). Where only one applies the
    other adds an exact 0 (``BoxPenalty.residual``'s one-slot value); a jam and a band on one motor add up as
    ``BoxPenalty``'s two slots do."""

    def __init__(self, box_a, box_b):
        self.box_a, self.box_b = box_a, box_b

    def residual(self, x, out=None):
        (lo_a, hi_a), (lo_b, hi_b) = self.box_a, self.box_b
        return (x - torch.clamp(x, lo_a, hi_a)) + (x - torch.clamp(x, lo_b, hi_b))  # ``out``: not needed in a graph


class AdapterModule(nn.Module):
    """The tensor-only adapter of a trained ``DiffusionSchema`` (see the module doc); ``seeds``: the x_T draws
    the ``seed`` input may pick (default: the schema's ``sample_seed`` only)."""

    def __init__(self, schema, n_steps: int = 20, seeds=None):
        super().__init__()
        check_supported(schema)
        self.n_steps, self.dtype, self.m = int(n_steps), schema.dtype, schema.n_muscles
        builder = schema.penalty_builder(VARIANT)
        self._mean_np, self._std_np, self.spring = builder.mean, builder.std, schema.spring
        self.c_w = _one_weight(builder)
        self.frozen, self.guidance, self._run = sampler_bridge(schema, self.n_steps, self.c_w)
        self._register_limits(schema)
        self.seeds = [int(schema.hparams.sample_seed)] if seeds is None else [int(s) for s in seeds]
        draws = [torch.randn(schema.x_dim, generator=torch.Generator().manual_seed(s), dtype=torch.float64)
                 for s in self.seeds]  # as DiffusionSchema.initial_noise: one float64 draw, cast
        self.register_buffer("x_T_table", torch.stack(draws).to(self.dtype))
        self.register_buffer("seed_table", torch.as_tensor(self.seeds, dtype=torch.int64))

    def _register_limits(self, schema):
        """Buffers (float64): the normalizer, the joint ranges, the healthy f_max and the plausible motor lengths."""
        m, f64 = self.m, dict(dtype=torch.float64)
        q_range = np.asarray(schema.robot_model.q_range, float)
        l_range = motor_length_range(self._mean_np, self._std_np, m)
        f_max = np.broadcast_to(np.asarray(schema.spring.f_max_n, float), (m,)).copy()
        for name, value in (("x_mean", self._mean_np), ("x_std", self._std_np), ("q_lo", q_range[:, 0]),
                            ("q_hi", q_range[:, 1]), ("f_max_n", f_max), ("l_lo_m", np.maximum(l_range[0], 0.0)),
                            ("l_hi_m", l_range[1])):
            self.register_buffer(name, torch.as_tensor(value, **f64))
        self.register_buffer("q_norm_lo", schema.normalizer.q_lo.detach().to(torch.float64).clone())
        self.register_buffer("q_norm_hi", schema.normalizer.q_hi.detach().to(torch.float64).clone())

    # ------------------------------------------------------------------ inside the graph
    def _normalized(self, bound_si, cols: slice):
        """SI bound (B, M) float64 -> normalized, in the schema's dtype (as ``PenaltyBuilder._normalized``)."""
        return ((bound_si - self.x_mean[cols]) / self.x_std[cols]).to(self.dtype)

    def _check_inputs(self, q, cut, jam, l_fixed, f_weak, band_lo, band_hi, seed):
        """(B,) bool: the case breaks a rule ``Faults.validate`` or the posture check would refuse."""
        def is_mask(a):
            return (a == 0.0) | (a == 1.0)
        bad = ~(torch.isfinite(q) & (q >= self.q_lo) & (q <= self.q_hi)).all(1)
        bad |= ~(is_mask(cut) & is_mask(jam)).all(1)
        c, j = cut == 1.0, jam == 1.0
        weak, band = ~torch.isnan(f_weak), ~(torch.isnan(band_lo) & torch.isnan(band_hi))
        per_muscle = (c & j) | (j & ~(torch.isfinite(l_fixed) & (l_fixed > 0)))
        per_muscle |= weak & (torch.isinf(f_weak) | (f_weak < 0) | (f_weak >= self.f_max_n))
        per_muscle |= band & ~(torch.isfinite(band_lo) & torch.isfinite(band_hi) & (band_lo <= band_hi)
                               & (band_hi > 0) & ~c)
        bad |= per_muscle.any(1) | c.all(1)
        return bad | ~(self.seed_table == seed).any()

    def _boxes(self, cut, jam, l_fixed, f_limit, band, band_lo, band_hi):
        """The two penalty terms' boxes (normalized, (B, D) each) and the projection's box (their intersection)."""
        m, inf = self.m, float("inf")
        lcols, fcols = slice(0, m), slice(m, 2 * m)
        zero_n = self._normalized(torch.zeros_like(f_limit), fcols)
        jam_hi = torch.where(jam, self._normalized(l_fixed, lcols), inf)
        band_lo_n = torch.where(band, self._normalized(band_lo, lcols), -inf)
        band_hi_n = torch.where(band, self._normalized(band_hi, lcols), inf)
        f_hi = torch.where(cut, zero_n, self._normalized(f_limit, fcols))
        free = torch.full_like(jam_hi, inf)
        box_a = (torch.cat([-free, zero_n], 1), torch.cat([jam_hi, f_hi], 1))
        box_b = (torch.cat([band_lo_n, -free], 1), torch.cat([band_hi_n, free], 1))
        both = (torch.maximum(box_a[0], box_b[0]), torch.minimum(box_a[1], box_b[1]))
        return box_a, box_b, both

    def forward(self, q_ref, cut, jam, l_fixed_m, f_weak_n, band_lo_m, band_hi_m, seed):
        bad = self._check_inputs(q_ref, cut, jam, l_fixed_m, f_weak_n, band_lo_m, band_hi_m, seed)
        keep = ~bad[:, None]
        mid = 0.5 * (self.q_lo + self.q_hi)
        q = torch.where(keep, q_ref, mid)  # a bad case runs on harmless inputs; its row is NaN below
        c, j = keep & (cut == 1.0), keep & (jam == 1.0)
        weak = keep & ~torch.isnan(f_weak_n)
        band = keep & ~(torch.isnan(band_lo_m) & torch.isnan(band_hi_m))
        f_limit = torch.where(weak, f_weak_n, self.f_max_n)
        box_a, box_b, both = self._boxes(c, j, l_fixed_m, f_limit, band, band_lo_m, band_hi_m)
        penalty = _GraphPenalty(box_a, box_b)
        projection = FaultProjection.from_penalty(SimpleNamespace(lo=both[0][None], slots=[(torch.ones_like(
            both[0]), both[0], both[1])]), self._mean_np, self._std_np, self.spring.k_n, self.spring.alpha_per_m,
            self.guidance.inpaint if self.guidance.inpaint != "none" else "box")
        q_n = (2.0 * (q - self.q_norm_lo) / (self.q_norm_hi - self.q_norm_lo) - 1.0).to(self.dtype)
        pick = (self.seed_table == seed).to(self.dtype)
        x_t = (pick / pick.sum().clamp_min(1.0)) @ self.x_T_table
        x_t = x_t.expand(q.shape[0], -1).clone()
        x_n = self._run(q_n, x_t, penalty, projection)
        return self._safe_command(x_n.to(torch.float64) * self.x_std + self.x_mean, bad, c, j, l_fixed_m, f_limit,
                                  band, band_lo_m, band_hi_m)

    def _safe_command(self, x, bad, cut, jam, l_fixed, f_limit, band, band_lo, band_hi):
        """``adaptation.command.safe_command`` as tensor ops, plus ``fault_not_met`` and ``bad_input``."""
        m = self.m
        l_motor, f = x[:, :m], x[:, m:]
        finite = torch.isfinite(x).all(1)
        f_safe = torch.minimum(torch.clamp_min(f, 0.0), f_limit)
        outside = torch.maximum(torch.maximum(self.l_lo_m - l_motor, l_motor - self.l_hi_m), torch.zeros_like(l_motor))
        out_of_range = (outside > 0).any(1) | (l_motor <= 0).any(1)
        broken_m = torch.where(jam, l_motor - l_fixed, 0.0)
        broken_m = torch.maximum(broken_m, torch.where(band, torch.maximum(band_lo - l_motor, l_motor - band_hi), 0.0))
        not_met = (broken_m > FAULT_TOL_M).any(1) | (torch.where(cut, f_safe, 0.0) > FAULT_TOL_N).any(1)
        status = torch.where(not_met, STATUS_CODES["fault_not_met"], STATUS_CODES["ok"])
        status = torch.where(out_of_range, STATUS_CODES["out_of_range"], status)
        status = torch.where(finite, status, STATUS_CODES["non_finite"])
        status = torch.where(bad, STATUS_CODES["bad_input"], status).to(torch.int32)
        ok = (status == 0)[:, None]
        nan = torch.full_like(l_motor, float("nan"))
        return torch.where(ok, l_motor, nan), torch.where(ok, f_safe, nan), status

    def example_inputs(self, batch: int = 1):
        """Healthy inputs of ``batch`` cases at the middle of the joint ranges (what export traces with)."""
        n, m = self.q_lo.shape[0], self.m
        nan = torch.full((batch, m), float("nan"), dtype=torch.float64)
        zero = torch.zeros((batch, m), dtype=torch.float64)
        q = (0.5 * (self.q_lo + self.q_hi)).expand(batch, n).clone()
        return (q, zero, zero.clone(), nan, nan.clone(), nan.clone(), nan.clone(),
                torch.tensor(self.seeds[0], dtype=torch.int64))
