"""Diffusion (DDPM) body schema (paper section II-C): eps-prediction conditioned on q, adapted by guided denoising."""
from __future__ import annotations

from dataclasses import fields, replace
from typing import Optional

import torch

from ..errors import BodySchemaInputError
from ..faults.projection import projection_for
from ..networks import EpsMLP
from ..samplers import GuidanceConfig, NoiseSchedule, denoise, plan_denoising, reference_loop
from ..samplers.schedule import SPACINGS
from .base import BodySchema


class DiffusionSchema(BodySchema):
    """DDPM over x = [l_motor, f] conditioned on q, trained with ``||eps - h_diff(x_t, t, q)||^2``.

    Args:
        n_timesteps: T (paper: 200), linear schedule rescaled so x_T is noise (see ``NoiseSchedule``).
        hidden, n_hidden: eps-MLP width/depth (paper: 2 x 91 SiLU, ~11k parameters).
        sample_seed: seed of the x_T shared by all cases, so the same q always gives the same command.
        sample_steps: denoising steps of ``infer`` and ``adapt`` (healthy and adapted commands alike).
            None (the paper's): all T deterministic DDPM mean steps (eq:diff-2 without its noise term). k < T: the
            strided sampler ``STRIDED`` over k steps. Per call: ``adapt(..., n_steps=k)``, ``generate(q_n, n_steps=k)``.
        compile_sampler: run the fast sampling loop through ``torch.compile`` (``samplers.guided.compiled_sampler``;
            per call: ``compiled=``). The first call per (step plan, batch size) compiles for ~20-40 s; later calls
            save Python's per-op dispatch (BENCHMARKS.md). Off by default: a controller that restarts pays the
            compile again.
    The healthy command runs the deterministic denoising eq:diff-1/eq:diff-2 from x_T.

    The strided sampler (``STRIDED``; each entry can be overridden per call): ``"quad"``-spaced steps (dense at low
    noise, ending at t = 0, see ``NoiseSchedule.timesteps``), each joined by the noise-free posterior-mean step
    (``eta=1``: for stride 1 exactly eq:diff-2; DDIM's ``eta=0`` drifts off the data here, 10x larger length
    residuals of the healthy command), two guidance steps per timestep (``n_guide=2``: one left E_tau 34 % and
    E_cut 2.6x above the 200-step sampler's) and guidance only where abar_t >= 0.5 (``min_abar``: guiding the
    noisier steps changed nothing measurable). With 20 steps it matches the 200-step sampler within 10 % on every
    feasible-case median over 600 cases (BENCHMARKS.md) with 30 network evaluations (20 with a backward pass)
    instead of 200 (all 200 with one).

    Sampling runs the autograd-free fast loop by default (``fast=False`` per call: the autograd reference; the
    same commands, see ``samplers.guided``).
    """

    capabilities = frozenset({"adapts_normalized"})  # contract.ADAPTS_NORMALIZED

    STRIDED = {"spacing": "quad", "eta": 1.0, "n_guide": 2, "min_abar": 0.5}
    # with inpainting, guide and inpaint from abar_t >= 0.3: at 0.5 the 20 strided steps left BOTH's E_tau 1.54x the
    # 200-step sampler's on binding faults, at 0.3 1.42x (RESULTS.md)
    STRIDED_INPAINT = {"min_abar": 0.3, "inpaint_min_abar": 0.3}

    # eq:diff-adapt settings per variant; see BodySchema.adapt, README "Design decisions" and RESULTS.md (binding
    # faults). The study variants are selectable by name (``adapt(..., variant=...)``, ``--variant``).
    _GUIDED = GuidanceConfig(lr=0.5, step_scale="abar")
    ADAPT = {"literal": GuidanceConfig(lr=0.01, step_scale="none"),
             # gradient guidance plus spring-consistent inpainting of x0 where abar_t >= 0.5: meets the binding-fault
             # targets where guidance alone leaves jams ~0.7 mm broken (RESULTS.md); lr 1: at 0.5 BOTH's E_tau misses
             "default": replace(_GUIDED, lr=1.0, inpaint="spring", inpaint_min_abar=0.5),
             "guided": _GUIDED,  # gradient guidance only: the default before the binding-fault study
             "strong": replace(_GUIDED, lr=1.0, n_guide=4),
             "recurrent": replace(_GUIDED, recurrence=3),
             "inpaint_box": replace(_GUIDED, inpaint="box"),
             "inpaint_spring": replace(_GUIDED, inpaint="spring"),
             "projected": replace(_GUIDED, project_xt=True)}
    VARIANTS = tuple(ADAPT)

    def __init__(self, n_timesteps: int = 200, hidden: int = 91, n_hidden: int = 2, sample_seed: int = 0,
                 robot: Optional[dict] = None, lr: float = 1e-3, lr_final: Optional[float] = 1e-5,
                 batch_size: int = 64, sample_steps: Optional[int] = None, compile_sampler: bool = False):
        super().__init__(robot=robot, lr=lr, lr_final=lr_final, batch_size=batch_size)
        self.save_hyperparameters()
        self.eps_model = EpsMLP(self.x_dim, self.n_joints, hidden=hidden, n_hidden=n_hidden, n_timesteps=n_timesteps)
        self.schedule = NoiseSchedule(n_timesteps)
        self._timesteps(sample_steps)  # refuse a bad value at construction

    def training_loss(self, q_n, x_n):
        t = torch.randint(0, self.schedule.n_timesteps, (len(x_n),), device=x_n.device)
        eps = torch.randn_like(x_n)
        x_t = self.schedule.add_noise(x_n, eps, t, check=False)  # t in 0..T-1 by construction
        loss = (eps - self.eps_model(x_t, t, q_n)).pow(2).mean()
        return loss, {}

    # ------------------------------------------------------------------ sampler settings
    def _timesteps(self, n_steps: Optional[int], spacing: Optional[str] = None) -> tuple[int, ...]:
        """The descending steps for ``n_steps`` (None: ``sample_steps``; None or T: all T steps)."""
        if spacing is not None and spacing not in SPACINGS:
            raise BodySchemaInputError(f"unknown spacing {spacing!r}; allowed: {list(SPACINGS)}")
        n_steps = self.hparams.get("sample_steps") if n_steps is None else n_steps
        T = self.schedule.n_timesteps
        if n_steps is not None and (isinstance(n_steps, bool) or not isinstance(n_steps, int) or not 1 <= n_steps <= T):
            raise BodySchemaInputError(f"n_steps/sample_steps={n_steps!r} must be an int in 1..{T} (T) or None "
                                       f"(all T DDPM steps)")
        if n_steps is None or n_steps == T:
            return tuple(range(T - 1, -1, -1))
        spacing = spacing or self.STRIDED["spacing"]
        return self.inference_cache.get(("timesteps", n_steps, spacing),
                                        lambda: tuple(self.schedule.timesteps(n_steps, spacing)))

    def _guidance(self, steps, variant, **overrides) -> GuidanceConfig:
        """The variant's eq:diff-adapt settings with per-call overrides (None: keep); the strided defaults for fewer
        than T steps."""
        values = {f.name: getattr(self.ADAPT[variant], f.name) for f in fields(GuidanceConfig)}
        if len(steps) < self.schedule.n_timesteps:
            values.update(n_guide=self.STRIDED["n_guide"], min_abar=self.STRIDED["min_abar"])
            if values["inpaint"] != "none" and overrides.get("inpaint") in (None, values["inpaint"]):
                values.update(self.STRIDED_INPAINT)
        values.update({name: value for name, value in overrides.items() if value is not None})
        return GuidanceConfig(**{**values, "min_abar": float(values["min_abar"])})

    def fault_projection(self, variant: str, penalty, inpaint: Optional[str] = None):
        """The ``faults.projection.FaultProjection`` the variant inpaints or projects with (None: it does neither)."""
        config = self.ADAPT[variant]
        mode = config.inpaint if inpaint is None else inpaint
        mode = "box" if mode == "none" and config.project_xt else mode
        return projection_for(penalty, mode, self.normalizer.x_mean, self.normalizer.x_std, self.spring)

    def initial_noise(self, n: int, like: torch.Tensor) -> torch.Tensor:
        """x_T for n cases: ONE seeded draw shared by every case.

        A command then depends only on its own q (and faults), never on the batch it was computed in (up to the
        rounding of matrix products of another batch size: ~1e-7 m, 1e-3 N in float32): torch draws different
        normals for a (6, D) and a (1, D) request from the same seed.
        """
        def draw():
            gen = torch.Generator().manual_seed(self.hparams.sample_seed)
            return torch.randn(self.x_dim, generator=gen, dtype=torch.float64).to(like.device, like.dtype)
        return self.inference_cache.get(("x_T", like.dtype, like.device), draw).expand(n, -1).clone()

    # ------------------------------------------------------------------ sampling
    def generate(self, q_n, n_steps: Optional[int] = None, fast: bool = True, eta: Optional[float] = None,
                 spacing: Optional[str] = None, compiled: Optional[bool] = None):
        """Healthy normalized command: unguided deterministic denoising from x_T (``sample_steps`` steps)."""
        steps = self._timesteps(n_steps, spacing)
        with torch.no_grad():
            return self._denoise(q_n, None, steps, self.STRIDED["eta"] if eta is None else eta, GuidanceConfig(),
                                 fast, compiled)

    def adapt_normalized(self, q_n, penalty, variant, lr=None, step_scale=None, n_steps=None, n_guide=None,
                         fast=True, eta=None, spacing=None, min_abar=None, compiled=None, inference_mode=True,
                         inpaint=None, inpaint_min_abar=None, inpaint_n_guide=None, recurrence=None, project_xt=None,
                         projection=None):
        """Gradient-guided denoising (eq:diff-1, eq:diff-adapt, eq:diff-2) of ``penalty`` from the same x_T as
        ``generate``.

        n_steps: None uses ``sample_steps`` (None: all T DDPM steps); k < T runs the strided sampler over k
        steps (``STRIDED``: spacing, eta, n_guide, min_abar, each overridable here). n_guide: guidance steps
        per timestep; min_abar: guide only where abar_t >= min_abar (for all T steps: 1 and 0, the paper's;
        see ``GuidanceConfig``). fast: the autograd-free loop (default) or the autograd reference
        (``fast=False``); same commands. compiled: ``torch.compile`` the fast loop (None: ``compile_sampler``).
        inference_mode: run the fast loop under ``torch.inference_mode`` (False: for benchmarks of that choice).
        inpaint, inpaint_min_abar, inpaint_n_guide, recurrence, project_xt: see ``GuidanceConfig``; projection: the ``fault_projection`` of the faults
        (the adapter builds it once; None with inpainting on: built here from ``penalty``).
        """
        steps = self._timesteps(n_steps, spacing)
        guidance = self._guidance(steps, variant, lr=lr, step_scale=step_scale, n_guide=n_guide, min_abar=min_abar,
                                  inpaint=inpaint, inpaint_min_abar=inpaint_min_abar, inpaint_n_guide=inpaint_n_guide,
                                  recurrence=recurrence, project_xt=project_xt)
        if projection is None and (guidance.inpaint != "none" or guidance.project_xt):
            projection = self.fault_projection(variant, penalty, guidance.inpaint)
        return self._denoise(q_n, penalty, steps, self.STRIDED["eta"] if eta is None else eta, guidance, fast, compiled,
                             inference_mode, projection)

    def _denoise(self, q_n, penalty, steps, eta, guidance, fast, compiled, inference_mode=True, projection=None):
        """The fast loop through the eps-model's frozen snapshot, or the autograd reference (``fast=False``, or an
        activation without a hand-written derivative)."""
        compiled = bool(fast and self.hparams.get("compile_sampler", False)) if compiled is None else bool(compiled)
        if compiled and not fast:
            raise BodySchemaInputError("compiled=True needs the fast path (fast=True)")
        x_T = self.initial_noise(len(q_n), q_n)
        frozen = self.inference_cache.get(("frozen_eps",), self.eps_model.frozen) if fast else None
        if frozen is None or guidance.reference_only:
            return reference_loop(self.eps_model, self.schedule, q_n, x_T, penalty, guidance, steps, eta, projection)
        c_w = 1.0 if penalty is None or penalty.uniform_weight is None else penalty.uniform_weight
        plan = self.inference_cache.get(("plan", steps, float(eta), guidance, c_w, penalty is not None),
                                        lambda: plan_denoising(frozen, self.schedule, steps, eta, guidance, c_w,
                                                               guided=penalty is not None))
        biases = self.eps_model.step_biases(frozen, q_n, steps)
        inpaint = projection if guidance.inpaint != "none" else None
        return denoise(frozen, plan, biases, x_T, penalty, compiled, inference_mode, inpaint)
