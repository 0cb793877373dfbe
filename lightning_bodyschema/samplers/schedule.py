"""DDPM noise schedule and deterministic update rules (paper section II-C and III-C).

Modelled on diffusers' ``scheduling_ddpm.py`` but kept to what the body schema needs: one linear
beta schedule, the forward (noising) process, ``x0`` prediction (eq:diff-1), the deterministic DDPM
mean step (eq:diff-2 with eta = 0) and a strided DDIM step (eta = 0) for fast adaptation.
The guidance step eq:diff-adapt is *not* here: it needs a loss and a model, and this module imports
neither (DESIGN §1). A sampler calls ``predict_x0`` -> its own guidance -> ``ddpm_mean_step``.

Shapes: ``x`` tensors are batched ``(B, D)`` (any trailing dims work); ``t`` is a Python ``int``
(same step for the whole batch, the fast path in sampling loops) or an integer tensor ``(B,)``
(one step per sample, as in training). All quantities are dimensionless (x is z-scored).
"""
from __future__ import annotations

import torch
from torch import nn

from ..errors import BodySchemaInputError

TimeStep = int | torch.Tensor


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

    def _alpha_bar_prev(self, t_prev: TimeStep, like: torch.Tensor) -> torch.Tensor:
        """alpha_bar at ``t_prev``; ``t_prev = -1`` means "the clean data", alpha_bar = 1."""
        if not isinstance(t_prev, torch.Tensor):
            return like.new_tensor(1.0) if t_prev < 0 else self._gather(self.alpha_bars, t_prev, like)
        abar = self._gather(self.alpha_bars, t_prev.clamp_min(0), like)
        is_data = (t_prev < 0).to(like.device).reshape(abar.shape)  # same (B, 1, ...) layout as abar
        return torch.where(is_data, torch.ones_like(abar), abar)

    # ---------------------------------------------------------------- processes
    def add_noise(self, x0: torch.Tensor, eps: torch.Tensor, t: TimeStep) -> torch.Tensor:
        """Forward process (paper II-C): ``x_t = sqrt(abar_t) x0 + sqrt(1 - abar_t) eps``.

        x0, eps: (B, D) clean data and unit Gaussian noise; t: int or (B,). Returns x_t (B, D).
        """
        self._check_t(t)
        return self._gather(self.sqrt_alpha_bars, t, x0) * x0 + self._gather(self.sqrt_one_minus_alpha_bars, t, x0) * eps

    def predict_x0(self, x_t: torch.Tensor, eps_hat: torch.Tensor, t: TimeStep) -> torch.Tensor:
        """eq:diff-1: ``x0_hat = (x_t - sqrt(1 - abar_t) eps_hat) / sqrt(abar_t)`` (exact inverse of add_noise).

        Note d x0_hat / d x_t ~ 1/sqrt(abar_t): up to ~180x at t = T-1 for T = 200 (why a literal
        guidance lr on x0_hat diverges early, DESIGN §5).
        """
        self._check_t(t)
        return (x_t - self._gather(self.sqrt_one_minus_alpha_bars, t, x_t) * eps_hat) / self._gather(self.sqrt_alpha_bars, t, x_t)

    def ddpm_mean_step(self, x_t: torch.Tensor, eps_hat: torch.Tensor, t: TimeStep) -> torch.Tensor:
        """eq:diff-2 with eta = 0 (no noise injected): one deterministic step t -> t-1.

        ``x_{t-1} = (x_t - (1 - a_t) / sqrt(1 - abar_t) eps_hat) / sqrt(a_t)``. At t = 0 the result is
        x0_hat exactly (abar_0 = a_0). Given the true noise of x_t this lands on
        ``sqrt(abar_{t-1}) x0 + sqrt(a_t) (1 - abar_{t-1}) / sqrt(1 - abar_t) eps``: the DDPM posterior
        mean, whose noise share is *smaller* than the DDIM step's ``sqrt(1 - abar_{t-1})``.
        """
        self._check_t(t)
        # 1. noise coefficient (1 - a_t) / sqrt(1 - abar_t) = beta_t / sqrt(1 - abar_t)
        c_eps = self._gather(self.betas, t, x_t) / self._gather(self.sqrt_one_minus_alpha_bars, t, x_t)
        # 2. remove the predicted noise share and rescale by 1 / sqrt(a_t)   (eq:diff-2)
        return (x_t - c_eps * eps_hat) / self._gather(self.sqrt_alphas, t, x_t)

    def ddim_step(self, x_t: torch.Tensor, eps_hat: torch.Tensor, t: TimeStep, t_prev: TimeStep) -> torch.Tensor:
        """Deterministic DDIM step (eta = 0) from t to any earlier ``t_prev`` (``-1`` returns x0_hat).

        ``x_{t_prev} = sqrt(abar_prev) x0_hat + sqrt(1 - abar_prev) eps_hat``: re-noise the current
        clean estimate to the earlier level with the *same* noise, so a few strided steps suffice.
        t, t_prev: ints or (B,) tensors with t_prev < t (not checked per element).
        """
        self._check_t(t_prev, "t_prev", allow_minus_one=True)
        if not isinstance(t, torch.Tensor) and not isinstance(t_prev, torch.Tensor) and t_prev >= t:
            raise BodySchemaInputError(f"t_prev={t_prev} must be smaller than t={t} (denoising runs backwards)")
        # 1. clean estimate from the predicted noise (eq:diff-1); validates t
        x0_hat = self.predict_x0(x_t, eps_hat, t)
        # 2. re-noise it to level t_prev with the same eps (DDIM, eta = 0)
        abar_prev = self._alpha_bar_prev(t_prev, x_t)
        return abar_prev.sqrt() * x0_hat + (1.0 - abar_prev).sqrt() * eps_hat

    def timesteps(self, n_steps: int) -> torch.Tensor:
        """Strided descending steps for a sampling loop, LongTensor (n_steps,) on the buffers' device.

        "Trailing" spacing (Lin et al. 2024): always starts at T-1 (pure noise) and spaces by T/n,
        e.g. T = 200, n = 20 -> 199, 189, ..., 9; n = T -> T-1, ..., 0. Pair each t with the next
        entry as ``t_prev`` and use ``t_prev = -1`` after the last one (``ddim_step`` then returns x0).
        Loop with ``for t in ts.tolist()`` so each step takes the fast int path.
        """
        if isinstance(n_steps, bool) or not isinstance(n_steps, int) or not 1 <= n_steps <= self.n_timesteps:
            raise BodySchemaInputError(f"n_steps={n_steps!r} must be an int in 1..{self.n_timesteps} (n_timesteps)")
        T = self.n_timesteps
        steps = [round(T - i * T / n_steps) - 1 for i in range(n_steps)]
        return torch.tensor(steps, dtype=torch.long, device=self.betas.device)
