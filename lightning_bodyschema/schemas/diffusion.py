"""Diffusion (DDPM) body schema (paper section II-C): eps-, x0- or v-prediction conditioned on q, adapted by guided
denoising."""
from __future__ import annotations

import math
from dataclasses import replace
from typing import Optional

import torch

from .._numpy import to_numpy
from ..errors import BodySchemaInputError
from ..faults.projection import projection_for
from ..networks import EpsMLP
from ..samplers import GuidanceConfig, NoiseSchedule, denoise, plan_denoising, reference_loop
from ..samplers.presets import SamplerPreset, adapt_preset
from ..samplers.schedule import check_prediction
from ..variants import check_variant
from .base import BodySchema


class DiffusionSchema(BodySchema):
    """DDPM over x = [l_motor, f] conditioned on q: the network h_diff(x_t, t, q) predicts ``prediction``
    (the paper's eps: trained with ``||eps - h_diff(x_t, t, q)||^2``).

    Args:
        n_timesteps: T (paper: 200), linear schedule rescaled so x_T is noise (see ``NoiseSchedule``).
        hidden, n_hidden: MLP width/depth (paper: 2 x 91 SiLU, ~11k parameters).
        sample_seed: seed of the x_T shared by all cases, so the same q always gives the same command.
        sample_steps: denoising steps of ``infer`` and ``adapt`` (healthy and adapted commands alike).
            None (the paper's): all T deterministic DDPM mean steps (eq:diff-2 without its noise term), each
            variant's ``full`` preset. k < T: the strided sampler over k steps, each variant's ``strided`` preset
            (``ADAPT``). Per call: ``adapt(..., n_steps=k)``, ``generate(q_n, n_steps=k)``.
        prediction: what the network outputs (``samplers.schedule.PREDICTIONS``): ``"eps"`` the noise (the paper's),
            ``"x0"`` the clean command, ``"v"`` sqrt(abar_t) eps - sqrt(1 - abar_t) x0; trained with the squared error
            to that target, converted for sampling by ``NoiseSchedule.split_output`` (every sampler path).
        min_snr_gamma: min-SNR-gamma loss weighting (Hang et al. 2023, ``NoiseSchedule.min_snr_weight``): each
            sample's squared error weighted by min(SNR_t, gamma) in its prediction's units; None: unweighted.
        compile_sampler: run the fast sampling loop through ``torch.compile`` (``samplers.guided.compiled_sampler``;
            per call: ``compiled=``). The first call per (step plan, batch size) compiles (its cost: BENCHMARKS.md
            "Figures behind code choices"); later calls save Python's per-op dispatch. Off by default: a
            controller that restarts pays the compile again.
    The healthy command runs the deterministic denoising eq:diff-1/eq:diff-2 from x_T.

    The strided sampler: ``"quad"``-spaced steps (dense at low noise, ending at t = 0, see
    ``NoiseSchedule.timesteps``), each joined by the noise-free posterior-mean step (``eta=1``: for stride 1
    exactly eq:diff-2), with the variant's strided guidance (``ADAPT[variant].strided``).

    Sampling runs the autograd-free fast loop by default (``fast=False`` per call: the autograd reference; the
    same commands, see ``samplers.guided``).
    """

    capabilities = frozenset({"adapts_normalized"})  # contract.ADAPTS_NORMALIZED

    # eq:diff-adapt settings per variant, each a fully resolved preset for all T steps and for the strided sampler
    # (``samplers.presets``); see BodySchema.adapt and README "Design decisions". The
    # strided sampler guides twice per step where abar_t >= 0.5, or, where it inpaints, guides and inpaints from
    # abar_t >= 0.3. Selectable by name (``adapt(..., variant=...)``, ``--variant``).
    _STRIDED = {"n_guide": 2, "min_abar": 0.5}
    _STRIDED_INPAINT = {"n_guide": 2, "min_abar": 0.3, "inpaint_min_abar": 0.3}
    _GUIDED = GuidanceConfig(lr=0.5, step_scale="abar")
    ADAPT = {"literal": adapt_preset(GuidanceConfig(lr=0.01, step_scale="none"), _STRIDED),
             # gradient guidance plus spring-consistent inpainting of x0 where abar_t >= 0.5 (all T steps)
             "default": adapt_preset(replace(_GUIDED, lr=1.0, inpaint="spring", inpaint_min_abar=0.5), _STRIDED_INPAINT),
             "guided": adapt_preset(_GUIDED, _STRIDED),  # gradient guidance only
             "strong": adapt_preset(replace(_GUIDED, lr=1.0, n_guide=4), _STRIDED),
             "recurrent": adapt_preset(replace(_GUIDED, recurrence=3), _STRIDED),
             "inpaint_box": adapt_preset(replace(_GUIDED, inpaint="box"), _STRIDED_INPAINT),
             "inpaint_spring": adapt_preset(replace(_GUIDED, inpaint="spring"), _STRIDED_INPAINT),
             "projected": adapt_preset(replace(_GUIDED, project_xt=True), _STRIDED)}
    VARIANTS = tuple(ADAPT)
    SAMPLE = SamplerPreset()  # the healthy (unguided) sample: quad spacing when strided, eta = 1
    RUN_OPTIONS = ("n_steps", "fast", "compiled", "inference_mode", "projection")  # adapt_normalized's own

    def __init__(self, n_timesteps: int = 200, hidden: int = 91, n_hidden: int = 2, sample_seed: int = 0,
                 robot: Optional[dict] = None, lr: float = 1e-3, lr_final: Optional[float] = 1e-5,
                 batch_size: int = 64, sample_steps: Optional[int] = None, compile_sampler: bool = False,
                 prediction: str = "eps", min_snr_gamma: Optional[float] = None):
        super().__init__(robot=robot, lr=lr, lr_final=lr_final, batch_size=batch_size)
        check_prediction(prediction)
        if min_snr_gamma is not None and (isinstance(min_snr_gamma, bool) or not 0.0 < float(min_snr_gamma) < math.inf):
            raise BodySchemaInputError(f"min_snr_gamma={min_snr_gamma!r} must be a positive number or None (no weighting)")
        self.save_hyperparameters()
        self.prediction = prediction
        self.eps_model = EpsMLP(self.x_dim, self.n_joints, hidden=hidden, n_hidden=n_hidden, n_timesteps=n_timesteps)
        self.schedule = NoiseSchedule(n_timesteps)
        self._n_steps(sample_steps)  # refuse a bad value at construction

    def training_loss(self, q_n, x_n):
        t = torch.randint(0, self.schedule.n_timesteps, (len(x_n),), device=x_n.device)
        eps = torch.randn_like(x_n)
        x_t = self.schedule.add_noise(x_n, eps, t, check=False)  # t in 0..T-1 by construction
        target = self.schedule.training_target(x_n, eps, t, self.prediction)
        gamma = self.hparams.get("min_snr_gamma")
        if gamma is None:
            return (target - self.eps_model(x_t, t, q_n)).pow(2).mean(), {}
        weight = self.schedule.min_snr_weight(t, gamma, self.prediction).to(x_n.dtype)
        return (weight * (target - self.eps_model(x_t, t, q_n)).pow(2).mean(-1)).mean(), {}

    # ------------------------------------------------------------------ sampler settings
    def timesteps(self, n_steps: Optional[int], spacing: str) -> tuple[int, ...]:
        """The descending steps of a call over ``n_steps`` (None: ``sample_steps``, else all T; checked) with
        ``spacing`` (unused for all T steps)."""
        T, n_steps = self.schedule.n_timesteps, self._n_steps(n_steps)
        if n_steps == T:
            return tuple(range(T - 1, -1, -1))
        return self.inference_cache.get(("timesteps", n_steps, spacing),
                                        lambda: tuple(self.schedule.timesteps(n_steps, spacing)))

    def denoising_plan(self, steps, eta: float, guidance, c_w: float = 1.0, guided: bool = True):
        """The fast loop's ``samplers.DenoisePlan`` over ``steps`` (``timesteps``) with ``eta`` and ``guidance`` (a
        resolved ``GuidanceConfig``), the penalty's one weight ``c_w`` folded in (``guided``: a penalty is given),
        through the network's frozen snapshot; cached per settings until the weights change. None where the network
        has no frozen snapshot (then only the autograd reference samples). ``_denoise`` and the exported package
        (``deploy``) both sample from it."""
        frozen = self.inference_cache.get(("frozen_eps",), self.eps_model.frozen)
        if frozen is None:
            return None
        return self.inference_cache.get(("plan", tuple(steps), float(eta), guidance, float(c_w), bool(guided)),
                                        lambda: plan_denoising(frozen, self.schedule, steps, eta, guidance, c_w,
                                                               guided, self.prediction))

    def _n_steps(self, n_steps: Optional[int]) -> int:
        """The step count of a call: ``n_steps``, else ``sample_steps``, else all T (checked: an int in 1..T)."""
        n_steps = self.hparams.get("sample_steps") if n_steps is None else n_steps
        T = self.schedule.n_timesteps
        if n_steps is not None and (isinstance(n_steps, bool) or not isinstance(n_steps, int) or not 1 <= n_steps <= T):
            raise BodySchemaInputError(f"n_steps/sample_steps={n_steps!r} must be an int in 1..{T} (T) or None "
                                       f"(all T DDPM steps)")
        return T if n_steps is None else n_steps

    def sampler_preset(self, variant: str, n_steps: Optional[int] = None, **overrides) -> SamplerPreset:
        """The resolved settings ``adapt(..., variant=variant, n_steps=n_steps, **overrides)`` runs with: the
        variant's full-T or strided preset (``ADAPT``), the named fields replaced by ``overrides``."""
        check_variant(self, variant)
        strided = self._n_steps(n_steps) < self.schedule.n_timesteps
        build = lambda: self.ADAPT[variant].resolve(strided, self.RUN_OPTIONS, **overrides)  # noqa: E731
        try:
            key = ("preset", variant, strided, tuple(sorted(overrides.items())))
            hash(key)
        except TypeError:  # an unhashable value: resolved (and refused, if it must be) without the cache
            return build()
        return self.inference_cache.get(key, build)

    def fault_projection(self, variant: str, penalty, inpaint: Optional[str] = None):
        """The ``faults.projection.FaultProjection`` the variant inpaints or projects with (None: it does neither)."""
        config = self.ADAPT[check_variant(self, variant)].full.guidance  # inpaint and project_xt: the same strided
        mode = config.inpaint if inpaint is None else inpaint
        mode = "box" if mode == "none" and config.project_xt else mode
        mean, std = to_numpy(self.normalizer.x_mean), to_numpy(self.normalizer.x_std)  # host arrays: any device
        return projection_for(penalty, mode, mean, std, self.spring)

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
        """Healthy normalized command: unguided deterministic denoising from x_T (``sample_steps`` steps, ``SAMPLE``
        with ``eta``/``spacing`` replaced where given)."""
        n_steps = self._n_steps(n_steps)
        preset = self.SAMPLE.with_overrides(eta=eta, spacing=spacing)
        with torch.no_grad():
            return self._denoise(q_n, None, self.timesteps(n_steps, preset.spacing), preset.eta, preset.guidance,
                                 fast, compiled)

    def adapt_normalized(self, q_n, penalty, variant, n_steps=None, fast=True, compiled=None, inference_mode=True,
                         projection=None, **overrides):
        """Gradient-guided denoising (eq:diff-1, eq:diff-adapt, eq:diff-2) of ``penalty`` from the same x_T as
        ``generate``, with the settings ``sampler_preset(variant, n_steps, **overrides)``.

        n_steps: None uses ``sample_steps`` (None: all T DDPM steps, the variant's full preset); k < T runs the
        strided sampler over k steps (the variant's strided preset). overrides: any field of the preset
        (``SamplerPreset.OPTIONS``: spacing, eta, lr, step_scale, n_guide, min_abar, inpaint, ...; see
        ``GuidanceConfig``); an unknown name is refused. fast: the autograd-free loop (default) or the autograd
        reference (``fast=False``); same commands. compiled: ``torch.compile`` the fast loop (None:
        ``compile_sampler``). inference_mode: run the fast loop under ``torch.inference_mode`` (False: for
        benchmarks of that choice). projection: the ``fault_projection`` of the faults (the adapter builds it once;
        None with inpainting on: built here from ``penalty``).
        """
        n_steps = self._n_steps(n_steps)
        preset = self.sampler_preset(variant, n_steps, **overrides)
        guidance = preset.guidance
        if projection is None and (guidance.inpaint != "none" or guidance.project_xt):
            projection = self.fault_projection(variant, penalty, guidance.inpaint)
        return self._denoise(q_n, penalty, self.timesteps(n_steps, preset.spacing), preset.eta, guidance, fast,
                             compiled, inference_mode, projection)

    def _denoise(self, q_n, penalty, steps, eta, guidance, fast, compiled, inference_mode=True, projection=None):
        """The fast loop through the network's frozen snapshot, or the autograd reference (``fast=False``, or an
        activation without a hand-written derivative)."""
        compiled = bool(fast and self.hparams.get("compile_sampler", False)) if compiled is None else bool(compiled)
        if compiled and not fast:
            raise BodySchemaInputError("compiled=True needs the fast path (fast=True)")
        x_T = self.initial_noise(len(q_n), q_n)
        frozen = self.inference_cache.get(("frozen_eps",), self.eps_model.frozen) if fast else None
        if frozen is None or guidance.reference_only:
            return reference_loop(self.eps_model, self.schedule, q_n, x_T, penalty, guidance, steps, eta, projection,
                                  self.prediction)
        c_w = 1.0 if penalty is None or penalty.uniform_weight is None else penalty.uniform_weight
        plan = self.denoising_plan(steps, eta, guidance, c_w, penalty is not None)
        biases = self.eps_model.step_biases(frozen, q_n, steps)
        inpaint = projection if guidance.inpaint != "none" else None
        return denoise(frozen, plan, biases, x_T, penalty, compiled, inference_mode, inpaint)
