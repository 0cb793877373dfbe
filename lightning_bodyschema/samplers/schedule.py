"""DDPM noise schedule and its deterministic update (paper section II-C and III-C).

Modelled on diffusers' ``scheduling_ddpm.py`` and kept to what the body schema needs: one linear beta
schedule, the forward (noising) process, THE conversion of a network's output into (x0_hat, eps_hat) for each
prediction type (``output_affine``/``split_output``; eq:diff-1 for eps), the training target and min-SNR loss
weight of each type, ONE deterministic update between two timesteps with its ONE coefficient formula
(``step_coefficients``), and the strided timestep lists of fast samplers. The guidance step eq:diff-adapt is not
here: it needs a loss and a model, and this module imports neither. A sampler calls ``split_output`` -> its own
guidance -> ``step``.

**prediction** (``PREDICTIONS``) is what the network outputs at x_t: ``"eps"`` the noise (the paper's), ``"x0"``
the clean data, ``"v"`` = sqrt(abar_t) eps - sqrt(1 - abar_t) x0 (Salimans & Ho 2022). Every type is an affine
map of (x_t, output) to x0_hat and to eps_hat, consistent with the forward process
(``x_t = sqrt(abar_t) x0_hat + sqrt(1 - abar_t) eps_hat`` holds exactly in exact arithmetic); adding a type is one
entry of ``_AFFINE`` and of ``training_target``.

**eta** is DDIM's eta (Song et al. 2021) everywhere in this package: it picks the deterministic update from t to
an earlier t' with the noise term left out. ``eta = 1``: the mean of the DDPM posterior q(x_t' | x_t, x0_hat);
for t' = t - 1 this is exactly the paper's eq:diff-2 with its noise term ``sigma_t eta_vec`` dropped (the paper
calls that noise *vector* eta and sets it to zero in adaptation). ``eta = 0``: DDIM's step, which re-noises
x0_hat with the same predicted noise.

Shapes: ``x`` tensors are batched ``(B, D)``; ``t`` is a Python ``int`` (one step for the whole batch, as in
sampling loops) or, in ``add_noise``/``predict_x0``, an integer tensor ``(B,)`` (one step per sample, as in
training). All quantities are dimensionless (x is z-scored).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from ..errors import BodySchemaInputError

TimeStep = int | torch.Tensor
SPACINGS = ("quad", "linspace", "trailing")  # strided timestep lists, see NoiseSchedule.timesteps
PREDICTIONS = ("eps", "x0", "v")  # what the network outputs, see the module doc


def check_prediction(prediction) -> str:
    """``prediction`` if it is one of ``PREDICTIONS``; else a ``BodySchemaInputError`` naming the allowed ones."""
    if prediction not in PREDICTIONS:
        raise BodySchemaInputError(f"unknown prediction {prediction!r}; allowed: {list(PREDICTIONS)}")
    return prediction


@dataclass(frozen=True)
class OutputAffine:
    """At one step: ``x0_hat = (x0_x x_t + x0_out out) / x0_div`` and ``eps_hat = (eps_x x_t + eps_out out) /
    eps_div`` for the network output ``out``. Floats (from the float64 buffers) or broadcastable tensors."""

    x0_x: object
    x0_out: object
    x0_div: object
    eps_x: object
    eps_out: object
    eps_div: object

    def x0_coefficients(self) -> tuple[float, float]:
        """(a, b) with x0_hat = a x_t + b out (floats)."""
        inv = 1.0 / self.x0_div
        return self.x0_x * inv, self.x0_out * inv

    def eps_coefficients(self) -> tuple[float, float]:
        """(a, b) with eps_hat = a x_t + b out (floats)."""
        inv = 1.0 / self.eps_div
        return self.eps_x * inv, self.eps_out * inv


# prediction -> OutputAffine from (s0, s1) = (sqrt(abar_t), sqrt(1 - abar_t)): the ONE table of conversions
_AFFINE = {"eps": lambda s0, s1: OutputAffine(1.0, -s1, s0, 0.0, 1.0, 1.0),  # eq:diff-1; eps_hat = out
           "x0": lambda s0, s1: OutputAffine(0.0, 1.0, 1.0, 1.0, -s0, s1),  # x0_hat = out
           "v": lambda s0, s1: OutputAffine(s0, -s1, 1.0, s1, s0, 1.0)}  # v = s0 eps - s1 x0


def _affine(a, x: torch.Tensor, b, out: torch.Tensor, div) -> torch.Tensor:
    """(a x + b out) / div, skipping the terms a Python 0 or 1 makes trivial (so eps_hat IS the eps output)."""
    trivial = lambda c, v: isinstance(c, float) and c == v  # noqa: E731
    value = out if trivial(b, 1.0) else b * out
    if not trivial(a, 0.0):
        value = a * x + value if not trivial(a, 1.0) else x + value
    return value if trivial(div, 1.0) else value / div


class NoiseSchedule(nn.Module):
    """Linear beta schedule over ``n_timesteps`` steps, with its derived buffers.

    ``betas = linspace(beta_start * s, beta_end * s, T)`` with ``s = 1000 / T`` when
    ``rescale_to_1000`` (default). Why: the usual range 1e-4..0.02 was tuned for T = 1000; over the
    paper's T = 200 it leaves ``alpha_bar_{T-1} ~ 0.13``, so ``x_T`` still holds a third of the data
    and sampling from N(0, I) starts off-distribution. Rescaling keeps the sum of betas (the total
    noise "budget") of the T = 1000 schedule: for T = 200, betas run 5e-4..0.1 and
    ``alpha_bar_{T-1} ~ 3e-5`` (x_T is noise), while ``alpha_bar_0 = 0.9995`` (x_0 is data).
    With rescaling, T must exceed ``1000 * beta_end`` (= 20 for the defaults) so every beta < 1.

    Buffers (float64, non-persistent: they are a pure function of the constructor arguments, so
    checkpoints do not carry them; coefficients are cast to the input's dtype on use):
    ``betas, alphas, alpha_bars, sqrt_alphas, sqrt_alpha_bars, sqrt_one_minus_alpha_bars``, each ``(T,)``.
    Index ``t`` runs 0..T-1; ``t = T-1`` is the noisiest step.
    """

    def __init__(self, n_timesteps: int = 200, beta_start: float = 1e-4, beta_end: float = 0.02,
                 rescale_to_1000: bool = True):
        super().__init__()
        if isinstance(n_timesteps, bool) or not isinstance(n_timesteps, int) or n_timesteps <= 1:
            raise BodySchemaInputError(f"n_timesteps={n_timesteps!r} must be an integer > 1")
        scale = 1000.0 / n_timesteps if rescale_to_1000 else 1.0
        lo, hi = beta_start * scale, beta_end * scale
        if not (0.0 < lo <= hi < 1.0):
            raise BodySchemaInputError(
                f"betas from {lo:g} to {hi:g} (beta_start={beta_start!r}, beta_end={beta_end!r}, "
                f"n_timesteps={n_timesteps}, rescale_to_1000={rescale_to_1000}) must satisfy "
                f"0 < beta_start <= beta_end < 1; with rescaling use n_timesteps > {1000 * beta_end:g}")
        self.n_timesteps = n_timesteps
        betas = torch.linspace(lo, hi, n_timesteps, dtype=torch.float64)
        alphas = 1.0 - betas
        alpha_bars = torch.cumprod(alphas, dim=0)
        for name, value in (("betas", betas), ("alphas", alphas), ("alpha_bars", alpha_bars),
                            ("sqrt_alphas", alphas.sqrt()), ("sqrt_alpha_bars", alpha_bars.sqrt()),
                            ("sqrt_one_minus_alpha_bars", (1.0 - alpha_bars).sqrt())):
            self.register_buffer(name, value, persistent=False)

    def extra_repr(self) -> str:
        return (f"n_timesteps={self.n_timesteps}, beta=[{self.betas[0].item():.3g}, {self.betas[-1].item():.3g}], "
                f"alpha_bar_T={self.alpha_bars[-1].item():.2e}")

    # ---------------------------------------------------------------- helpers
    def _check_t(self, t: TimeStep, name: str = "t", allow_minus_one: bool = False) -> None:
        """Reject out-of-range steps: a tensor index of -1 would silently wrap to T-1."""
        lo = -1 if allow_minus_one else 0
        allowed = f"{lo}..{self.n_timesteps - 1}"
        if isinstance(t, torch.Tensor):
            if t.dtype.is_floating_point or t.dtype.is_complex or t.dtype == torch.bool:
                raise BodySchemaInputError(f"{name} has dtype {t.dtype}; use an int or an integer tensor in {allowed}")
            if t.numel() and (int(t.min()) < lo or int(t.max()) >= self.n_timesteps):
                raise BodySchemaInputError(
                    f"{name} has values in {int(t.min())}..{int(t.max())}; allowed is {allowed}")
        elif isinstance(t, bool) or not isinstance(t, int) or not lo <= t < self.n_timesteps:
            raise BodySchemaInputError(f"{name}={t!r} must be an int in {allowed}")

    @staticmethod
    def _gather(buf: torch.Tensor, t: TimeStep, like: torch.Tensor) -> torch.Tensor:
        """``buf[t]`` shaped to broadcast against ``like`` (B, ...): a 0-d tensor or (B, 1, ...)."""
        coef = buf[t].to(dtype=like.dtype, device=like.device)
        if isinstance(t, torch.Tensor) and t.ndim > 0:
            coef = coef.reshape(coef.shape + (1,) * (like.ndim - coef.ndim))
        return coef

    # ---------------------------------------------------------------- processes
    def add_noise(self, x0: torch.Tensor, eps: torch.Tensor, t: TimeStep, check: bool = True) -> torch.Tensor:
        """Forward process (paper II-C): ``x_t = sqrt(abar_t) x0 + sqrt(1 - abar_t) eps``.

        x0, eps: (B, D) clean data and unit Gaussian noise; t: int or (B,). Returns x_t (B, D).
        check=False skips the range check of t (two reductions and syncs): for callers whose t is valid by
        construction, e.g. training's ``randint(0, T)`` on every minibatch.
        """
        if check:
            self._check_t(t)
        return self._gather(self.sqrt_alpha_bars, t, x0) * x0 + self._gather(self.sqrt_one_minus_alpha_bars, t, x0) * eps

    def output_affine(self, t: int, prediction: str = "eps") -> OutputAffine:
        """The conversion of the network's output at step ``t`` (an int) into x0_hat and eps_hat (float
        coefficients): what the fused sampler folds into its plan."""
        self._check_t(t)
        abar = float(self.alpha_bars[t])
        return _AFFINE[check_prediction(prediction)](math.sqrt(abar), math.sqrt(1.0 - abar))

    def split_output(self, output: torch.Tensor, x_t: torch.Tensor, t: TimeStep,
                     prediction: str = "eps") -> tuple[torch.Tensor, torch.Tensor]:
        """(x0_hat, eps_hat), each (B, D), from the network's ``output`` (B, D) at ``x_t`` (B, D) and step t (int or
        (B,)): THE conversion every sampler path uses (``output_affine``'s coefficients, as tensors for a (B,) t)."""
        aff = self._affine_at(t, prediction, x_t)
        return (_affine(aff.x0_x, x_t, aff.x0_out, output, aff.x0_div),
                _affine(aff.eps_x, x_t, aff.eps_out, output, aff.eps_div))

    def _affine_at(self, t: TimeStep, prediction: str, like: torch.Tensor) -> OutputAffine:
        self._check_t(t)
        if isinstance(t, torch.Tensor):
            s0, s1 = self._gather(self.sqrt_alpha_bars, t, like), self._gather(self.sqrt_one_minus_alpha_bars, t, like)
            return _AFFINE[check_prediction(prediction)](s0, s1)
        return self.output_affine(t, prediction)

    def predict_x0(self, x_t: torch.Tensor, output: torch.Tensor, t: TimeStep, prediction: str = "eps") -> torch.Tensor:
        """x0_hat from the network's ``output`` (``split_output``); for eps, eq:diff-1:
        ``x0_hat = (x_t - sqrt(1 - abar_t) eps_hat) / sqrt(abar_t)`` (exact inverse of add_noise).

        Note d x0_hat / d x_t ~ 1/sqrt(abar_t) for eps: large at t = T-1 (why the paper's guidance step with a fixed
        lr diverges early in SI units; docs/design.md, "Guidance step").
        """
        return self.split_output(output, x_t, t, prediction)[0]

    def training_target(self, x0: torch.Tensor, eps: torch.Tensor, t: TimeStep, prediction: str = "eps"):
        """What the network is trained to output at ``add_noise(x0, eps, t)``: eps, x0, or
        v = sqrt(abar_t) eps - sqrt(1 - abar_t) x0. x0, eps (B, D); t int or (B,) (not range-checked)."""
        if check_prediction(prediction) == "eps":
            return eps
        if prediction == "x0":
            return x0
        return self._gather(self.sqrt_alpha_bars, t, x0) * eps - self._gather(self.sqrt_one_minus_alpha_bars, t, x0) * x0

    def min_snr_weight(self, t: torch.Tensor, gamma: float, prediction: str = "eps") -> torch.Tensor:
        """Min-SNR-gamma loss weight (Hang et al. 2023) per sample, (B,), for steps ``t`` (B,): with
        SNR_t = abar_t / (1 - abar_t), min(SNR_t, gamma) / SNR_t for eps, min(SNR_t, gamma) for x0 and
        min(SNR_t, gamma) / (SNR_t + 1) for v (each the x0-error weight min(SNR_t, gamma) in the type's own units)."""
        abar = self.alpha_bars[t]
        snr = abar / (1.0 - abar)
        clipped = snr.clamp(max=float(gamma))
        divisor = {"eps": snr, "x0": torch.ones_like(snr), "v": snr + 1.0}[check_prediction(prediction)]
        return clipped / divisor

    def step_coefficients(self, t: int, t_prev: int, eta: float = 1.0) -> tuple[float, float]:
        """(cx, ce) of the deterministic update ``x_t' = cx x_t + ce eps_hat`` from t to t_prev (-1: the data).

        ``x_t' = sqrt(abar') x0_hat + sqrt(1 - abar' - sigma^2) eps_hat`` with x0_hat from eq:diff-1 and
        ``sigma^2 = eta^2 (1 - abar') / (1 - abar_t) (1 - abar_t / abar')`` (abar' = abar_{t_prev}, 1 for -1), so
        ``cx = sqrt(abar' / abar_t)`` and ``ce = sqrt(1 - abar' - sigma^2) - cx sqrt(1 - abar_t)``. Plain floats
        from the float64 buffers: every sampler, eager, fused or compiled, uses these two numbers.
        """
        self._check_t(t)
        self._check_t(t_prev, "t_prev", allow_minus_one=True)
        if t_prev >= t:
            raise BodySchemaInputError(f"t_prev={t_prev} must be smaller than t={t} (denoising runs backwards)")
        if not 0.0 <= float(eta) <= 1.0:
            raise BodySchemaInputError(f"eta={eta!r} must be in [0, 1] (0: DDIM, 1: the DDPM posterior mean)")
        abar = float(self.alpha_bars[t])
        abar_prev = float(self.alpha_bars[t_prev]) if t_prev >= 0 else 1.0
        sigma2 = eta ** 2 * (1.0 - abar_prev) / (1.0 - abar) * (1.0 - abar / abar_prev)
        s0, s1 = math.sqrt(abar), math.sqrt(1.0 - abar)
        return math.sqrt(abar_prev) / s0, math.sqrt(max(0.0, 1.0 - abar_prev - sigma2)) - math.sqrt(abar_prev) * s1 / s0

    def step(self, x_t: torch.Tensor, output: torch.Tensor, t: int, t_prev: int, eta: float = 1.0,
             prediction: str = "eps") -> torch.Tensor:
        """The deterministic update x_t -> x_{t_prev} (``step_coefficients``) from the network's ``output`` at x_t
        (eps_hat by ``split_output``); eta = 1 and t_prev = t - 1 is eq:diff-2 without its noise term, and at
        t = 0 -> -1 the result is x0_hat."""
        cx, ce = self.step_coefficients(t, t_prev, eta)
        aff = self._affine_at(t, prediction, x_t)
        eps_hat = _affine(aff.eps_x, x_t, aff.eps_out, output, aff.eps_div)
        # 1. eq:diff-1 and 2. the re-noising to t_prev, folded into one linear combination of x_t and eps_hat
        return cx * x_t + ce * eps_hat

    def timesteps(self, n_steps: int, spacing: str = "quad") -> list[int]:
        """``n_steps`` distinct descending steps from T-1 for a strided sampler.

        ``"quad"``: t_i = (T-1) (1 - i/(n-1))^2 rounded, dense at low noise where guidance settles the command,
        ending at t = 0; ``"linspace"``: evenly from T-1 to 0; ``"trailing"`` (Lin et al. 2024): T-1, T-1-T/n, ...,
        ending at T/n - 1. With n = T all three are T-1, ..., 0. "trailing" never reaches t = 0, so its last
        guidance step acts where x0_hat is still blurred; how far each spacing leaves a fault: BENCHMARKS.md,
        "Spacing".
        """
        T = self.n_timesteps
        if isinstance(n_steps, bool) or not isinstance(n_steps, int) or not 1 <= n_steps <= T:
            raise BodySchemaInputError(f"n_steps={n_steps!r} must be an int in 1..{T} (n_timesteps)")
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
