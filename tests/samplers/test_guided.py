"""The fast guided-denoising loop (eager and compiled) returns the autograd reference's commands.

Equality is checked in float64 (1e-5, measured ~1e-12) and, with the float32 models the package ships,
within tolerances a few times the reference's own float32 error. Nothing here is timed
(tools/bench_adaptation.py measures speed).
"""
import numpy as np
import pytest
import torch
from physics_checks import assert_same_commands, mixed_faults

from lightning_bodyschema.errors import BodySchemaInputError
from lightning_bodyschema.evaluation import make_fault_cases
from lightning_bodyschema.faults import Faults
from lightning_bodyschema.networks import EpsMLP
from lightning_bodyschema.samplers import GuidanceConfig, NoiseSchedule, guided, reference_loop

F64_TOL = 1e-5
F32_TOL_N, F32_TOL_M = 0.05, 2e-5  # float32: 0.05 N of tension, 20 um of motor length (reference's own: ~0.02 N)
SAMPLERS = {
    "ddpm200": {},
    "strided20": dict(n_steps=20),
    "strided20_one_guide_trailing_eta0": dict(n_steps=20, n_guide=1, min_abar=0.0, eta=0.0, spacing="trailing"),
    "linspace7_three_guides": dict(n_steps=7, n_guide=3, min_abar=0.0, spacing="linspace"),
    # the paper's SI-unit loss (stable with sqrt(abar) scaling and 20 steps on this briefly trained model; with
    # 200 steps it runs away to ~1e8 m on some cases, where two chaotic trajectories cannot be compared)
    "literal_sqrt_abar_strided20": dict(variant="literal", step_scale="sqrt_abar", n_steps=20),
    "guided_no_inpainting": dict(variant="guided"),
    "inpaint_box_every_step_strided20": dict(variant="inpaint_box", n_steps=20, min_abar=0.0),
    "inpaint_spring_every_step": dict(variant="inpaint_spring"),
}


@pytest.mark.parametrize("sampler", sorted(SAMPLERS))
def test_fast_guided_denoising_returns_the_reference_commands_float64(diff60_f64, dm, sampler):
    q, faults = mixed_faults(diff60_f64, dm)
    assert_same_commands(diff60_f64.adapt(q, faults, **SAMPLERS[sampler]),
                         diff60_f64.adapt(q, faults, fast=False, **SAMPLERS[sampler]), F64_TOL, F64_TOL)


@pytest.mark.parametrize("sampler", ["ddpm200", "strided20", "literal_sqrt_abar_strided20"])
def test_fast_guided_denoising_float32_within_tolerance(diff60, dm, sampler):
    schema = diff60[0]
    q, faults = mixed_faults(schema, dm)
    assert_same_commands(schema.adapt(q, faults, **SAMPLERS[sampler]),
                         schema.adapt(q, faults, fast=False, **SAMPLERS[sampler]), F32_TOL_N, F32_TOL_M)


@pytest.mark.parametrize("n_steps", [None, 20])
@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-9), (torch.float32, 1e-5)])
def test_fast_unguided_sampling_returns_the_reference_sample(diff60, diff60_f64, dm, n_steps, dtype, tol):
    schema = diff60_f64 if dtype == torch.float64 else diff60[0]
    q_n = schema.encode_q(dm.splits["val"][0][:9])
    torch.testing.assert_close(schema.generate(q_n, n_steps=n_steps), schema.generate(q_n, n_steps=n_steps, fast=False),
                               rtol=0, atol=tol)


@pytest.mark.parametrize("n_steps", [None, 20])
def test_inpainting_leaves_no_jam_cut_or_band_broken_where_guidance_alone_does(diff60_f64, dm, n_steps):
    """The default inpaints the predicted x0 at the low-noise steps; its last step is x0 := P(x0), so the raw
    output (before the safe-command clipping) meets every fault exactly."""
    q, faults = mixed_faults(diff60_f64, dm)
    inpainted = diff60_f64.adapt(q, faults, n_steps=n_steps, check_physics=False).diagnostics
    guided_only = diff60_f64.adapt(q, faults, variant="guided", n_steps=n_steps, check_physics=False).diagnostics
    with np.errstate(invalid="ignore"):  # a jam below its own band's floor: no length meets both
        contradictory = (faults.fix & faults.band & (faults.l_fixed_m < faults.l_band_m[..., 0])).any(1)
    assert 0 < contradictory.sum() < len(q)
    for name in ("cut_violation_n", "jam_violation_m", "band_violation_m", "weak_violation_n"):
        assert np.nanmax(inpainted[name][~contradictory]) < 1e-9, name
    assert max(np.nanmax(guided_only[name]) for name in ("jam_violation_m", "band_violation_m")) > 1e-5


@pytest.mark.parametrize("variant", ["recurrent", "projected"])
def test_reference_only_variants_run_from_the_fast_path_and_meet_the_faults_better_than_none(diff60_f64, dm, variant):
    q, faults = mixed_faults(diff60_f64, dm, n=6)
    fast = diff60_f64.adapt(q, faults, variant=variant, n_steps=20, check_physics=False)
    ref = diff60_f64.adapt(q, faults, variant=variant, n_steps=20, fast=False, check_physics=False)
    assert_same_commands(fast, ref, 1e-12, 1e-12)  # the fast path hands these to the reference loop
    plain_l = diff60_f64.infer(q)[0]
    jam = faults.fix
    assert (fast.status == "ok").all()
    broken_before = np.maximum(plain_l - faults.l_fixed_m, 0.0)[jam].sum()
    assert np.maximum(fast.l_motor_m - faults.l_fixed_m, 0.0)[jam].sum() < 0.5 * broken_before


def test_a_case_adapts_the_same_alone_or_in_a_batch_with_the_strided_sampler(diff60_f64, dm):
    q, faults = mixed_faults(diff60_f64, dm, n=6)
    batch = diff60_f64.adapt(q, faults, n_steps=20)
    for i in (0, 4):
        alone = diff60_f64.adapt(q[i:i + 1], faults.take([i]), n_steps=20)
        np.testing.assert_allclose(alone.f_n[0], batch.f_n[i], rtol=0, atol=1e-9)


def test_the_literal_recipe_still_diverges_on_the_fast_path_and_is_never_returned(diff60, dm):
    schema = diff60[0]
    q = dm.splits["val"][0][:4].numpy()
    faults = Faults.from_names(schema.robot_model.muscle_names, cut=[["shoulder_flexor"]] * 4)
    result = schema.adapt(q, faults, variant="literal")
    assert (result.status == "non_finite").all() and np.isnan(result.f_n).all()


def test_an_activation_without_a_hand_written_derivative_runs_the_reference():
    """ReLU has no FrozenMLP: fast=True falls back to the autograd reference and still guides."""
    torch.manual_seed(0)
    schedule = NoiseSchedule(200).double()
    net = EpsMLP(12, 2, activation="relu").double()
    assert net.frozen() is None
    q, x_T = torch.randn(5, 2, dtype=torch.float64), torch.randn(5, 12, dtype=torch.float64)

    class Squares:  # a penalty value: called for the loss
        def __call__(self, x):
            return torch.relu(x[:, :3] - 0.2).pow(2).sum(-1) + x[:, 6].pow(2)

    guidance = GuidanceConfig(0.5, "abar", n_guide=2)
    guided_x0 = reference_loop(net, schedule, q, x_T, Squares(), guidance, schedule.timesteps(20))
    plain_x0 = reference_loop(net, schedule, q, x_T, None, guidance, schedule.timesteps(20))
    assert Squares()(guided_x0).sum() < 0.1 * Squares()(plain_x0).sum()


# ---------------------------------------------------------------------------- the compiled loop
def _paper_faults(schema, dm, n=12, seed=0):
    q, x = dm.splits["val"]
    cases = make_fault_cases(q.numpy(), x[:, :schema.n_muscles].numpy(), n // 3, seed)
    return cases.q_ref, cases.faults


def _compiled_commands(schema, q, faults, **options):
    calls = guided.compiled_sampler.cache_info().hits + guided.compiled_sampler.cache_info().misses
    result = schema.adapt(q, faults, compiled=True, **options)
    assert guided.compiled_sampler.cache_info().hits + guided.compiled_sampler.cache_info().misses > calls, \
        "the compiled loop was not used"
    return result


def test_the_compiled_sampler_returns_the_reference_commands_float64(diff60_f64, dm):
    """torch.compile (inductor, C++) of the one loop body, 20 guided steps: the autograd reference's commands."""
    q, faults = _paper_faults(diff60_f64, dm)
    assert_same_commands(_compiled_commands(diff60_f64, q, faults, n_steps=20),
                         diff60_f64.adapt(q, faults, fast=False, n_steps=20), F64_TOL, F64_TOL)


@pytest.mark.slow
def test_the_compiled_sampler_returns_the_reference_commands_200_steps_and_unguided(diff60_f64, dm):
    q, faults = _paper_faults(diff60_f64, dm)
    assert_same_commands(_compiled_commands(diff60_f64, q, faults),
                         diff60_f64.adapt(q, faults, fast=False), F64_TOL, F64_TOL)
    q_n = diff60_f64.encode_q(torch.as_tensor(q))
    torch.testing.assert_close(diff60_f64.generate(q_n, n_steps=20, compiled=True),
                               diff60_f64.generate(q_n, n_steps=20, fast=False), rtol=0, atol=1e-9)


def test_compiled_needs_the_fast_path(diff60, dm):
    q, faults = _paper_faults(diff60[0], dm)
    with pytest.raises(BodySchemaInputError, match="compiled=True needs the fast path"):
        diff60[0].adapt(q, faults, fast=False, compiled=True)
