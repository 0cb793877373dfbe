"""Diffusion (DDPM) body schema (paper section II-C): eps-prediction conditioned on q."""
from __future__ import annotations

from typing import Optional

import torch

from ..errors import BodySchemaInputError
from ..networks import EpsMLP
from ..samplers import GuidanceConfig, NoiseSchedule, guided_denoise
from ..samplers.guided import BoxPenaltyBuilder
from .base import BodySchema


class LazyLoss:
    """``build(*args)``'s loss function, built on the first call: the fast paths use only ``grad_x0``, and
    building ``BodySchema``'s closure costs ~50 us, a twentieth of a fast adaptation at batch 1."""

    def __init__(self, build, *args):
        self._build, self._args, self._fn = build, args, None

    def __call__(self, x_n):
        if self._fn is None:
            self._fn = self._build(*self._args)
        return self._fn(x_n)


def with_analytic_gradient(schema: BodySchema, loss_fn, constraints, variant: str):
    """Attach ``loss_fn.grad_x0`` (dL/dx_n without autograd, ``samplers.guided.BoxPenalty``) to the loss
    ``BodySchema.adaptation_loss_fn`` built, for the fast adaptation paths.

    The loss's weights and unit scales come from ``BodySchema.adaptation_units``, as for the autograd
    loss; a test checks the two gradients against each other. Constraints of an unknown kind leave the loss without
    ``grad_x0`` (the fast paths then differentiate the loss with autograd).
    """
    # the model's dtype, from the constraints' float tensors (``adapt`` builds them in it): cheaper than
    # walking the module tree with ``next(schema.parameters())``
    dtype = next((v.dtype for c in constraints for v in vars(c).values()
                  if torch.is_tensor(v) and v.is_floating_point()), None) or next(schema.parameters()).dtype
    norm = schema.normalizer
    std, mean = norm._buffers["x_std"], norm._buffers["x_mean"]
    key = (variant, dtype, std.data_ptr(), std._version, mean.data_ptr(), mean._version)
    cache = schema.__dict__.setdefault("_box_builders", {})
    builder = cache.get(key)
    if builder is not None and (builder.x_std is not std or builder.x_mean is not mean):
        builder = None  # the normalizer's buffers were replaced (e.g. .double()/.float())
    if builder is None:
        if len(cache) >= 8:  # stale normalizer versions (e.g. during training): start over
            cache.clear()
        weights, l_scale, f_scale = schema.adaptation_units(variant, std)
        builder = cache[key] = BoxPenaltyBuilder(weights, l_scale, f_scale, mean, std, dtype)
        builder.x_mean, builder.x_std = mean, std  # held: their addresses cannot be reused while cached
    penalty = builder(constraints)
    if penalty is not None:
        loss_fn.grad_x0, loss_fn.box_penalty = penalty.grad_x0, penalty
    return loss_fn


SPACINGS = ("quad", "linspace", "trailing")


def strided_timesteps(n_timesteps: int, n_steps: int, spacing: str = "quad") -> list[int]:
    """``n_steps`` distinct descending steps from T-1 for a strided sampler.

    ``"quad"``: t_i = (T-1) (1 - i/(n-1))^2 rounded, i.e. dense at low noise, where the guidance settles the
    command (DDIM's "quadratic" spacing), ending at t = 0; ``"linspace"``: evenly from T-1 to 0;
    ``"trailing"``: ``NoiseSchedule.timesteps`` (T-1, T-1-T/n, ..., ending at T/n - 1). With n = T all three
    are T-1, ..., 0. Measured on the paper checkpoint (BENCHMARKS.md, 20 steps, one guidance step): quad
    leaves 0.03 N on a cut muscle (0.002 N with two guidance steps, the 200-step sampler 0.011 N), linspace
    0.4 N, trailing 2.6 N (its last guided step is at t = 9, where the network's Jacobian still blurs the
    correction).
    """
    import numpy as np

    T = n_timesteps
    if isinstance(n_steps, bool) or not isinstance(n_steps, int) or not 1 <= n_steps <= T:
        raise BodySchemaInputError(f"n_steps={n_steps!r} must be an int in 1..{T} (T)")
    if spacing not in SPACINGS:
        raise BodySchemaInputError(f"unknown spacing {spacing!r}; allowed: {list(SPACINGS)}")
    if n_steps == 1:
        return [T - 1]
    if spacing == "trailing":
        return [round(T - i * T / n_steps) - 1 for i in range(n_steps)]
    u = np.linspace(1.0, 0.0, n_steps)
    steps = np.rint((T - 1) * (u ** 2 if spacing == "quad" else u)).astype(int)
    for i in range(n_steps - 2, -1, -1):  # rounding can repeat a step near 0: keep them distinct
        steps[i] = max(steps[i], steps[i + 1] + 1)
    return steps.tolist()


class DiffusionSchema(BodySchema):
    """DDPM over x = [l_motor, f] conditioned on q, trained with ``||eps - h_diff(x_t, t, q)||^2``.

    Args:
        n_timesteps: T (paper: 200), linear schedule rescaled so x_T is noise (see ``NoiseSchedule``).
        hidden, n_hidden: eps-MLP width/depth (paper: 2 x 91 SiLU, ~11k parameters).
        sample_seed: seed of the x_T shared by all cases, so the same q always gives the same command.
        sample_steps: denoising steps of ``infer`` and ``adapt`` (healthy and adapted commands alike).
            None (the paper's): all T deterministic DDPM mean steps (eq:diff-2, no noise injected). k < T:
            the strided sampler ``STRIDED`` over k steps. Per call: ``adapt(..., n_steps=k)``, ``generate(q_n, n_steps=k)``.
        compile_sampler: run the fused sampling loop through ``torch.compile`` (``samplers.guided.compiled_core``;
            per call: ``compiled=``). The first call per (step plan, batch size) compiles for ~30 s; later calls
            save Python's per-op dispatch (BENCHMARKS.md). Off by default: a controller that restarts pays
            the compile again.
    The healthy command runs the deterministic denoising eq:diff-1/eq:diff-2 from x_T.

    The strided sampler (``STRIDED``; each entry can be overridden per call): ``"quad"``-spaced steps (dense at
    low noise, ending at t = 0, see ``strided_timesteps``), each joined by the noise-free *posterior-mean*
    step (``eta=1``: for stride 1 exactly eq:diff-2; DDIM's ``eta=0`` drifts off the data here, 10x larger
    length residuals of the healthy command), two guidance steps per timestep (``n_guide=2``: one left
    E_tau 34 % and E_cut 2.6x above the 200-step sampler's) and guidance only where abar_t >= 0.5
    (``min_abar``: guiding the noisier steps changed nothing measurable). With 20 steps it matches the
    200-step sampler within 10 % on every feasible-case median over 600 cases (BENCHMARKS.md) with 30
    network evaluations (20 with a backward pass) instead of 200 (all 200 with one).

    Sampling runs the autograd-free fast path by default (``fast=False`` per call: the autograd reference;
    the same commands, see ``samplers.guided``).
    """

    STRIDED = {"spacing": "quad", "eta": 1.0, "n_guide": 2, "min_abar": 0.5}

    # eq:diff-adapt settings per variant; see BodySchema.adapt and README "Design decisions"
    ADAPT = {"literal": GuidanceConfig(lr=0.01, step_scale="none"),
             "default": GuidanceConfig(lr=0.5, step_scale="abar")}

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
        x_t = self.schedule.add_noise(x_n, eps, t)
        loss = (eps - self.eps_model(x_t, t, q_n)).pow(2).mean()
        return loss, {}

    def _timesteps(self, n_steps: Optional[int], spacing: Optional[str] = None) -> Optional[list[int]]:
        """None (all T steps) or the strided steps for ``n_steps`` (None: ``sample_steps``)."""
        if spacing is not None and spacing not in SPACINGS:
            raise BodySchemaInputError(f"unknown spacing {spacing!r}; allowed: {list(SPACINGS)}")
        n_steps = self.hparams.get("sample_steps") if n_steps is None else n_steps
        if n_steps is None:
            return None
        T = self.schedule.n_timesteps
        if isinstance(n_steps, bool) or not isinstance(n_steps, int) or not 1 <= n_steps <= T:
            raise BodySchemaInputError(f"n_steps/sample_steps={n_steps!r} must be an int in 1..{T} (T) or None "
                                       f"(all T DDPM steps)")
        if n_steps == T:
            return None
        key = (n_steps, spacing or self.STRIDED["spacing"])
        cache = self.__dict__.setdefault("_steps_cache", {})
        if key not in cache:
            cache[key] = strided_timesteps(T, *key)
        return cache[key]

    def _sampler_options(self, steps, eta, n_guide, min_abar, base: GuidanceConfig):
        """eta, n_guide and min_abar for a run over ``steps``: the strided defaults, or the paper's for all T."""
        strided = steps is not None
        eta = (self.STRIDED["eta"] if strided else 1.0) if eta is None else eta
        n_guide = (self.STRIDED["n_guide"] if strided else base.n_guide) if n_guide is None else n_guide
        min_abar = (self.STRIDED["min_abar"] if strided else base.min_abar) if min_abar is None else min_abar
        return float(eta), n_guide, float(min_abar)

    def initial_noise(self, n: int, like: torch.Tensor) -> torch.Tensor:
        """x_T for n cases: ONE seeded draw shared by every case.

        A command then depends only on its own q (and faults), never on the batch it was computed in:
        torch draws different normals for a (6, D) and a (1, D) request from the same seed.
        """
        key = (self.hparams.sample_seed, like.dtype, like.device)
        cached = self.__dict__.get("_x_T")
        if cached is None or cached[0] != key:  # one draw per seed/dtype/device, reused (read-only)
            gen = torch.Generator().manual_seed(self.hparams.sample_seed)
            x_T = torch.randn(self.x_dim, generator=gen, dtype=torch.float64)
            cached = (key, x_T.to(like.device, like.dtype))
            self.__dict__["_x_T"] = cached
        return cached[1].expand(n, -1).clone()

    def generate(self, q_n, n_steps: Optional[int] = None, fast: bool = True, eta: Optional[float] = None,
                 spacing: Optional[str] = None, compiled: Optional[bool] = None):
        """Healthy normalized command: unguided deterministic denoising from x_T (``sample_steps`` steps)."""
        steps = self._timesteps(n_steps, spacing)
        eta = self._sampler_options(steps, eta, None, None, GuidanceConfig())[0]
        with torch.no_grad():
            return guided_denoise(self.eps_model, self.schedule, q_n, self.initial_noise(len(q_n), q_n), None,
                                  GuidanceConfig(), steps, fast=fast, eta=eta, compiled=self._compiled(fast, compiled))

    def adaptation_loss_fn(self, constraints, variant: str):
        """``BodySchema``'s loss (built on first use), with its analytic gradient attached for the fast path."""
        return with_analytic_gradient(self, LazyLoss(super().adaptation_loss_fn, constraints, variant),
                                      constraints, variant)

    def adapt_normalized(self, q_n, loss_fn, variant, lr=None, step_scale=None, n_steps=None, n_guide=None,
                         fast=True, eta=None, spacing=None, min_abar=None, compiled=None):
        """Gradient-guided denoising (eq:diff-1, eq:diff-adapt, eq:diff-2) from the same x_T as ``generate``.

        n_steps: None uses ``sample_steps`` (None: all T DDPM steps); k < T runs the strided sampler over k
        steps (``STRIDED``: spacing, eta, n_guide, min_abar, each overridable here). n_guide: guidance steps
        per timestep; min_abar: guide only where abar_t >= min_abar (for all T steps: 1 and 0, the paper's;
        see ``GuidanceConfig``). fast: the autograd-free path (default) or the autograd reference
        (``fast=False``); same commands. compiled: ``torch.compile`` the fast loop (None: ``compile_sampler``).
        """
        base = self.ADAPT[variant]
        steps = self._timesteps(n_steps, spacing)
        eta, n_guide, min_abar = self._sampler_options(steps, eta, n_guide, min_abar, base)
        guidance = GuidanceConfig(lr=base.lr if lr is None else lr,
                                  step_scale=base.step_scale if step_scale is None else step_scale,
                                  n_guide=n_guide, min_abar=min_abar)
        return guided_denoise(self.eps_model, self.schedule, q_n, self.initial_noise(len(q_n), q_n), loss_fn,
                              guidance, steps, fast=fast, eta=eta, compiled=self._compiled(fast, compiled))

    def _compiled(self, fast: bool, compiled: Optional[bool]) -> bool:
        """Per-call ``compiled``, else the ``compile_sampler`` default (only with the fast path)."""
        if compiled is None:
            return bool(fast and self.hparams.get("compile_sampler", False))
        return bool(compiled)
