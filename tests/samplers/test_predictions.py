"""Prediction types (eps, x0, v): the schedule's one conversion recovers the truth, every sampler path goes through
it (fused eager loop = autograd reference, guided and inpainting), and x0 and v schemas learn the paper arm."""
import numpy as np
import pytest
import torch
from physics_checks import mixed_faults, rounding_tol, torque_residual, train_schema

from lightning_bodyschema.errors import BodySchemaInputError
from lightning_bodyschema.samplers import PREDICTIONS, NoiseSchedule
from lightning_bodyschema.schemas import DiffusionSchema, load_schema


@pytest.fixture(scope="module")
def sched():
    return NoiseSchedule(200).double()


@pytest.mark.parametrize("prediction", PREDICTIONS)
def test_the_conversion_recovers_x0_and_eps_from_the_true_output(sched, prediction):
    gen = torch.Generator().manual_seed(0)
    x0, eps = torch.randn(64, 12, generator=gen, dtype=torch.float64), torch.randn(64, 12, generator=gen,
                                                                                   dtype=torch.float64)
    t = torch.randint(0, 200, (64,), generator=gen)
    # x0 and eps out of x_t and the output divide by sqrt(abar) or sqrt(1 - abar) (down to 0.01 at t = 0): a few
    # roundings at the data's scale times that gain (~7e-13); a coefficient of another step is off by O(0.01)
    gain = 1.0 / torch.minimum(sched.sqrt_alpha_bars, sched.sqrt_one_minus_alpha_bars).min().item()
    tol = rounding_tol(4, x0, eps) * gain  # x_t: two products and a sum; back: two products and a difference
    for step in (t, 0, 117, 199):  # per-sample steps (training) and one step for the batch (sampling)
        x_t = sched.add_noise(x0, eps, step)
        x0_hat, eps_hat = sched.split_output(sched.training_target(x0, eps, step, prediction), x_t, step, prediction)
        torch.testing.assert_close(x0_hat, x0, rtol=0, atol=tol)
        torch.testing.assert_close(eps_hat, eps, rtol=0, atol=tol)


@pytest.mark.parametrize("prediction", PREDICTIONS)
def test_any_output_gives_a_pair_the_forward_process_joins_back_into_x_t(sched, prediction):
    gen = torch.Generator().manual_seed(1)
    x_t, out = torch.randn(8, 12, generator=gen, dtype=torch.float64), torch.randn(8, 12, generator=gen,
                                                                                 dtype=torch.float64)
    for t in (0, 50, 199):
        x0_hat, eps_hat = sched.split_output(out, x_t, t, prediction)
        torch.testing.assert_close(sched.add_noise(x0_hat, eps_hat, t), x_t, rtol=0, atol=1e-10)
        a = sched.output_affine(t, prediction)  # the float coefficients the fused plan folds in
        (ax, bx), (ae, be) = a.x0_coefficients(), a.eps_coefficients()
        torch.testing.assert_close(ax * x_t + bx * out, x0_hat, rtol=0, atol=1e-9)
        torch.testing.assert_close(ae * x_t + be * out, eps_hat, rtol=0, atol=1e-9)


@pytest.mark.parametrize("gamma", [0.5, 5.0])
def test_min_snr_weights_make_every_type_weigh_the_x0_error_by_min_snr_gamma(sched, gamma):
    gen = torch.Generator().manual_seed(2)
    x0, eps = torch.randn(200, 12, generator=gen, dtype=torch.float64), torch.randn(200, 12, generator=gen,
                                                                                    dtype=torch.float64)
    t = torch.arange(200)
    x_t = sched.add_noise(x0, eps, t)
    wrong_x0 = x0 + 0.1 * torch.randn(200, 12, generator=gen, dtype=torch.float64)
    snr = sched.alpha_bars / (1 - sched.alpha_bars)
    expected = snr.clamp(max=gamma) * (wrong_x0 - x0).pow(2).sum(-1)
    for prediction in PREDICTIONS:
        wrong_eps = (x_t - sched.sqrt_alpha_bars[:, None] * wrong_x0) / sched.sqrt_one_minus_alpha_bars[:, None]
        output = sched.training_target(wrong_x0, wrong_eps, t, prediction)  # the output that implies wrong_x0
        error = (output - sched.training_target(x0, eps, t, prediction)).pow(2).sum(-1)
        torch.testing.assert_close(sched.min_snr_weight(t, gamma, prediction) * error, expected, rtol=1e-9, atol=0)


def test_unknown_predictions_and_gammas_are_refused(sched, dm):
    with pytest.raises(BodySchemaInputError, match=r"unknown prediction 'sample'; allowed: \['eps', 'x0', 'v'\]"):
        DiffusionSchema(robot=dm.robot, prediction="sample")
    with pytest.raises(BodySchemaInputError, match="prediction 'epsilon'"):
        sched.split_output(torch.zeros(1, 2), torch.zeros(1, 2), 3, "epsilon")
    with pytest.raises(BodySchemaInputError, match="min_snr_gamma"):
        DiffusionSchema(robot=dm.robot, min_snr_gamma=0.0)


# ---------------------------------------------------------------------------- every sampler path, per type
@pytest.fixture(scope="module", params=PREDICTIONS)
def random_schema(request, dm):
    """A randomly initialised float64 schema of the paper arm predicting ``prediction``, with the data's
    normalizer."""
    torch.manual_seed(0)
    schema = DiffusionSchema(robot=dm.robot, prediction=request.param)
    schema.normalizer.load_state_dict(dm.normalizer.state_dict())
    return schema.double().eval()


def _normalized(schema, dm):
    q, faults = mixed_faults(schema, dm)
    penalty = schema.penalty_builder("default")(faults.constraints(schema.spring.f_max_n))
    return schema.encode_q(torch.as_tensor(q)), penalty


def _same(fast, ref):
    """Equal up to float64 rounding, relative to the sample's size (a random eps network's samples are large)."""
    assert torch.isfinite(ref).all() and (fast - ref).abs().max() <= 1e-10 * (1.0 + ref.abs().max())


@pytest.mark.parametrize("variant,n_steps,options", [("guided", None, {"lr": 0.1}), ("default", None, {"lr": 0.1}),
                                                     ("default", 20, {}), ("inpaint_box", 7, {"eta": 0.0})])
def test_the_fused_loop_returns_the_reference_for_every_prediction(random_schema, dm, variant, n_steps, options):
    q_n, penalty = _normalized(random_schema, dm)
    fast = random_schema.adapt_normalized(q_n, penalty, variant, n_steps=n_steps, **options)
    _same(fast, random_schema.adapt_normalized(q_n, penalty, variant, n_steps=n_steps, fast=False, **options))
    unguided = random_schema.generate(q_n, n_steps=n_steps, eta=options.get("eta"))
    assert (fast - unguided).abs().max() > 1e-3  # the guidance did act
    _same(unguided, random_schema.generate(q_n, n_steps=n_steps, eta=options.get("eta"), fast=False))


@pytest.mark.slow
def test_the_compiled_loop_returns_the_reference_for_every_prediction(random_schema, dm):
    q_n, penalty = _normalized(random_schema, dm)
    compiled = random_schema.adapt_normalized(q_n, penalty, "default", n_steps=20, compiled=True)
    _same(compiled, random_schema.adapt_normalized(q_n, penalty, "default", n_steps=20, fast=False))


# ---------------------------------------------------------------------------- training
@pytest.mark.parametrize("prediction", ["x0", "v"])
def test_x0_and_v_schemas_learn_the_paper_arm(dm, prediction, tmp_path):
    """60 epochs: the loss on a fixed batch falls, the healthy command holds its posture far better than the
    untrained network's (torque residual of the MuJoCo model), and the checkpoint brings the type back."""
    torch.manual_seed(0)
    untrained = DiffusionSchema(robot=dm.robot, prediction=prediction, min_snr_gamma=5.0)
    untrained.normalizer.load_state_dict(dm.normalizer.state_dict())
    untrained.eval()
    trained, trainer, _ = train_schema(DiffusionSchema, 60, dm, prediction=prediction, min_snr_gamma=5.0)
    q_n, x_n = trained.encode_q(dm.splits["val"][0][:256]), trained.normalizer.encode_x(dm.splits["val"][1][:256])
    losses = []
    for schema in (untrained, trained):
        torch.manual_seed(1)
        with torch.no_grad():
            losses.append(float(schema.training_loss(q_n, x_n.to(q_n.dtype))[0]))
    assert losses[1] < 0.6 * losses[0]
    q = dm.splits["val"][0][:64].numpy()
    before, after = (np.median(torque_residual(trained.robot_model, q, s.infer(q)[1])) for s in (untrained, trained))
    assert np.isfinite(after) and after < 0.2 * before
    trainer.save_checkpoint(tmp_path / "x.ckpt")
    loaded = load_schema(str(tmp_path / "x.ckpt"))
    assert (loaded.prediction, loaded.hparams.min_snr_gamma) == (prediction, 5.0)
    np.testing.assert_array_equal(loaded.infer(q)[1], trained.infer(q)[1])
