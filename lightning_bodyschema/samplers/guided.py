"""Gradient-guided denoising (paper section III-C): the autograd reference and the one fast loop.

Update rules only. The network, the schedule and the loss come in as arguments, the loss as a penalty *value*
(``faults.penalty.BoxPenalty`` or anything with its methods: called for the loss, ``residual`` for its
gradient); nothing here imports Lightning or ``faults``. Every case of a batch is updated by the same tensor ops.

* ``reference_loop``: eq:diff-1 -> eq:diff-adapt -> eq:diff-2 as printed, autograd through the network and the
  loss. The yardstick in tests, and the sampler of networks that have no ``FrozenMLP``.
* ``denoise``: the same maths for an MLP through its ``FrozenMLP`` snapshot, without autograd. The state is
  u = x_t / sqrt(abar_t), every schedule and guidance coefficient is folded into per-step records (``PlanStep``,
  made by ``plan_denoising``), and ONE loop body (``guided_loop``) runs either eagerly, writing into buffers
  allocated once per call, or through ``torch.compile``. At batch 1 a tensor op costs microseconds of dispatch, so
  the fast loop is mostly about doing fewer of them. Same commands as the reference (tests: 1e-5 in float64).

Both loops take the network's output type (``prediction``: eps, x0 or v) and convert it in ONE place, the schedule
(``NoiseSchedule.split_output`` for the reference, its float coefficients ``output_affine`` for the plan): the fused
algebra is written for any affine x0_hat = ax x_t + bx o, eps_hat = ae x_t + be o. The denoising step carries
eps_hat (predicted before the last guidance step) to the next noise level, whatever the network outputs.
"""
from __future__ import annotations

import functools
import math
import sys
from dataclasses import dataclass
from typing import NamedTuple, Optional, Sequence

import torch

from ..errors import BodySchemaInputError
from .schedule import check_prediction

STEP_SCALES = ("none", "sqrt_abar", "abar")
INPAINT = ("none", "box", "spring")  # the inpainting modes, defined here once (faults.projection imports them)


@dataclass(frozen=True)
class GuidanceConfig:
    """How eq:diff-adapt steps.

    lr: C_lr^adapt. step_scale: the factor s_t multiplying the step at noise level t:
      ``"none"``      s_t = 1               the paper as printed (diverges early in SI units: docs/design.md);
      ``"sqrt_abar"`` s_t = sqrt(abar_t)    damps the noisy steps by the sensitivity of x0_hat to x_t;
      ``"abar"``      s_t = abar_t          x0_hat moves by -lr grad_{x0} L at every t, whatever the noise level
                                            (d x0_hat / d x_t ~ 1/sqrt(abar_t) cancels: a Newton-like step in x0).
    n_guide: guidance steps per timestep (eq:diff-adapt repeated, eps re-predicted at the updated x_t; the
      denoising step then uses the eps of the last one). 1 is the paper's.
    min_abar: guide only where abar_t >= min_abar (0, the paper's: every step). With ``"abar"`` a step at a
      noisy level moves x_t by only ~lr sqrt(abar_t) |grad_x0 L| and the following denoising washes it out.
    inpaint: at every guided step, replace the x0 the denoising step uses by its projection onto the faults'
      feasible set (``"box"`` or ``"spring"``, a ``faults.projection.FaultProjection`` given to the sampler), keeping
      the predicted eps: x_{t'} += sqrt(abar_t') (P(x0_hat) - x0_hat). ``"none"``: the paper's guidance only.
    inpaint_min_abar: inpaint only where abar_t >= inpaint_min_abar (0: at every guided step). At the noisier
      steps the predicted x0 is still far from the data, and snapping it costs accuracy in conditions where the
      faults need little change.
    inpaint_n_guide: guidance steps per timestep where the step inpaints (at least ``n_guide``). With one, the eps the
      step keeps was predicted before the guidance moved x_t, and where no command can meet the faults that stale pair
      can diverge; the second re-predicts eps at the guided x_t.
    recurrence: denoise t -> t' then re-noise t' -> t with fresh seeded noise, ``recurrence`` times per step
      (universal guidance's recurrence; 1: none). Autograd reference loop only.
    project_xt: also project x_t itself (scaled to x0 units) after every step, as projected diffusion models do.
      Autograd reference loop only.
    Why those two stay out of the fused loop: they are study variants none of the presets the package recommends
    uses; recurrence draws fresh seeded noise inside the loop, which ``torch.compile`` cannot trace with a
    generator (reproducing the reference's draws would mean drawing them outside, in its order and shapes); and
    the fused loop's op count is its cost at batch 1. ``reference_only`` sends them to ``reference_loop``, which
    converts the network's output through the same schedule method as the fused plan.
    """

    lr: float = 0.01
    step_scale: str = "none"
    n_guide: int = 1
    min_abar: float = 0.0
    inpaint: str = "none"
    inpaint_min_abar: float = 0.0
    inpaint_n_guide: int = 2
    recurrence: int = 1
    project_xt: bool = False

    def __post_init__(self):
        if self.step_scale not in STEP_SCALES:
            raise BodySchemaInputError(f"unknown step_scale {self.step_scale!r}; allowed: {list(STEP_SCALES)}")
        if self.inpaint not in INPAINT:
            raise BodySchemaInputError(f"unknown inpaint {self.inpaint!r}; allowed: {list(INPAINT)}")
        for name in ("n_guide", "inpaint_n_guide", "recurrence"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise BodySchemaInputError(f"{name}={value!r} must be an integer >= 1")

    @property
    def reference_only(self) -> bool:
        """True for the settings only the autograd reference loop implements."""
        return self.recurrence > 1 or self.project_xt

    def scale(self, abar: float) -> float:
        """s_t at alpha_bar_t = ``abar``."""
        return {"none": 1.0, "sqrt_abar": math.sqrt(abar), "abar": abar}[self.step_scale]

    def n_guide_at(self, abar: float) -> int:
        if abar < self.min_abar:
            return 0
        return max(self.n_guide, self.inpaint_n_guide) if self.inpaints_at(abar) else self.n_guide

    def inpaints_at(self, abar: float) -> bool:
        """True where a guided step at alpha_bar_t = ``abar`` inpaints its x0."""
        return self.inpaint != "none" and abar >= max(self.inpaint_min_abar, self.min_abar)


def _check_steps(schedule, timesteps: Optional[Sequence[int]]) -> list[int]:
    return list(range(schedule.n_timesteps - 1, -1, -1)) if timesteps is None else [int(t) for t in timesteps]


# ---------------------------------------------------------------------------------------------- the reference
def reference_loop(model, schedule, q_n, x_T, penalty=None, guidance: GuidanceConfig = GuidanceConfig(),
                   timesteps: Optional[Sequence[int]] = None, eta: float = 1.0, projection=None,
                   prediction: str = "eps") -> torch.Tensor:
    """Deterministic denoising from ``x_T (B, D)`` over ``timesteps`` (descending; None: all T), guided by
    ``penalty`` on the predicted x0 at every step (None: the unguided healthy sample) and, with ``guidance.inpaint``,
    inpainted by ``projection`` (``offset(x0) = x0 - P(x0)``). ``model(x_t, t, q_n)`` outputs ``prediction``
    (``samplers.schedule.PREDICTIONS``), turned into (x0_hat, eps_hat) by ``schedule.split_output``. Returns x0
    (B, D); rows may be non-finite if guidance diverged (the caller checks)."""
    check_prediction(prediction)
    steps, x = _check_steps(schedule, timesteps), x_T
    gen = torch.Generator(device=x_T.device).manual_seed(0) if guidance.recurrence > 1 else None
    for i, t in enumerate(steps):
        t_next = steps[i + 1] if i + 1 < len(steps) else -1
        for r in range(guidance.recurrence if penalty is not None else 1):
            if r > 0:  # universal guidance's recurrence: back to t with fresh noise, q(x_t | x_t')
                x = _renoise(schedule, x_next, t, t_next, gen)
            x_next = _reference_step(model, schedule, q_n, x, t, t_next, penalty, guidance, eta, projection,
                                     prediction)
        x = x_next
    return x


def _reference_step(model, schedule, q_n, x, t, t_next, penalty, guidance, eta, projection, prediction):
    """One timestep t -> t_next: guidance (eq:diff-1, eq:diff-adapt), the denoising step (eq:diff-2), inpainting."""
    n_guide = 0 if penalty is None else guidance.n_guide_at(float(schedule.alpha_bars[t]))
    if n_guide == 0:
        with torch.no_grad():
            eps = schedule.split_output(model(x, t, q_n), x, t, prediction)[1]
    for _ in range(n_guide):
        x, eps = _guide(model, schedule, q_n, x, t, penalty, guidance, prediction)
    with torch.no_grad():  # 3. eq:diff-2 (eta = 1, stride 1) or its strided form, with the eps before guidance
        x_next = schedule.step(x, eps, t, t_next, eta)
        s0_next = math.sqrt(float(schedule.alpha_bars[t_next])) if t_next >= 0 else 1.0
        if projection is not None and n_guide > 0 and guidance.inpaints_at(float(schedule.alpha_bars[t])):
            # 4. inpainting: the step's x0_hat replaced by P(x0_hat), eps kept (its x0 coefficient is s0')
            x_next = x_next - s0_next * projection.offset(schedule.predict_x0(x, eps, t))
        if projection is not None and guidance.project_xt:
            x_next = x_next - s0_next * projection.offset(x_next / s0_next)
    return x_next


def _renoise(schedule, x_next, t, t_next, gen):
    """A draw of x_t given x_t' (t' < t): sqrt(abar_t / abar_t') x_t' + sqrt(1 - abar_t / abar_t') xi."""
    ratio = float(schedule.alpha_bars[t]) / (float(schedule.alpha_bars[t_next]) if t_next >= 0 else 1.0)
    noise = torch.randn(x_next.shape, generator=gen, device=x_next.device, dtype=x_next.dtype)
    return math.sqrt(ratio) * x_next + math.sqrt(1.0 - ratio) * noise


def _guide(model, schedule, q_n, x_t, t, penalty, guidance, prediction):
    """One guidance step at t: the guided x_t and the eps_hat predicted before it."""
    x_t = x_t.detach().requires_grad_(True)
    with torch.enable_grad():
        # 1. eq:diff-1 (for eps: x0_hat = (x_t - sqrt(1 - abar_t) eps) / sqrt(abar_t)), the schedule's conversion
        x0_hat, eps = schedule.split_output(model(x_t, t, q_n), x_t, t, prediction)
        # 2. eq:diff-adapt: x_t <- x_t - C_lr s_t grad_{x_t} L(x0_hat)   (cases are independent: sum)
        grad, = torch.autograd.grad(penalty(x0_hat).sum(), x_t)
    return (x_t - guidance.lr * guidance.scale(float(schedule.alpha_bars[t])) * grad).detach(), eps.detach()


# ---------------------------------------------------------------------------------------------- the fast loop
class PlanStep(NamedTuple):
    """One timestep of a ``DenoisePlan``. The loop state is u = x_t / s0 (s0 = sqrt(abar_t); s0', s1 likewise; the
    next step's s0' is 1 after the last step). From the schedule (the ONE conversion of the network's output o,
    ``NoiseSchedule.output_affine``): x0_hat = ax x_t + bx o, eps_hat = ae x_t + be o; (cx, ce) =
    ``step_coefficients``; K = lr s_t; c the penalty's uniform weight (dL/dx0_hat = c r, r = ``penalty.residual``).

    n_guide      guidance evaluations at this step (0: unguided)
    inv_s0       1 / s0: x_t -> u (used once, for x_T)
    w1           first layer in u units, s0 W1_free^T (n_free, H)
    beta, w_e    the output scaled so that e = beta + h w_e: e = bx o where guided, (ce be / s0') o where not
    c_u          x0_hat = c_u u + e (c_u = ax s0; 1 for eps)
    a_u          u' = a_u u + ... : the x_t-part of the step in the next step's units ((cx + ce ae) s0 / s0')
    a_e          u' += a_e e: the eps_hat-part carried by the output (ce be / (bx s0'))
    w_r          r -> dL/d(output) for the backward, c W_out (H, D) (shared by every guided step)
    k_r, w_k     one guidance step, eq:diff-adapt: u <- u + k_r r + g1 w_k, grad_{x_t} L = c (ax r + bx g1 W1_free)
                 with g1 = ``back`` of r through w_r: k_r = -K ax c / s0, w_k = (-K bx / s0) W1_free; the last one
                 is folded into the denoising step (the guided x_t's share of x_t' is cx s0 / s0' = 1 in u units)
    inpaint      this step replaces the guided x0 by its projection: u' -= d, d = x0_g - P(x0_g),
                 x0_g = x0_hat + k_r r + g1 w_k (the x0 of the guided x_t with eps_hat kept: x_t' moves by s0' d)

    So the guided step is u' = a_u u + a_e e + k_r r + g1 w_k (one fused expression for every prediction type), the
    unguided one u' = a_u u + beta + h w_e. Build it by name; ``guided_loop`` unpacks it in this field order.
    """

    n_guide: int
    inv_s0: float
    w1: torch.Tensor
    beta: torch.Tensor
    w_e: torch.Tensor
    c_u: float = 1.0
    a_u: float = 1.0
    a_e: float = 0.0
    w_r: Optional[torch.Tensor] = None
    k_r: float = 0.0
    w_k: Optional[torch.Tensor] = None
    inpaint: bool = False


STACKED = ("w1", "beta", "w_e", "w_k")  # per-step matrices stacked (S, ...) for torch.compile
SCALARS = ("n_guide", "inv_s0", "c_u", "a_u", "a_e", "k_r", "inpaint")  # per-step numbers


@dataclass
class DenoisePlan:
    """Per-step records (``PlanStep``) of ``guided_loop`` for one (network snapshot, schedule, steps, eta,
    guidance, weight c, prediction type)."""

    steps: list

    @functools.cached_property
    def stacked(self) -> tuple:
        """(matrices, w_r, scalars): the plan as a few stacked (S, ...) tensors by name (``STACKED``; zeros where a
        step has none), the shared w_r, and a tuple of per-step numbers (``SCALARS``, in that order): what
        ``torch.compile`` sees (~10 tensor inputs instead of ~200 list entries, so its per-call guards stay cheap)."""
        first = self.steps[0]
        likes = {"w1": first.w1, "beta": first.beta, "w_e": first.w_e, "w_k": first.w1.t()}  # w_k: (H, n_free)
        matrices = {name: torch.stack([torch.zeros_like(likes[name]) if getattr(p, name) is None else getattr(p, name)
                                       for p in self.steps]) for name in STACKED}
        w_r = next((p.w_r for p in self.steps if p.w_r is not None), first.w_e.t())
        scalars = tuple(tuple(getattr(p, name) for name in SCALARS) for p in self.steps)
        return matrices, w_r, scalars


def plan_denoising(net, schedule, timesteps: Optional[Sequence[int]], eta: float, guidance: GuidanceConfig,
                   c_w: float = 1.0, guided: bool = True, prediction: str = "eps") -> DenoisePlan:
    """The ``DenoisePlan`` of ``net`` (a ``FrozenMLP`` of the network, which outputs ``prediction``) over
    ``timesteps`` (None: all T); ``c_w``: the penalty's uniform weight (1 when it has none); ``guided=False``: the
    unguided healthy sample."""
    steps, w_r = _check_steps(schedule, timesteps), c_w * net.out_w  # w_r: one tensor shared by every step
    return DenoisePlan([_plan_step(net, schedule, t, steps[i + 1] if i + 1 < len(steps) else -1, eta, guidance, c_w,
                                   w_r, guided, prediction) for i, t in enumerate(steps)])


def _plan_step(net, schedule, t, t_next, eta, guidance, c_w, w_r, guided, prediction) -> PlanStep:
    """The ``PlanStep`` from t to t_next (see its doc for every formula)."""
    abar = float(schedule.alpha_bars[t])
    cx, ce = schedule.step_coefficients(t, t_next, eta)
    affine = schedule.output_affine(t, prediction)
    (ax, bx), (ae, be) = affine.x0_coefficients(), affine.eps_coefficients()
    inv_s0, n_guide = 1.0 / math.sqrt(abar), guidance.n_guide_at(abar) if guided else 0
    s0 = 1.0 / inv_s0  # the first layer's scale, as the loop state u = x_t * inv_s0 sees it
    s0_next = cx * s0  # s0' = sqrt(abar_prev)
    a_u = (cx + ce * ae) * s0 / s0_next  # exactly 1 for eps (ae = 0)
    if n_guide == 0:
        f = ce * be / s0_next
        return PlanStep(0, inv_s0, s0 * net.w1_free_t, f * net.out_b, f * net.out_w_t, a_u=a_u)
    if bx == 0.0:
        raise BodySchemaInputError(f"prediction {prediction!r}: x0_hat does not depend on the network output at t={t}")
    k = guidance.lr * guidance.scale(abar)  # K
    return PlanStep(n_guide, inv_s0, s0 * net.w1_free_t, bx * net.out_b, bx * net.out_w_t, c_u=ax / inv_s0, a_u=a_u,
                    a_e=ce * be / (bx * s0_next), w_r=w_r, k_r=-k * ax * c_w * inv_s0,
                    w_k=(-k * bx * inv_s0) * net.w1_free, inpaint=guidance.inpaints_at(abar))


def guided_loop(steps, biases, x, penalty, net, ops, projection=None) -> torch.Tensor:
    """THE fused loop body (see ``PlanStep``): ``steps`` the plan's records, ``biases[i]`` step i's first-layer
    bias (B, H), ``x`` x_T (B, D); returns x0 (B, D). Every intermediate is written into buffers allocated here, once
    per call (at batch 1 an op that allocates nothing costs less); ``u`` alternates between two of them
    because ``addmm``'s out must not be an input. ``ops``: ``net.eager`` or, under torch.compile, ``net.traceable``.
    ``projection``: inpaint every guided step's x0 (``GuidanceConfig.inpaint``; None: no inpainting)."""
    (b, d), new = x.shape, x.new_empty
    bufs = net.buffers(b, x)
    e, x0, tmp, res, states = new((b, d)), new((b, d)), new((b, d)), (new((b, d)), new((b, d))), (new((b, d)), new((b, d)))
    x0_guided = (new((b, d)), new((b, d)), new((b, d)))  # x0_g, its addmm twin, and d
    u, k = torch.mul(x, steps[0].inv_s0, out=states[0]), 0  # x_T / sqrt(abar_T)
    # unpacked in PlanStep's field order (one tuple unpack per step: at batch 1 attribute reads add up)
    for i, (n_guide, _, w1, beta, w_e, c_u, a_u, a_e, w_r, k_r, w_k, inpaint) in enumerate(steps):
        if n_guide == 0:  # eq:diff-2 / DDIM without guidance: u' = a_u u + beta + h We
            h, _ = net.trunk(u, biases[i], w1, bufs, ops)
            k = 1 - k
            tmp_u = torch.add(u, beta, out=tmp) if a_u == 1.0 else torch.add(beta, u, alpha=a_u, out=tmp)
            u = torch.addmm(tmp_u, h, w_e, out=states[k])
            continue
        for j in range(n_guide):
            h, saved = net.trunk(u, biases[i], w1, bufs, ops)
            torch.addmm(beta, h, w_e, out=e)  # bx o
            if c_u == 1.0:  # 1. eq:diff-1: x0_hat = c_u u + e
                torch.add(u, e, out=x0)
            else:
                torch.add(e, u, alpha=c_u, out=x0)
            r = penalty.residual(x0, res)  # dL/dx0_hat / c
            g1 = net.back(r, w_r, saved, bufs, ops)  # J^T dL/dx0_hat = g1 W1_free, J = d o / d x_t
            k = 1 - k
            if j + 1 < n_guide:  # 2. eq:diff-adapt only
                u = torch.addmm(torch.add(u, r, alpha=k_r, out=tmp), g1, w_k, out=states[k])
            else:  # 2. eq:diff-adapt and 3. eq:diff-2 / DDIM, in the next step's units
                inpaint = inpaint and projection is not None
                if inpaint:  # the guided x0_hat (the inner step's u, plus e) and its offset d
                    d = projection.offset(torch.addmm(torch.add(x0, r, alpha=k_r, out=x0_guided[0]), g1, w_k,
                                                      out=x0_guided[1]), out=x0_guided[2])
                if a_u == 1.0:  # a_u u + a_e e
                    torch.add(u, e, alpha=a_e, out=tmp)
                else:
                    torch.mul(u, a_u, out=tmp).add_(e, alpha=a_e)
                u = torch.addmm(tmp.add_(r, alpha=k_r), g1, w_k, out=states[k])
                if inpaint:  # 4. inpainting: x0_hat -> P(x0_hat) with eps_hat kept is u' -= d
                    u.sub_(d)
    return u


def _from_stacked(matrices, w_r, scalars, biases, x, penalty, net, projection=None):
    """``guided_loop`` on the stacked plan (``DenoisePlan.stacked``): what ``torch.compile`` traces; the indexing
    becomes free views inside the graph."""
    steps = [PlanStep(w_r=w_r, **{name: m[i] for name, m in matrices.items()}, **dict(zip(SCALARS, numbers)))
             for i, numbers in enumerate(scalars)]
    return guided_loop(steps, biases, x, penalty, net, net.traceable, projection)


@functools.lru_cache(maxsize=1)
def compiled_sampler():
    """``guided_loop`` (through ``_from_stacked``) compiled by inductor with its C++ wrapper, the whole loop as one
    graph. Specialised to a plan and a batch size: the first call for each compiles (a C++ compiler is needed;
    ``denoise`` says so on stderr; inductor's on-disk cache serves a repeat in a new process; BENCHMARKS.md "Figures
    behind code choices" has the cost); later calls skip Python's per-op dispatch and fuse the elementwise ops."""
    return torch.compile(_from_stacked, fullgraph=True, dynamic=False, options={"cpp_wrapper": True})


_COMPILED_FOR: set = set()  # the (batch shape, dtype, steps, guided, inpainted) the sampler was compiled for


def _announce_compile(key: tuple) -> None:
    """One stderr line before a call that compiles (a new batch size or plan): it is silent for minutes otherwise."""
    if key not in _COMPILED_FOR:
        _COMPILED_FOR.add(key)
        print(f"compiling the sampler for {key[0][0]} case(s) per call, {key[2]} steps (torch.compile, C++: 1-3 min "
              "on 2 cores the first time, seconds once inductor's disk cache has it)", file=sys.stderr, flush=True)


def denoise(net, plan: DenoisePlan, biases: torch.Tensor, x_T: torch.Tensor, penalty=None, compiled: bool = False,
            inference_mode: bool = True, projection=None) -> torch.Tensor:
    """Run ``plan`` from ``x_T (B, D)`` with the first-layer biases ``(S, B, H)`` of its steps; returns x0 (B, D).

    ``compiled``: through ``compiled_sampler``; ``inference_mode``: run under ``torch.inference_mode`` (no version
    counters or autograd bookkeeping); the result is an ordinary tensor either way.
    ``projection``: inpaint the guided steps (see ``guided_loop``)."""
    with torch.inference_mode(inference_mode):
        if compiled:
            matrices, w_r, scalars = plan.stacked
            _announce_compile((tuple(x_T.shape), x_T.dtype, len(plan.steps), penalty is None, projection is None))
            out = compiled_sampler()(matrices, w_r, scalars, biases, x_T, penalty, net, projection)
        else:
            out = guided_loop(plan.steps, biases.unbind(0), x_T, penalty, net, net.eager, projection)
    return out.clone()
