"""The autograd-free fast adaptation paths return the reference (autograd) commands; the strided sampler.

Equality is checked in float64 (1e-5, measured ~1e-12) and, with the float32 models the package ships,
within tolerances a few times the reference's own float32 error. Nothing here is timed
(tools/bench_adaptation.py measures speed).
"""
import copy
import dataclasses

import lightning as L
import numpy as np
import pytest
import torch

from lightning_bodyschema.apps.case_tools import adapt_cases_main
from lightning_bodyschema.apps.common import ADAPT_SAMPLERS
from lightning_bodyschema.data import EquilibriumDataModule
from lightning_bodyschema.errors import BodySchemaInputError
from lightning_bodyschema.evaluation import make_fault_cases
from lightning_bodyschema.faults import AdaptWeights, Faults
from lightning_bodyschema.faults import constraints as fc
from lightning_bodyschema.networks import EpsMLP
from lightning_bodyschema.npz import load_npz
from lightning_bodyschema.samplers import GuidanceConfig, NoiseSchedule, guided_denoise
from lightning_bodyschema.samplers.guided import BoxPenaltyBuilder, deterministic_step, optimize_latent, LatentConfig
from lightning_bodyschema.schemas import AutoEncoderSchema, DiffusionSchema, VAESchema, load_schema
from lightning_bodyschema.schemas.base import BodySchema
from lightning_bodyschema.schemas.diffusion import strided_timesteps

F64_TOL = 1e-5
F32_TOL_N, F32_TOL_M = 0.05, 2e-5  # float32: 0.05 N of tension, 20 um of motor length (reference's own: ~0.02 N)


def _train(cls, epochs, dm, **kwargs):
    L.seed_everything(0)
    schema = cls(robot=dm.robot, **kwargs)
    trainer = L.Trainer(max_epochs=epochs, logger=False, enable_checkpointing=False, enable_progress_bar=False,
                        enable_model_summary=False, check_val_every_n_epoch=10 ** 6, num_sanity_val_steps=0)
    trainer.fit(schema, dm)
    return schema.eval(), trainer


@pytest.fixture(scope="module")
def dm():
    datamodule = EquilibriumDataModule(cache_dir=None)
    datamodule.prepare_data()
    datamodule.setup("fit")
    return datamodule


@pytest.fixture(scope="module")
def diffusion(dm):
    return _train(DiffusionSchema, 60, dm)


@pytest.fixture(scope="module")
def diffusion64(diffusion):
    """A float64 copy. (Converting back with ``.float()`` would round the float64 noise-schedule buffers for
    good, and the reference then works with other coefficients than a fresh schema.)"""
    return copy.deepcopy(diffusion[0]).double()


@pytest.fixture(scope="module", params=[AutoEncoderSchema, VAESchema], ids=["AE", "VAE"])
def latent(request, dm):
    return _train(request.param, 60, dm)[0]


@pytest.fixture(scope="module")
def latent64(latent):
    return copy.deepcopy(latent).double()


def _faults(schema, dm, n=12, seed=0):
    """Cut, jammed, weakened and (where the package supports it) length-banded muscles, mixed."""
    q, x = dm.splits["val"]
    m = schema.n_muscles
    cases = make_fault_cases(q.numpy(), x[:, :m].numpy(), n // 3, seed)
    faults = cases.faults
    f_max = np.full(faults.cut.shape, np.nan)
    f_max[::4, 3] = 60.0  # a weakened muscle in every fourth case
    fields = {f.name for f in dataclasses.fields(Faults)}
    extra = {"f_max_n": np.where(faults.cut, np.nan, f_max)}
    if "l_band_m" in fields:  # one banded motor per third case, overlapping a jam where there is one
        band = np.full(faults.cut.shape + (2,), np.nan)
        l_plain = schema.infer(cases.q_ref)[0]
        for i in range(0, len(cases), 3):
            j = int(np.flatnonzero(~faults.cut[i])[0])
            band[i, j] = [l_plain[i, j] - 0.004, l_plain[i, j] - 0.001]
        extra["l_band_m"] = band
    return cases.q_ref, Faults(faults.cut, faults.fix, faults.l_fixed_m, **extra)


def _assert_same_commands(fast, ref, tol_n, tol_m):
    assert (fast.status == ref.status).all()
    ok = ref.status == "ok"
    assert ok.any()
    np.testing.assert_allclose(fast.f_n[ok], ref.f_n[ok], rtol=0, atol=tol_n)
    np.testing.assert_allclose(fast.l_motor_m[ok], ref.l_motor_m[ok], rtol=0, atol=tol_m)


# ---------------------------------------------------------------------------- guided denoising
SAMPLERS = {
    "ddpm200": {},
    "ddim20": dict(ADAPT_SAMPLERS["ddim20"]),
    "ddim20_one_guide_trailing_eta0": dict(n_steps=20, n_guide=1, min_abar=0.0, eta=0.0, spacing="trailing"),
    "linspace7_three_guides": dict(n_steps=7, n_guide=3, min_abar=0.0, spacing="linspace"),
    # the paper's SI-unit loss (stable with sqrt(abar) scaling and 20 steps on this briefly trained model; with
    # 200 steps it runs away to ~1e8 m on some cases, where two chaotic trajectories cannot be compared)
    "literal_sqrt_abar_ddim20": dict(variant="literal", step_scale="sqrt_abar", n_steps=20),
}


@pytest.mark.parametrize("sampler", sorted(SAMPLERS))
def test_fast_guided_denoising_returns_the_reference_commands_float64(diffusion64, dm, sampler):
    schema = diffusion64
    q, faults = _faults(schema, dm)
    fast = schema.adapt(q, faults, **SAMPLERS[sampler])
    ref = schema.adapt(q, faults, fast=False, **SAMPLERS[sampler])
    _assert_same_commands(fast, ref, F64_TOL, F64_TOL)


@pytest.mark.parametrize("sampler", ["ddpm200", "ddim20", "literal_sqrt_abar_ddim20"])
def test_fast_guided_denoising_float32_within_tolerance(diffusion, dm, sampler):
    schema = diffusion[0]
    q, faults = _faults(schema, dm)
    _assert_same_commands(schema.adapt(q, faults, **SAMPLERS[sampler]),
                          schema.adapt(q, faults, fast=False, **SAMPLERS[sampler]), F32_TOL_N, F32_TOL_M)


@pytest.mark.parametrize("n_steps", [None, 20])
@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-9), (torch.float32, 1e-5)])
def test_fast_unguided_sampling_returns_the_reference_sample(diffusion, diffusion64, dm, n_steps, dtype, tol):
    schema = diffusion64 if dtype == torch.float64 else diffusion[0]
    q_n = schema.encode_q(dm.splits["val"][0][:9])
    torch.testing.assert_close(schema.generate(q_n, n_steps=n_steps), schema.generate(q_n, n_steps=n_steps, fast=False),
                               rtol=0, atol=tol)


def test_a_case_adapts_the_same_alone_or_in_a_batch_with_the_strided_sampler(diffusion64, dm):
    schema = diffusion64
    q, faults = _faults(schema, dm, n=6)
    batch = schema.adapt(q, faults, n_steps=20)
    for i in (0, 4):
        alone = schema.adapt(q[i:i + 1], faults.take([i]), n_steps=20)
        np.testing.assert_allclose(alone.f_n[0], batch.f_n[i], rtol=0, atol=1e-9)


def test_the_literal_recipe_still_diverges_on_the_fast_path_and_is_never_returned(diffusion, dm):
    schema = diffusion[0]
    q = dm.splits["val"][0][:4].numpy()
    faults = Faults.from_names(schema.robot_model.muscle_names, cut=[["shoulder_flexor"]] * 4)
    result = schema.adapt(q, faults, variant="literal")
    assert (result.status == "non_finite").all() and np.isnan(result.f_n).all()


# ---------------------------------------------------------------------------- latent descent
@pytest.mark.parametrize("options", [{}, {"optimizer": "adam"}, {"variant": "literal"}], ids=["sgd", "adam", "literal"])
def test_fast_latent_descent_returns_the_reference_commands(latent, latent64, dm, options):
    q, faults = _faults(latent, dm)
    _assert_same_commands(latent64.adapt(q, faults, **options), latent64.adapt(q, faults, fast=False, **options),
                          F64_TOL, F64_TOL)
    _assert_same_commands(latent.adapt(q, faults, **options), latent.adapt(q, faults, fast=False, **options),
                          F32_TOL_N, F32_TOL_M)


# ---------------------------------------------------------------------------- the analytic loss gradient
@pytest.mark.parametrize("variant", ["default", "literal"])
@pytest.mark.parametrize("n", [3, 24], ids=["python_builder", "numpy_builder"])
def test_box_penalty_is_the_adaptation_loss_and_its_gradient(diffusion64, dm, variant, n):
    schema = diffusion64
    q, faults = _faults(schema, dm, n=max(n, 3))
    q, faults = q[:n], faults.take(np.arange(n))
    constraints = faults.constraints(schema.spring.f_max_n, dtype=torch.float64)
    loss_fn = schema.adaptation_loss_fn(constraints, variant)
    box = loss_fn.box_penalty
    x = (3.0 * torch.randn(n, schema.x_dim, dtype=torch.float64)).requires_grad_(True)
    reference = BodySchema.adaptation_loss_fn(schema, constraints, variant)(x)
    grad, = torch.autograd.grad(reference.sum(), x)
    torch.testing.assert_close(box(x.detach()), reference.detach(), rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(loss_fn.grad_x0(x.detach()), grad, rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(loss_fn(x.detach()), reference.detach())  # the lazy reference closure
    if "l_band_m" in {f.name for f in dataclasses.fields(Faults)} and (faults.fix & faults.band).any():
        assert len(box.slots) == 2  # a jam and a band on one motor: two upper bounds, two slots


def test_an_unknown_constraint_falls_back_to_autograd_on_the_loss(diffusion64, dm):
    """A constraint kind the builder does not know: no analytic gradient, and the fast path still agrees."""

    @dataclasses.dataclass
    class Brake(fc.Rupture):  # same penalty as a rupture, but a kind the builder does not list
        pass

    schema = diffusion64
    q, faults = _faults(schema, dm, n=6)
    constraints = faults.constraints(schema.spring.f_max_n, dtype=torch.float64)
    constraints[0] = Brake(constraints[0].mask)
    builder = BoxPenaltyBuilder(AdaptWeights(), 1.0, 1.0, schema.normalizer.x_mean, schema.normalizer.x_std,
                                torch.float64)
    assert builder(constraints) is None
    loss_fn = schema.adaptation_loss_fn(constraints, "default")
    assert not hasattr(loss_fn, "grad_x0")
    q_n = schema.encode_q(torch.as_tensor(q))
    for n_steps in (None, 20):
        fast = schema.adapt_normalized(q_n, loss_fn, "default", n_steps=n_steps)
        ref = schema.adapt_normalized(q_n, loss_fn, "default", n_steps=n_steps, fast=False)
        torch.testing.assert_close(fast, ref, rtol=0, atol=F64_TOL)


# ---------------------------------------------------------------------------- the bound networks
@pytest.mark.parametrize("activation", ["silu", "tanh"])
def test_bound_eps_mlp_matches_the_module_and_autograd(activation):
    torch.manual_seed(0)
    net = EpsMLP(12, 2, activation=activation).double()
    q, x, v = (torch.randn(5, d, dtype=torch.float64) for d in (2, 12, 12))
    steps = [199, 120, 7, 0]
    bound = net.bind(q, steps)
    for i, t in enumerate(steps):
        torch.testing.assert_close(bound.eps(x, i), net(x, t, q))
        eps, vjp = bound.eps_and_vjp(x, i)
        x_req = x.clone().requires_grad_(True)
        ref_vjp, = torch.autograd.grad(net(x_req, t, q), x_req, v)
        torch.testing.assert_close(vjp(v), ref_vjp)
    with torch.no_grad():  # an in-place weight change (an optimizer step) invalidates the cached frozen weights
        net.mlp.net[0].weight.add_(0.1)
    torch.testing.assert_close(net.bind(q, steps).eps(x, 0), net(x, steps[0], q))


@pytest.mark.parametrize("n_steps", [None, 20])
def test_an_activation_without_a_hand_written_derivative_takes_the_generic_fast_loop(n_steps):
    torch.manual_seed(0)
    schedule = NoiseSchedule(200).double()
    net = EpsMLP(12, 2, activation="relu").double()
    assert net.bind(torch.zeros(1, 2, dtype=torch.float64), [199]) is None
    q, x_T = torch.randn(5, 2, dtype=torch.float64), torch.randn(5, 12, dtype=torch.float64)
    steps = None if n_steps is None else strided_timesteps(200, n_steps)

    def loss_fn(x):
        return torch.relu(x[:, :3] - 0.2).pow(2).sum(-1) + x[:, 6].pow(2)

    guidance = GuidanceConfig(0.5, "abar", n_guide=2)
    torch.testing.assert_close(guided_denoise(net, schedule, q, x_T, loss_fn, guidance, steps, fast=True),
                               guided_denoise(net, schedule, q, x_T, loss_fn, guidance, steps), rtol=0, atol=F64_TOL)


def test_bound_decoder_matches_the_module_and_autograd(latent64):
    decoder = latent64.decoder
    q, z, v = (torch.randn(4, d, dtype=torch.float64) for d in (decoder.q_dim, decoder.z_latent_dim, 12))
    frozen, bias = decoder.bind(q)
    out, vjp = frozen.forward_vjp(z, bias)
    z_req = z.clone().requires_grad_(True)
    ref = decoder(q, z_req)
    ref_vjp, = torch.autograd.grad(ref, z_req, v)
    torch.testing.assert_close(out, ref.detach())
    torch.testing.assert_close(vjp(v), ref_vjp)


def test_latent_descent_without_an_analytic_gradient_matches_the_reference(latent64):
    decoder = latent64.decoder
    q = torch.randn(3, decoder.q_dim, dtype=torch.float64)
    z0 = torch.randn(3, decoder.z_latent_dim, dtype=torch.float64)
    loss_fn = lambda x: (x - 0.3).pow(2).sum(-1) + torch.relu(x[:, :2]).pow(3).sum(-1)  # noqa: E731
    for optimizer in ("sgd", "adam"):
        config = LatentConfig(lr=0.05, n_steps=50, optimizer=optimizer)
        torch.testing.assert_close(optimize_latent(decoder, q, z0, loss_fn, config, fast=True),
                                   optimize_latent(decoder, q, z0, loss_fn, config), rtol=0, atol=F64_TOL)


# ---------------------------------------------------------------------------- the strided sampler itself
class OracleEps(torch.nn.Module):
    """Predicts the true noise of x_t for a known x0: eps = (x_t - sqrt(abar_t) x0) / sqrt(1 - abar_t)."""

    def __init__(self, schedule, x0):
        super().__init__()
        self.schedule, self.x0 = schedule, x0

    def forward(self, x_t, t, q):
        s = self.schedule
        return (x_t - s.sqrt_alpha_bars[t].to(x_t.dtype) * self.x0) / s.sqrt_one_minus_alpha_bars[t].to(x_t.dtype)


@pytest.mark.parametrize("spacing", ["quad", "linspace", "trailing"])
@pytest.mark.parametrize("eta", [0.0, 1.0])
@pytest.mark.parametrize("fast", [False, True])
def test_the_strided_sampler_with_the_true_noise_returns_the_data(spacing, eta, fast):
    """Given the exact noise, every deterministic step lands on the forward process's mean path and the
    last one returns x0 exactly, whatever the stride, eta or guidance that sees no violation."""
    torch.manual_seed(0)
    schedule = NoiseSchedule(200).double()
    x0 = torch.randn(4, 12, dtype=torch.float64)
    model = OracleEps(schedule, x0)
    x_T = torch.randn(4, 12, dtype=torch.float64)
    steps = strided_timesteps(200, 10, spacing)
    out = guided_denoise(model, schedule, None, x_T, None, timesteps=steps, eta=eta, fast=fast)
    torch.testing.assert_close(out, x0, rtol=0, atol=1e-9)

    def loss_fn(x):  # zero at x0: the guidance must leave the samples alone
        return torch.relu(x - x0 - 1.0).pow(2).sum(-1)

    guided = guided_denoise(model, schedule, None, x_T, loss_fn, GuidanceConfig(0.5, "abar", n_guide=2),
                            timesteps=steps, eta=eta, fast=fast)
    torch.testing.assert_close(guided, x0, rtol=0, atol=1e-9)


def test_deterministic_step_is_ddpm_mean_for_eta_one_and_ddim_for_eta_zero():
    schedule = NoiseSchedule(200).double()
    x, eps = torch.randn(3, 12, dtype=torch.float64), torch.randn(3, 12, dtype=torch.float64)
    for t in (199, 57, 0):
        torch.testing.assert_close(deterministic_step(schedule, x, eps, t, t - 1, 1.0),
                                   schedule.ddpm_mean_step(x, eps, t))
        torch.testing.assert_close(deterministic_step(schedule, x, eps, t, max(t - 10, -1), 0.0),
                                   schedule.ddim_step(x, eps, t, max(t - 10, -1)))
    # eta = 1 with stride 1 through the general formula (not the shortcut) is the DDPM mean step as well
    general = deterministic_step(schedule, x, eps, 57, 56, 1.0 - 1e-15)
    torch.testing.assert_close(general, schedule.ddpm_mean_step(x, eps, 57))


@pytest.mark.parametrize("spacing", ["quad", "linspace", "trailing"])
def test_strided_timesteps_are_distinct_and_descending_from_noise(spacing):
    for n in (1, 2, 10, 20, 150, 199, 200):
        steps = strided_timesteps(200, n, spacing)
        assert len(steps) == n and steps[0] == 199 and all(a > b for a, b in zip(steps, steps[1:]))
        assert steps[-1] >= 0 and (spacing == "trailing" or n == 1 or steps[-1] == 0)
    assert strided_timesteps(200, 200, spacing) == list(range(199, -1, -1))
    quad = strided_timesteps(200, 20, "quad")
    assert sum(t < 50 for t in quad) >= 10  # dense at low noise, where the guidance settles the command


# ---------------------------------------------------------------------------- API and tools
def test_sample_steps_selects_the_strided_sampler_for_infer_and_adapt(diffusion, dm):
    schema, _ = diffusion
    fast = DiffusionSchema(robot=dm.robot, sample_steps=20)
    fast.load_state_dict(schema.state_dict())
    fast.eval()
    q, faults = _faults(schema, dm, n=6)
    np.testing.assert_array_equal(fast.infer(q)[1], schema.decode(schema.generate(
        schema.encode_q(torch.as_tensor(q)), n_steps=20))[:, 6:].numpy())
    np.testing.assert_array_equal(fast.adapt(q, faults).f_n, schema.adapt(q, faults, n_steps=20).f_n)
    np.testing.assert_array_equal(fast.adapt(q, faults, n_steps=200).f_n, schema.adapt(q, faults).f_n)
    assert not np.allclose(fast.infer(q)[1], schema.infer(q)[1], atol=1e-6)  # really another sampler


@pytest.mark.parametrize("bad", [0, 201, 2.5, True, "20"])
def test_bad_step_counts_and_spacings_are_refused(diffusion, dm, bad):
    schema, _ = diffusion
    q, faults = _faults(schema, dm, n=3)
    with pytest.raises(BodySchemaInputError, match="n_steps"):
        schema.adapt(q, faults, n_steps=bad)
    with pytest.raises(BodySchemaInputError, match="sample_steps|n_steps"):
        DiffusionSchema(robot=dm.robot, sample_steps=bad)
    with pytest.raises(BodySchemaInputError, match="spacing"):
        schema.adapt(q, faults, n_steps=20, spacing="cubic")
    with pytest.raises(BodySchemaInputError, match="n_guide"):
        schema.adapt(q, faults, n_steps=20, n_guide=0)


def test_adapt_cases_runs_the_ddim20_sampler(diffusion, dm, tmp_path, capsys):
    schema, trainer = diffusion
    ckpt = tmp_path / "diff.ckpt"
    trainer.save_checkpoint(ckpt)
    q, x = dm.splits["val"]
    cases = make_fault_cases(q.numpy(), x[:, :6].numpy(), 5, 0)
    cases.save(tmp_path / "cases.npz")
    adapt_cases_main(["--ckpt", str(ckpt), "--cases", str(tmp_path / "cases.npz"), "--out", str(tmp_path / "out.npz"),
                      "--sampler", "ddim20"])
    assert "sampler ddim20" in capsys.readouterr().out
    out = load_npz(str(tmp_path / "out.npz"))
    expected = load_schema(str(ckpt)).adapt(cases.q_ref, cases.faults, n_steps=20)
    np.testing.assert_array_equal(out["f"], expected.f_n)


# ---------------------------------------------------------------------------- compiled loop and the prepared adapter
def _paper_faults(schema, dm, n=12, seed=0):
    """The paper's faults only (cut and jammed muscles): the loss the fused (and compiled) loop covers."""
    q, x = dm.splits["val"]
    cases = make_fault_cases(q.numpy(), x[:, :schema.n_muscles].numpy(), n // 3, seed)
    return cases.q_ref, cases.faults


def _compiled_commands(schema, q, faults, **options):
    from lightning_bodyschema.samplers import guided

    calls = guided.compiled_core.cache_info().hits + guided.compiled_core.cache_info().misses
    result = schema.adapt(q, faults, compiled=True, **options)
    assert guided.compiled_core.cache_info().hits + guided.compiled_core.cache_info().misses > calls, \
        "the compiled loop was not used"
    return result


def test_the_compiled_loop_returns_the_reference_commands_float64(diffusion64, dm):
    """torch.compile (inductor, C++) of the fused 20-step guided loop: the autograd reference's commands."""
    q, faults = _paper_faults(diffusion64, dm)
    options = dict(ADAPT_SAMPLERS["ddim20"])
    _assert_same_commands(_compiled_commands(diffusion64, q, faults, **options),
                          diffusion64.adapt(q, faults, fast=False, **options), F64_TOL, F64_TOL)


@pytest.mark.slow
def test_the_compiled_loop_returns_the_reference_commands_200_steps_and_unguided(diffusion, diffusion64, dm):
    q, faults = _paper_faults(diffusion64, dm)
    _assert_same_commands(_compiled_commands(diffusion64, q, faults),
                          diffusion64.adapt(q, faults, fast=False), F64_TOL, F64_TOL)
    q_n = diffusion64.encode_q(torch.as_tensor(q))
    torch.testing.assert_close(diffusion64.generate(q_n, n_steps=20, compiled=True),
                               diffusion64.generate(q_n, n_steps=20, fast=False), rtol=0, atol=1e-9)


def test_compiled_needs_the_fast_path(diffusion, dm):
    q, faults = _paper_faults(diffusion[0], dm)
    with pytest.raises(BodySchemaInputError, match="compiled=True needs the fast path"):
        diffusion[0].adapt(q, faults, fast=False, compiled=True)


def _assert_adapter_matches_adapt(schema, dm, **options):
    q, faults = _faults(schema, dm)
    adapter, expected = schema.adapter(faults, **options), schema.adapt(q, faults, **options)
    for _ in range(2):  # reusable: a controller calls it every tick
        got = adapter(q)
        assert (got.status == expected.status).all()
        np.testing.assert_array_equal(got.l_motor_m, expected.l_motor_m)
        np.testing.assert_array_equal(got.f_n, expected.f_n)
    with pytest.raises(BodySchemaInputError, match="postures but"):
        adapter(q[:1])


def test_a_prepared_adapter_returns_what_adapt_returns_diffusion(diffusion, dm):
    _assert_adapter_matches_adapt(diffusion[0], dm, n_steps=20)


def test_a_prepared_adapter_returns_what_adapt_returns_latent(latent, dm):
    _assert_adapter_matches_adapt(latent, dm)
