"""Gradient-guided denoising (paper section III-C) and latent-space optimization (section III-B).

Update rules only: the networks, the loss and the schedule come in as arguments; no Lightning.
Everything is batched over cases: one tensor op per step for all cases, each case its own loss.

Two implementations of each loop compute the same maths:

* the *reference* path (``fast=False``): autograd through the network and the loss, literally
  eq:diff-1 -> eq:diff-adapt -> eq:diff-2 with the schedule's own update functions;
* the *fast* path (``fast=True``): no autograd. The loss gradient comes from ``loss_fn.grad_x0`` when
  the loss carries one (``BoxPenalty``: the adaptation loss is a sum of squared distances to per-element
  intervals, so its gradient is ``2 w (x - clamp(x, lo, hi))``), else from autograd on the loss alone.
  For an MLP eps-model with ``bind`` (``networks.EpsMLP``) the loop is fused (``_fused_loop``): the
  t/q part of the first layer is computed once for all steps, the backward pass is hand-written, and
  every schedule coefficient is folded into small per-step matrices, so a guided evaluation is 15
  tensor ops, run under ``torch.inference_mode``. Other models take ``_generic_loop`` (their
  ``eps_and_vjp``, or autograd through the network). At batch 1 each tensor op costs ~2 us of
  dispatch on the project's CPU, so the fast path is mostly about doing fewer of them.
  Returns the same commands as the reference (tests/test_fast_paths.py: 1e-5 in float64, ~1e-12 measured).
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Callable, Optional, Sequence

import numpy as np
import torch

from ..errors import BodySchemaInputError

LossFn = Callable[[torch.Tensor], torch.Tensor]  # normalized x0 (B, D) -> loss per case (B,)
# the fast loops run under torch.inference_mode (tools/bench_adaptation.py --ablation turns it off)
_INFERENCE_MODE = True


@dataclass(frozen=True)
class GuidanceConfig:
    """How eq:diff-adapt scales its step.

    lr: C_lr^adapt. step_scale: the factor s_t multiplying the step at noise level t:
      ``"none"``   s_t = 1           the paper as printed (diverges early in SI units, DESIGN §5);
      ``"sqrt_abar"`` s_t = sqrt(abar_t)  damps the noisy steps by the x0_hat sensitivity (DESIGN §5's fix);
      ``"abar"``   s_t = abar_t      x0_hat moves by -lr * grad_{x0} L at every t, whatever the noise level
                                     (d x0_hat / d x_t ~ 1/sqrt(abar_t) cancels: a Newton-like step in x0).
    n_guide: guidance steps per timestep (eq:diff-adapt repeated, eps re-predicted at the updated x_t;
      the denoising step then uses the eps of the last one). 1 is the paper's.
    min_abar: guide only the steps with abar_t >= min_abar (0, the paper's: every step). With
      ``step_scale="abar"`` a step at noise level t moves x_t by only ~lr sqrt(abar_t) |grad_x0 L| and the
      following denoising washes it out: on the paper checkpoint, guiding only where abar_t >= 0.5
      (signal variance >= noise variance) changed no feasible-case median by more than 2 % (BENCHMARKS.md).
    """

    lr: float = 0.01
    step_scale: str = "none"
    n_guide: int = 1
    min_abar: float = 0.0


def _step_scale(schedule, t: int, mode: str) -> float:
    if mode == "none":
        return 1.0
    if mode == "abar":
        return float(schedule.alpha_bars[t])
    if mode == "sqrt_abar":
        return float(schedule.sqrt_alpha_bars[t])
    raise BodySchemaInputError(f"unknown step_scale {mode!r}; allowed: 'none', 'sqrt_abar', 'abar'")


def _check_guidance(guidance: GuidanceConfig):
    if guidance.step_scale not in ("none", "abar", "sqrt_abar"):
        raise BodySchemaInputError(f"unknown step_scale {guidance.step_scale!r}; allowed: 'none', 'sqrt_abar', 'abar'")
    if isinstance(guidance.n_guide, bool) or not isinstance(guidance.n_guide, int) or guidance.n_guide < 1:
        raise BodySchemaInputError(f"n_guide={guidance.n_guide!r} must be an integer >= 1")


def guided_denoise(eps_model, schedule, q_n: torch.Tensor, x_T: torch.Tensor, loss_fn: Optional[LossFn],
                   guidance: GuidanceConfig = GuidanceConfig(), timesteps: Optional[Sequence[int]] = None,
                   fast: bool = False, eta: Optional[float] = None, compiled: bool = False):
    """Deterministic denoising from x_T, guided by ``loss_fn`` on the predicted x0 at every step.

    ``timesteps``: descending steps; None runs all T steps. ``loss_fn=None`` gives the unguided sample.
    ``eta``: which deterministic update joins consecutive steps t -> t' (see ``deterministic_step``):
    1 the posterior mean (for t' = t - 1 exactly the DDPM mean step eq:diff-2), 0 DDIM; None: 1 for
    all T steps (the paper's), 0 for strided steps.
    ``fast``: the autograd-free path (see the module docstring); needs ``eps_model.bind`` or
    ``eps_model.eps_and_vjp`` (else it falls back to autograd per step) and uses ``loss_fn.grad_x0`` when
    present (else autograd on the loss alone).
    ``compiled``: with ``fast``, run the fused loop through ``torch.compile`` (``compiled_core``); cases the
    fused loop does not cover (see ``_fast_denoise``) run the eager fast path.
    Returns x0 (B, D) (rows may be non-finite if guidance diverged: the caller checks).
    """
    _check_guidance(guidance)
    steps = list(range(schedule.n_timesteps - 1, -1, -1)) if timesteps is None else [int(t) for t in timesteps]
    if eta is None:
        eta = 0.0 if timesteps is not None and len(steps) < schedule.n_timesteps else 1.0
    if not 0.0 <= float(eta) <= 1.0:
        raise BodySchemaInputError(f"eta={eta!r} must be in [0, 1] (0: DDIM, 1: the DDPM posterior mean)")
    if fast:
        return _fast_denoise(eps_model, schedule, q_n, x_T, loss_fn, guidance, steps, float(eta), compiled)
    if compiled:
        raise BodySchemaInputError("compiled=True needs the fast path (fast=True)")
    x = x_T
    for i, t in enumerate(steps):
        if loss_fn is None:
            with torch.no_grad():
                eps = eps_model(x, t, q_n)
        else:
            n_guide = guidance.n_guide if float(schedule.alpha_bars[t]) >= guidance.min_abar else 0
            if n_guide == 0:
                with torch.no_grad():
                    eps = eps_model(x, t, q_n)
            for _ in range(n_guide):
                x, eps = _guide(eps_model, schedule, q_n, x, t, loss_fn, guidance)
        with torch.no_grad():
            t_prev = steps[i + 1] if i + 1 < len(steps) else -1
            # 3. eq:diff-2 (eta = 1, one step) or its strided / DDIM form, with the eps computed before guidance
            x = deterministic_step(schedule, x, eps, t, t_prev, eta)
    return x


def deterministic_step(schedule, x_t: torch.Tensor, eps: torch.Tensor, t: int, t_prev: int, eta: float) -> torch.Tensor:
    """x_t -> x_{t_prev} without noise: ``sqrt(abar') x0_hat + sqrt(1 - abar' - sigma^2) eps`` (DDIM's step
    with its noise term left out), ``sigma^2 = eta^2 (1 - abar') / (1 - abar_t) (1 - abar_t / abar')``,
    abar' = abar_{t_prev} (1 for t_prev = -1).

    eta = 0: DDIM (``schedule.ddim_step``). eta = 1: the mean of the DDPM posterior q(x_{t'} | x_t, x0_hat);
    for t_prev = t - 1 it is exactly the paper's deterministic DDPM step eq:diff-2 (``ddpm_mean_step``),
    and for larger strides it keeps that sampler's character (it shrinks the noise share faster than DDIM).
    """
    if eta == 0.0:
        return schedule.ddim_step(x_t, eps, t, t_prev)
    if eta == 1.0 and t_prev == t - 1:
        return schedule.ddpm_mean_step(x_t, eps, t)
    abar, abar_prev = float(schedule.alpha_bars[t]), (float(schedule.alpha_bars[t_prev]) if t_prev >= 0 else 1.0)
    sigma2 = eta ** 2 * (1.0 - abar_prev) / (1.0 - abar) * (1.0 - abar / abar_prev)
    x0_hat = schedule.predict_x0(x_t, eps, t)
    return math.sqrt(abar_prev) * x0_hat + math.sqrt(max(0.0, 1.0 - abar_prev - sigma2)) * eps


def _guide(eps_model, schedule, q_n, x_t, t, loss_fn, guidance):
    """One guidance step at t: returns the guided x_t and the eps predicted before it."""
    x_t = x_t.detach().requires_grad_(True)
    with torch.enable_grad():
        eps = eps_model(x_t, t, q_n)
        # 1. eq:diff-1: x0_hat = (x_t - sqrt(1 - abar_t) eps) / sqrt(abar_t)
        x0_hat = schedule.predict_x0(x_t, eps, t)
        # 2. eq:diff-adapt: x_t <- x_t - C_lr s_t grad_{x_t} L(x0_hat)   (cases are independent: sum)
        grad, = torch.autograd.grad(loss_fn(x0_hat).sum(), x_t)
    scale = guidance.lr * _step_scale(schedule, t, guidance.step_scale)
    return (x_t - scale * grad).detach(), eps.detach()


# ---------------------------------------------------------------------------------------------- fast path
@functools.lru_cache(maxsize=64)
def _coefficients(alpha_bars: tuple, steps: tuple, eta: float, lr: float, step_scale: str, n_guide: int,
                  min_abar: float):
    """Per step, plain floats computed in float64 once per (schedule, steps, eta, guidance):

    the literal form ``x0 = (x - s1 eps) / s0``, ``x -= k (g - s1 J^T g)``, ``x_prev = cx x + ce eps``
    (s0, s1 = sqrt(abar_t), sqrt(1 - abar_t); k = lr s_t / s0 since grad_{x_t} L = (g - s1 J^T g) / s0;
    cx, ce: ``deterministic_step`` to the next t), and its fused form (``_fused_loop``): with
    eps = (x - s0 x0) / s1 the guided update plus denoising step is
    ``x_prev = A x + Bc x0 + C g + D (J^T g)`` with A = cx + ce / s1, Bc = -ce s0 / s1, C = -cx k,
    D = cx k s1 (and A s0 + Bc = cx s0 = sqrt(abar_prev)).
    Each entry: (n_guide at this step, s1, 1/s0, k, cx, ce, Bc, C, D).
    """
    out = []
    for i, t in enumerate(steps):
        abar = alpha_bars[t]
        s0, s1 = math.sqrt(abar), math.sqrt(1.0 - abar)
        scale = {"none": 1.0, "abar": abar, "sqrt_abar": s0}[step_scale]
        k = lr * scale / s0
        abar_prev = alpha_bars[steps[i + 1]] if i + 1 < len(steps) else 1.0
        sigma2 = eta ** 2 * (1.0 - abar_prev) / (1.0 - abar) * (1.0 - abar / abar_prev)
        cx = math.sqrt(abar_prev) / s0
        ce = math.sqrt(max(0.0, 1.0 - abar_prev - sigma2)) - math.sqrt(abar_prev) * s1 / s0
        out.append((n_guide if abar >= min_abar else 0, s1, 1.0 / s0, k, cx, ce, -ce * s0 / s1, -cx * k, cx * k * s1))
    return tuple(out)


def _schedule_key(schedule) -> tuple:
    """alpha_bar as a tuple of floats (the ``_coefficients`` cache key), recomputed when the buffer changes
    (``.to()``/``.float()`` replace it; the entry holds the old one, so its address is not reused)."""
    abar = schedule.alpha_bars
    cached = schedule.__dict__.get("_abar_tuple")
    if cached is None or cached[0] is not abar or cached[1] != abar._version:
        cached = (abar, abar._version, tuple(abar.tolist()))
        schedule.__dict__["_abar_tuple"] = cached
    return cached[2]


def _autograd_loss_grad(loss_fn: LossFn) -> Callable[[torch.Tensor], torch.Tensor]:
    """dL/dx0 by autograd on the loss alone (for losses without an analytic ``grad_x0``)."""
    def grad(x0):
        with torch.enable_grad():
            x = x0.detach().requires_grad_(True)
            g, = torch.autograd.grad(loss_fn(x).sum(), x)
        return g
    return grad


def loss_gradient(loss_fn: LossFn) -> Callable[[torch.Tensor], torch.Tensor]:
    """``loss_fn.grad_x0`` when the loss carries an analytic gradient, else autograd on the loss alone."""
    grad = getattr(loss_fn, "grad_x0", None)
    return grad if grad is not None else _autograd_loss_grad(loss_fn)


def _fast_denoise(eps_model, schedule, q_n, x_T, loss_fn, guidance, steps, eta, compiled=False):
    coefs = _coefficients(_schedule_key(schedule), tuple(steps), eta, float(guidance.lr), guidance.step_scale,
                          guidance.n_guide if loss_fn is not None else 0, float(guidance.min_abar))
    x = x_T.detach().clone()
    box = None if loss_fn is None else getattr(loss_fn, "box_penalty", None)
    bound = eps_model.bind(q_n, steps) if hasattr(eps_model, "bind") else None
    if bound is not None and (loss_fn is None or (box is not None and len(box.slots) == 1)):
        # inference mode: no version counters or autograd bookkeeping (~0.15 us per op at batch 1); the
        # clone makes the result an ordinary tensor again
        with torch.inference_mode(_INFERENCE_MODE):
            out = _fused_loop(bound.frozen, bound.stacked_biases, x, coefs, box, compiled)
        return out.clone()
    # not fusable (another eps model, a loss with overlapping boxes or no analytic gradient): eager, compiled or not
    return _generic_loop(eps_model, q_n, steps, x, coefs, None if loss_fn is None else loss_gradient(loss_fn))


def _fused_loop(net, biases, x, coefs, box, compiled: bool = False):
    """The loop for an MLP eps-model (``FrozenMLP`` blocks) and a one-slot ``BoxPenalty`` (or no guidance).

    It carries the state u = x_t / sqrt(abar_t), in which x0_hat = u + e with e = -(s1/s0) eps, and folds
    every schedule coefficient into small per-step matrices (``_fused_plan``, cached per schedule,
    guidance and weights) rather than scalar arguments: at batch 1 an op's dispatch costs ~2 us and an
    ``alpha=``/``beta=`` argument ~1 us more. Same maths as the reference (tested to 1e-5 in float64).
    Per guided evaluation: 2 x (addmm + SiLU), e and x0 (2 ops), residual (2), backward pass
    (2 x (mm + SiLU backward)), update (3 or 2): 15 tensor ops, 2 with a scalar argument. Unguided: 6.
    ``biases``: the first-layer bias of every step, (S, B, H). ``compiled``: run ``_fused_core`` through
    ``torch.compile`` (``compiled_core``) on the stacked plan.
    """
    uniform = None if box is None else box.uniform_weight
    plan = _fused_plan(net, coefs, 1.0 if uniform is None else uniform)
    w2 = lo = hi = None
    if box is not None:
        w2, lo, hi = box.slots[0]
        w2 = w2 if uniform is None else None
    if compiled:
        matrices, scalars = _stacked_plan(net, plan)
        return compiled_core()(matrices, scalars, biases, x, lo, hi, w2, *net.traceable_act, net.silu)
    hidden = [(w_t, b) for w_t, _, b in net.hidden]
    hidden_back = [w for _, w, _ in reversed(net.hidden)]
    return _fused_core_buffered(plan, biases.unbind(0), x, lo, hi, w2, hidden, hidden_back, net.act_out,
                                net.act_backward_out, net.silu)


def _fused_core(plan, biases, x, lo, hi, w2, hidden, hidden_back, act, act_backward, silu: bool):
    """``_fused_loop``'s arithmetic on plain tensors and floats (what ``torch.compile`` traces)."""
    addmm, add, mm = torch.addmm, torch.add, torch.mm
    u = x * plan[0][1]  # x_T / sqrt(abar_T)
    for bias, (n_guide, _, w1_t, beta, w_e, w_r, w_g, a_e, a_r, w_k, k_r) in zip(biases, plan):
        if n_guide == 0:  # eq:diff-2 / DDIM without guidance: u' = u + beta' + h W'
            h = act(addmm(bias, u, w1_t))
            for w_t, b in hidden:
                h = act(addmm(b, h, w_t))
            u = addmm(add(u, beta), h, w_e)
            continue
        for j in range(n_guide):
            # the network's hidden layers (FrozenMLP.trunk, inlined: a Python call costs ~1 us per step)
            a = addmm(bias, u, w1_t)
            h = act(a)
            saved = [a if silu else h]
            for w_t, b in hidden:
                a = addmm(b, h, w_t)
                h = act(a)
                saved.append(a if silu else h)
            e = addmm(beta, h, w_e)  # -(s1/s0) eps
            x0 = add(u, e)  # 1. eq:diff-1: x0_hat
            r = torch.sub(x0, torch.clamp(x0, lo, hi))  # dL/dx0_hat / c
            if w2 is not None:
                r = r.mul(w2)
            # backward pass (FrozenMLP.back): J^T dL/dx0_hat = g1 W1_free, J = d eps / d x_t
            g1 = act_backward(mm(r, w_r), saved[-1])
            for w, sv in zip(hidden_back, saved[-2::-1]):
                g1 = act_backward(mm(g1, w), sv)
            if j + 1 < n_guide:  # 2. eq:diff-adapt only: x -= k (g - s1 J^T g)
                u = addmm(add(u, r, alpha=k_r), g1, w_k)
            else:  # 2. eq:diff-adapt + 3. eq:diff-2 / DDIM, in the next step's units
                u = addmm(add(u, e, alpha=a_e).add_(r, alpha=a_r), g1, w_g)
    return u


def _fused_core_buffered(plan, biases, x, lo, hi, w2, hidden, hidden_back, act, act_backward, silu: bool):
    """``_fused_core`` (same ops, same order, same results to the bit) writing every intermediate into
    buffers allocated once per call: at batch 1 an op that allocates nothing costs ~0.5 us less, ~15 % of an
    op here. Eager only (``torch.compile`` traces ``_fused_core``; out= variants and private bindings are
    opaque to it). ``act``/``act_backward``: ``FrozenMLP.act_out``/``act_backward_out``."""
    (b, d), h_dim = x.shape, plan[0][2].shape[1]
    new = x.new_empty
    n_layers = 1 + len(hidden)
    pre = [new((b, h_dim)) for _ in range(n_layers)]  # pre-activations (what SiLU's backward needs)
    post = [new((b, h_dim)) for _ in range(n_layers)]  # activations (what Tanh's backward needs)
    saved = pre if silu else post
    grads = [new((b, h_dim)) for _ in range(2 * n_layers)]
    e, x0, c, r, t = (new((b, d)) for _ in range(5))
    states = (new((b, d)), new((b, d)))  # u alternates between two buffers: addmm's out must not be an input
    addmm, mm, add = torch.addmm, torch.mm, torch.add
    u = torch.mul(x, plan[0][1], out=states[0])  # x_T / sqrt(abar_T)
    k = 0

    def forward(u, bias, w1_t):
        act(addmm(bias, u, w1_t, out=pre[0]), out=post[0])
        for i, (w_t, bh) in enumerate(hidden, start=1):
            act(addmm(bh, post[i - 1], w_t, out=pre[i]), out=post[i])
        return post[-1]

    for bias, (n_guide, _, w1_t, beta, w_e, w_r, w_g, a_e, a_r, w_k, k_r) in zip(biases, plan):
        if n_guide == 0:  # eq:diff-2 / DDIM without guidance: u' = u + beta' + h W'
            h = forward(u, bias, w1_t)
            k = 1 - k
            u = addmm(add(u, beta, out=t), h, w_e, out=states[k])
            continue
        for j in range(n_guide):
            h = forward(u, bias, w1_t)
            addmm(beta, h, w_e, out=e)  # -(s1/s0) eps
            add(u, e, out=x0)  # 1. eq:diff-1: x0_hat
            torch.sub(x0, torch.clamp(x0, lo, hi, out=c), out=r)  # dL/dx0_hat / c
            if w2 is not None:
                r.mul_(w2)
            # backward pass (FrozenMLP.back): J^T dL/dx0_hat = g1 W1_free, J = d eps / d x_t
            g1 = act_backward(mm(r, w_r, out=grads[0]), saved[-1], grad_input=grads[1])
            for i, w in enumerate(hidden_back, start=1):
                g1 = act_backward(mm(g1, w, out=grads[2 * i]), saved[-1 - i], grad_input=grads[2 * i + 1])
            k = 1 - k
            if j + 1 < n_guide:  # 2. eq:diff-adapt only: x -= k (g - s1 J^T g)
                u = addmm(add(u, r, alpha=k_r, out=t), g1, w_k, out=states[k])
            else:  # 2. eq:diff-adapt + 3. eq:diff-2 / DDIM, in the next step's units
                u = addmm(add(u, e, alpha=a_e, out=t).add_(r, alpha=a_r), g1, w_g, out=states[k])
    return u


def _stacked_fused_core(matrices, scalars, biases, x, lo, hi, w2, act, act_backward, silu: bool):
    """``_fused_core`` on the plan as a few stacked tensors (``_stacked_plan``) and Python numbers.

    What ``torch.compile`` sees: ~10 tensor inputs instead of ~200 list entries, so the guards that run on
    every call stay cheap; the indexing below is traced into free views.
    """
    w1, beta, w_e, w_r, w_g, w_k, h_w_t, h_b, h_w = matrices
    plan = [(n, inv_s0, w1[i], beta[i], w_e[i], w_r, w_g[i], a_e, a_r, w_k[i], k_r)
            for i, (n, inv_s0, a_e, a_r, k_r) in enumerate(scalars)]
    hidden = [(h_w_t[j], h_b[j]) for j in range(len(h_b))]
    hidden_back = [h_w[j] for j in range(len(h_b) - 1, -1, -1)]
    return _fused_core(plan, [biases[i] for i in range(len(scalars))], x, lo, hi, w2, hidden, hidden_back,
                       act, act_backward, silu)


def _stacked_plan(net, plan: list) -> tuple:
    """``plan`` (``_fused_plan``) as stacked (S, ...) matrices (zeros where a step has none) plus a tuple of
    per-step numbers, cached with the plan."""
    cache = net.__dict__.setdefault("_stacked_plans", {})
    hit = cache.get(id(plan))
    if hit is not None and hit[0] is plan:
        return hit[1]
    if len(cache) >= 6:
        cache.clear()

    def stack(k, like=None):  # unguided steps have no w_g, w_k (shaped like W1_free): zeros, never read
        return torch.stack([torch.zeros_like(like) if p[k] is None else p[k] for p in plan])

    w_r = next((p[5] for p in plan if p[5] is not None), net.out_w)  # the same matrix at every guided step
    if net.hidden:  # (W^T, W, b) per hidden-to-hidden layer
        hidden_w_t, hidden_w, hidden_b = (torch.stack(list(part)) for part in zip(*net.hidden))
    else:  # one hidden layer: nothing between the first layer and the output
        hidden_w_t = hidden_w = net.out_w.new_zeros((0, 1, 1))
        hidden_b = net.out_w.new_zeros((0, 1))
    matrices = (stack(2), stack(3), stack(4), w_r, stack(6, net.w1_free), stack(9, net.w1_free),
                hidden_w_t, hidden_b, hidden_w)
    scalars = tuple((p[0], p[1], p[7], p[8], p[10]) for p in plan)
    cache[id(plan)] = (plan, (matrices, scalars))
    return matrices, scalars


@functools.lru_cache(maxsize=1)
def compiled_core():
    """``_stacked_fused_core`` through ``torch.compile`` (inductor, C++ wrapper, the whole loop as one graph).

    The graph is specialised to a plan (schedule, step count, guidance) and a batch size: the first call
    for each compiles, ~20-40 s on the project's CPU (a C++ compiler is needed; inductor's on-disk cache
    makes a repeat in a new process a few seconds); later calls skip Python's per-op dispatch and fuse the
    elementwise ops. Same commands as the eager loop (tests/test_fast_paths.py, 1e-5).
    """
    return torch.compile(_stacked_fused_core, fullgraph=True, dynamic=False, options={"cpp_wrapper": True})


def _fused_plan(net, coefs: tuple, c_w: float) -> list:
    """Per-step matrices of ``_fused_loop``, cached on ``net`` (a ``FrozenMLP``, rebuilt when the weights
    change, and the plan with it).

    State u = x_t / s0 (s0 = sqrt(abar_t), s0' the next step's, 1 after the last). With the coefficients of
    ``_coefficients`` (k, cx, ce, Bc, C, D) and c_w the penalty weight (dL/dx0 = c_w r):
      first layer  x W1^T = u (s0 W1_free^T);  e = -(s1/s0) (b_out + h W_out^T),  x0_hat = u + e;
      backward     (dL/dx0) W_out = r (c_w W_out);
      guided step  u' = u + (Bc/s0') e + (C c_w/s0') r + g1 (D/s0') W1_free    (A s0 + Bc = s0' exactly);
      inner step   u <- u - (k c_w/s0) r + g1 (k s1/s0) W1_free                  (n_guide > 1, same t);
      unguided     u' = u + (ce/s0') (b_out + h W_out^T)                          (cx s0 = s0').
    Entry: (n_guide, 1/s0, W1_i, beta_i, We_i, Wr, Wg_i, Bc/s0', C c_w/s0', Wk_i, -k c_w/s0).
    """
    cache = net.__dict__.setdefault("_plans", {})
    key = (id(coefs), c_w)
    if key in cache and cache[key][0] is coefs:
        return cache[key][1]
    if len(cache) >= 6:  # a 200-step plan holds ~3.5 MB of small float32 matrices
        cache.clear()
    w1f_t, w1f, w_out_t, w_out, b_out = net.w1_free_t, net.w1_free, net.out_w_t, net.out_w, net.out_b
    w_r = c_w * w_out
    plan = []
    for n_guide, s1, inv_s0, k, cx, ce, bc, c, d in coefs:
        s0 = 1.0 / inv_s0
        s0_next = cx * s0  # sqrt(abar_prev): the update's x coefficient is sqrt(abar_prev) / s0
        if n_guide == 0:
            f = ce / s0_next
            plan.append((0, inv_s0, s0 * w1f_t, f * b_out, f * w_out_t, None, None, 0.0, 0.0, None, 0.0))
            continue
        f = -s1 * inv_s0
        plan.append((n_guide, inv_s0, s0 * w1f_t, f * b_out, f * w_out_t, w_r, (d / s0_next) * w1f,
                     bc / s0_next, c * c_w / s0_next, (k * s1 * inv_s0) * w1f, -k * c_w * inv_s0))
    cache[key] = (coefs, plan)
    return plan


def _generic_loop(eps_model, q_n, steps, x, coefs, grad_x0):
    """The loop for any eps model: ``eps_and_vjp`` if it has one, else autograd through the network."""
    for t, (n_guide, s1, inv_s0, k, cx, ce, *_) in zip(steps, coefs):
        if n_guide == 0:
            with torch.no_grad():
                eps = eps_model(x, t, q_n)
        for _ in range(n_guide):
            eps, vjp = _eps_and_vjp(eps_model, x, t, q_n)
            x0 = torch.add(x, eps, alpha=-s1).mul_(inv_s0)  # eq:diff-1
            g = grad_x0(x0)
            x = x.add_(torch.add(g, vjp(g), alpha=-s1), alpha=-k)  # eq:diff-adapt
        x = x.mul_(cx).add_(eps, alpha=ce)  # deterministic_step: eq:diff-2 or its strided form
    return x


def _eps_and_vjp(eps_model, x, t, q_n):
    if hasattr(eps_model, "eps_and_vjp"):
        return eps_model.eps_and_vjp(x, t, q_n)
    with torch.enable_grad():
        xr = x.detach().requires_grad_(True)
        eps = eps_model(xr, t, q_n)
    return eps.detach(), lambda v: torch.autograd.grad(eps, xr, v, retain_graph=True)[0]


# ---------------------------------------------------------------------------------------------- analytic loss
class BoxPenalty:
    """``L(x) = sum_k sum_j w_kj dist(x_j, [lo_kj, hi_kj])^2`` per case, on normalized x (B, D).

    Every adaptation loss term is of this kind once expressed on the normalized data: a rupture is the
    interval [0, 0] on f_i, a jam (-inf, l_fixed] on l_j, the tension bounds [f_min, f_max], a length
    band [lo, hi]; the weight folds C^adapt and the unit scales. Terms that never overlap on an element
    share one slot, so the usual loss is ONE slot: ``grad = 2 w (x - clamp(x, lo, hi))``.
    w2 = 2 w, lo, hi: (K, B, D) tensors (K slots); bounds may be +-inf, w2 is 0 where nothing applies.
    """

    def __init__(self, w2: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor, uniform_weight: Optional[float] = None):
        self.w2, self.lo, self.hi = w2, lo, hi
        if uniform_weight is not None:  # the builder knows it already (saves a device sync)
            self._uniform = uniform_weight
        if len(w2) == 1:  # the usual case: no loop over slots (each op counts at batch 1)
            self.slots = [(w2[0], lo[0], hi[0])]
            self.grad_x0 = self._grad_one_slot
        else:
            self.slots = list(zip(w2.unbind(0), lo.unbind(0), hi.unbind(0)))

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        """Loss per case (B,)."""
        total = 0.0
        for w2, lo, hi in self.slots:
            r = x - torch.clamp(x, lo, hi)
            total = total + (0.5 * w2 * r * r).sum(-1)
        return total

    @property
    def uniform_weight(self) -> Optional[float]:
        """c when there is one slot and every constrained element has ``w2 = c`` (then grad = c residual)."""
        if "_uniform" not in self.__dict__:
            w2 = self.w2.detach().cpu().numpy()
            self._uniform = _uniform(w2)
        return self._uniform

    def _grad_one_slot(self, x: torch.Tensor) -> torch.Tensor:
        w2, lo, hi = self.slots[0]
        return torch.sub(x, torch.clamp(x, lo, hi)).mul_(w2)

    def grad_x0(self, x: torch.Tensor) -> torch.Tensor:
        """dL/dx (B, D)."""
        g = None
        for w2, lo, hi in self.slots:
            term = torch.sub(x, torch.clamp(x, lo, hi)).mul_(w2)
            g = term if g is None else g.add_(term)
        return g


_SMALL_BATCH = 8  # up to this many cases the penalty is assembled in plain Python (fewer calls than numpy)


class BoxPenaltyBuilder:
    """Turns a batch's fault constraints into the ``BoxPenalty`` of ``faults.adaptation_loss`` on normalized x.

    Built once per (weights, scales, normalizer): ``weights`` an ``AdaptWeights``; ``l_scale``, ``f_scale``
    scalars or (M,) [m], [N] (residuals are divided by them before squaring); ``x_mean``, ``x_std`` (2M,)
    with ``x = x_n * x_std + x_mean``. Calling it on constraints (``faults`` objects, (B, M) masks) gives the
    penalty, or None if a constraint is of a kind it does not know (the caller then uses autograd).
    Each call runs once per ``adapt``, so at batch 1 it is part of the latency: up to ``_SMALL_BATCH`` cases
    it works element by element on Python floats (~30 us), beyond that vectorized in numpy.
    """

    def __init__(self, weights, l_scale, f_scale, x_mean, x_std, dtype=torch.float32):
        from ..faults import constraints as fc

        self.mean, self.std = _np(x_mean), _np(x_std)
        self.m = m = self.mean.shape[-1] // 2
        scale = np.concatenate([np.broadcast_to(_np(l_scale), (m,)), np.broadcast_to(_np(f_scale), (m,))])
        ratio2 = (self.std / scale) ** 2
        self.dtype = dtype
        # kind -> (first column, weight name, bounds in SI units: (B, M) tensors, or +-inf / 0.0)
        self.kinds = {fc.Rupture: (m, lambda c: (0.0, 0.0)),
                      fc.Jam: (0, lambda c: (-math.inf, c.l_fixed_m)),
                      fc.MinTension: (m, lambda c: (c.f_min_n, math.inf)),
                      fc.MaxTension: (m, lambda c: (-math.inf, c.f_max_n))}
        band = getattr(fc, "LengthBand", None)
        if band is not None:
            self.kinds[band] = (0, lambda c: (c.l_lo_m, c.l_hi_m))
        self._w2 = {start: {} for start in (0, m)}
        self._ratio2 = ratio2
        self._lists = {start: (self.mean[start:start + m].tolist(), self.std[start:start + m].tolist())
                       for start in (0, m)}
        self.weights = weights

    def _w2_of(self, start: int, weight_name: str) -> np.ndarray:
        cache = self._w2[start]
        if weight_name not in cache:
            cache[weight_name] = 2.0 * float(getattr(self.weights, weight_name)) * self._ratio2[start:start + self.m]
        return cache[weight_name]

    def __call__(self, constraints) -> Optional[BoxPenalty]:
        if not constraints:
            return None
        for c in constraints:
            if type(c) not in self.kinds:
                return None
        b, d = len(constraints[0].mask), 2 * self.m
        if b <= _SMALL_BATCH:
            flat, n_slots = self._small(constraints, b, d)
            w2 = flat[:n_slots * b * d]
            nz = [w for w in w2 if w != 0.0]
            uniform = None if n_slots != 1 else (nz[0] if nz and all(w == nz[0] for w in nz) else (None if nz else 1.0))
            packed = torch.tensor(flat, dtype=self.dtype, device=constraints[0].mask.device).view(3, n_slots, b, d)
        else:
            packed = self._vectorized(constraints, b, d)
            uniform = _uniform(packed[0])
            packed = torch.from_numpy(packed).to(dtype=self.dtype, device=constraints[0].mask.device)
        return BoxPenalty(packed[0], packed[1], packed[2], uniform)

    def _small(self, constraints, b: int, d: int) -> tuple[list, int]:
        """Element by element: each element keeps a list of boxes; a term joins the first compatible one."""
        boxes = [[] for _ in range(b * d)]
        for c in constraints:
            start, bounds = self.kinds[type(c)]
            w2 = self._w2_of(start, c.weight_name).tolist()
            if w2[0] == 0.0 and not any(w2):
                continue
            mu, sd = self._lists[start]
            lo, hi = bounds(c)
            lo = lo.tolist() if torch.is_tensor(lo) else lo
            hi = hi.tolist() if torch.is_tensor(hi) else hi
            for i, row in enumerate(c.mask.tolist()):
                for j, on in enumerate(row):
                    if not on:
                        continue
                    lo_ij = lo if isinstance(lo, float) else lo[i][j]
                    hi_ij = hi if isinstance(hi, float) else hi[i][j]
                    new = (w2[j], lo_ij if math.isinf(lo_ij) else (lo_ij - mu[j]) / sd[j],
                           hi_ij if math.isinf(hi_ij) else (hi_ij - mu[j]) / sd[j])
                    cell = boxes[i * d + start + j]
                    for k, box in enumerate(cell):
                        if _compatible(box, *new):
                            cell[k] = (box[0], max(box[1], new[1]), min(box[2], new[2]))
                            break
                    else:
                        cell.append(new)
        n_slots = max(1, max(len(cell) for cell in boxes))
        empty = (0.0, -math.inf, math.inf)
        flat = [(cell[k] if k < len(cell) else empty)[q] for q in range(3) for k in range(n_slots) for cell in boxes]
        return flat, n_slots  # (3, n_slots, B, D) in C order

    def _vectorized(self, constraints, b: int, d: int) -> np.ndarray:
        slots = []
        for c in constraints:
            start, bounds = self.kinds[type(c)]
            w2 = self._w2_of(start, c.weight_name)
            mask = c.mask.detach().cpu().numpy()
            if not w2.any() or not mask.any():
                continue
            cols = slice(start, start + self.m)
            lo, hi = bounds(c)  # NaN off the mask (e.g. l_fixed) is never copied
            lo = lo if isinstance(lo, float) and math.isinf(lo) else (_np(lo) - self.mean[cols]) / self.std[cols]
            hi = hi if isinstance(hi, float) and math.isinf(hi) else (_np(hi) - self.mean[cols]) / self.std[cols]
            _place(slots, b, d, cols, mask, w2, lo, hi)
        return np.stack([slot for slot, _ in slots] or [_empty_slot(b, d)], axis=1)


def box_penalty(constraints, weights, l_scale, f_scale, x_mean, x_std, dtype=None) -> Optional[BoxPenalty]:
    """``BoxPenaltyBuilder(weights, l_scale, f_scale, x_mean, x_std, dtype)(constraints)`` in one call."""
    return BoxPenaltyBuilder(weights, l_scale, f_scale, x_mean, x_std, dtype or torch.float32)(constraints)


def _uniform(w2: np.ndarray) -> Optional[float]:
    """The one nonzero value of a single-slot weight array (K=1, B, D), else None (1.0 if all zero)."""
    if len(w2) != 1:
        return None
    nz = w2[w2 != 0]
    if not nz.size:
        return 1.0
    return float(nz[0]) if (nz == nz[0]).all() else None


def _np(a) -> np.ndarray:
    return a.detach().cpu().numpy().astype(np.float64) if torch.is_tensor(a) else np.asarray(a, np.float64)


def _compatible(box, w2, lo, hi) -> bool:
    """Two squared hinge distances add up to one box distance when they have the same weight, one bounds
    only from below and the other only from above, and the bounds do not cross."""
    b_w2, b_lo, b_hi = box
    return (b_w2 == w2 and (lo == -math.inf or b_lo == -math.inf) and (hi == math.inf or b_hi == math.inf)
            and max(lo, b_lo) <= min(hi, b_hi))


def _empty_slot(b: int, d: int) -> np.ndarray:
    slot = np.empty((3, b, d))
    slot[0], slot[1], slot[2] = 0.0, -np.inf, np.inf
    return slot


def _place(slots: list, b: int, d: int, cols: slice, mask, w2, lo, hi) -> None:
    """Vectorized ``BoxPenaltyBuilder._small``: put a whole term in the first slot where, on every element, it meets
    nothing or a compatible box (see ``_compatible``); otherwise open a new slot."""
    lo_b, hi_b = np.broadcast_to(lo, mask.shape), np.broadcast_to(hi, mask.shape)
    for slot, occupied in slots:
        overlap = occupied[:, cols] & mask
        if overlap.any():
            s_w2, s_lo, s_hi = slot[0][:, cols][overlap], slot[1][:, cols][overlap], slot[2][:, cols][overlap]
            n_lo, n_hi = lo_b[overlap], hi_b[overlap]
            ok = ((s_w2 == np.broadcast_to(w2, mask.shape)[overlap]).all()
                  and ((n_lo == -np.inf) | (s_lo == -np.inf)).all() and ((n_hi == np.inf) | (s_hi == np.inf)).all()
                  and (np.maximum(n_lo, s_lo) <= np.minimum(n_hi, s_hi)).all())
            if not ok:
                continue
        break
    else:
        slot, occupied = _empty_slot(b, d), np.zeros((b, d), bool)
        slots.append((slot, occupied))
    np.copyto(slot[0][:, cols], w2, where=mask)
    np.copyto(slot[1][:, cols], np.maximum(slot[1][:, cols], lo), where=mask)
    np.copyto(slot[2][:, cols], np.minimum(slot[2][:, cols], hi), where=mask)
    occupied[:, cols] |= mask


# ---------------------------------------------------------------------------------------------- latent space
@dataclass(frozen=True)
class LatentConfig:
    """eq:latent-opt: ``z <- z - lr grad_z L(dec(q, z))`` for ``n_steps`` (``optimizer="adam"`` optional)."""

    lr: float = 0.01
    n_steps: int = 200
    optimizer: str = "sgd"


def optimize_latent(decoder, q_n: torch.Tensor, z0: torch.Tensor, loss_fn: LossFn,
                    config: LatentConfig = LatentConfig(), fast: bool = False) -> torch.Tensor:
    """Gradient descent on z_latent (B, L), q fixed to q_ref; returns the final z.

    ``fast``: no autograd (``decoder.bind(q)`` gives the decoder with a hand-written backward pass, the loss
    gradient comes from ``loss_fn.grad_x0`` when present); SGD and Adam written out with torch.optim's
    formulas. Same result as the reference (tested).
    """
    if config.optimizer not in ("sgd", "adam"):
        raise BodySchemaInputError(f"unknown latent optimizer {config.optimizer!r}; allowed: 'sgd', 'adam'")
    bound = decoder.bind(q_n) if fast and hasattr(decoder, "bind") else None
    if bound is not None:
        return _fast_latent(bound, z0, loss_fn, config)
    z = z0.detach().clone().requires_grad_(True)
    opt = (torch.optim.SGD if config.optimizer == "sgd" else torch.optim.Adam)([z], lr=config.lr)
    with torch.enable_grad():
        for _ in range(config.n_steps):
            opt.zero_grad(set_to_none=True)
            loss_fn(decoder(q_n, z)).sum().backward()
            opt.step()
    return z.detach()


def _fast_latent(bound, z0, loss_fn, config: LatentConfig, betas=(0.9, 0.999), eps=1e-8):
    """Latent descent without autograd: decoder forward, dL/dx (``BoxPenalty`` residual, or autograd on the
    loss alone for other losses), the decoder's hand-written backward pass, then SGD or Adam (torch.optim's
    single-tensor formulas, no weight decay). For SGD with a uniform penalty weight c the update is one
    ``addmm`` with W = -lr c W1_z (the scalars folded into the matrix)."""
    net, bias = bound
    box = getattr(loss_fn, "box_penalty", None)
    if box is not None and len(box.slots) != 1:
        box = None
    grad_x = loss_gradient(loss_fn) if box is None else None
    uniform = None if box is None else box.uniform_weight
    c = 1.0 if uniform is None else uniform
    if box is not None:
        w2, lo, hi = box.slots[0]
        w2 = w2 if uniform is None else None
    act, act_backward, silu = net._act, net._act_backward, net.silu
    hidden = [(w_t, w, b) for w_t, w, b in net.hidden]
    w1_t, w_out_t, w_out, b_out = net.w1_free_t, net.out_w_t, net.out_w, net.out_b
    addmm, mm = torch.addmm, torch.mm
    sgd = config.optimizer == "sgd"
    with torch.inference_mode(_INFERENCE_MODE and box is not None):  # autograd on the loss needs grad mode
        w_z = (-config.lr * c) * net.w1_free if sgd else c * net.w1_free
        z = z0.detach().clone()
        if not sgd:
            m, v = torch.zeros_like(z), torch.zeros_like(z)
        for step in range(1, config.n_steps + 1):
            a = addmm(bias, z, w1_t)
            h = act(a)
            saved = [a if silu else h]
            for w_t_, _, b in hidden:
                a = addmm(b, h, w_t_)
                h = act(a)
                saved.append(a if silu else h)
            x = addmm(b_out, h, w_out_t)
            if box is not None:
                r = torch.sub(x, torch.clamp(x, lo, hi))  # dL/dx / c
                if w2 is not None:
                    r = r.mul_(w2)
            else:
                r = grad_x(x)
            g1 = act_backward(mm(r, w_out), saved[-1])
            for (_, w, _), sv in zip(reversed(hidden), reversed(saved[:-1])):
                g1 = act_backward(mm(g1, w), sv)
            if sgd:  # z -= lr c (J^T r)
                z = addmm(z, g1, w_z)
            else:
                grad = mm(g1, w_z)
                m.lerp_(grad, 1.0 - betas[0])
                v.mul_(betas[1]).addcmul_(grad, grad, value=1.0 - betas[1])
                step_size = config.lr / (1.0 - betas[0] ** step)
                denom = (v.sqrt() / math.sqrt(1.0 - betas[1] ** step)).add_(eps)
                z.addcdiv_(m, denom, value=-step_size)
    return z.clone()
