"""NoiseSchedule: the update rules must undo the forward process exactly when fed the true noise."""
import pytest
import torch
from physics_checks import rounding_tol

from lightning_bodyschema.errors import BodySchemaInputError
from lightning_bodyschema.samplers import NoiseSchedule

B, D = 16, 12  # batch, x = [l_motor, f] for 6 muscles


@pytest.fixture
def sched():
    return NoiseSchedule(200)


@pytest.fixture
def data():
    g = torch.Generator().manual_seed(0)
    return torch.randn(B, D, generator=g, dtype=torch.float64), torch.randn(B, D, generator=g, dtype=torch.float64)


def true_eps(sched, x_t, x0, t):
    """The noise that x_t actually carries at level t: eps = (x_t - sqrt(abar_t) x0) / sqrt(1 - abar_t)."""
    abar = sched.alpha_bars[t]
    return (x_t - abar.sqrt() * x0) / (1.0 - abar).sqrt()


def test_schedule_endpoints_and_monotone(sched):
    # x_T must be (almost) pure noise and x_0 (almost) clean data, or sampling starts off-distribution
    assert sched.alpha_bars[-1] < 1e-2
    assert sched.alpha_bars[0] > 0.99
    assert torch.all(torch.diff(sched.betas) > 0)
    assert torch.all((sched.betas > 0) & (sched.betas < 1))
    assert torch.allclose(sched.alpha_bars, torch.cumprod(1 - sched.betas, 0))


def test_unrescaled_range_is_not_noise_at_T200():
    # the reason for the 1000/T rescaling (docs/design.md, noise schedule): the T = 1000 range over 200 steps keeps ~13% signal
    plain = NoiseSchedule(200, rescale_to_1000=False)
    assert 0.1 < plain.alpha_bars[-1] < 0.2


def posterior_mean(sched, x_t, x0, t):
    """Ho et al. (2020) eq. 7, the x0-form of E[x_{t-1} | x_t, x0] -- independent of the eps form."""
    abar, abar_prev = sched.alpha_bars[t], sched.alpha_bars[t - 1] if t > 0 else torch.tensor(1.0, dtype=torch.float64)
    beta, alpha = sched.betas[t], sched.alphas[t]
    return (abar_prev.sqrt() * beta * x0 + alpha.sqrt() * (1 - abar_prev) * x_t) / (1 - abar)


def test_ddpm_mean_loop_with_true_noise_recovers_x0(sched, data):
    x0, eps = data
    T = sched.n_timesteps
    x = sched.add_noise(x0, eps, T - 1)
    for t in range(T - 1, -1, -1):
        x_next = sched.step(x, true_eps(sched, x, x0, t), t, t - 1, eta=1.0)  # eq:diff-2 without its noise term
        # every step, not only the end (the last step alone returns x0 whatever x is): with the true
        # noise, eq:diff-2 must be the exact posterior mean of q(x_{t-1} | x_t, x0)
        assert torch.allclose(x_next, posterior_mean(sched, x, x0, t), atol=1e-10, rtol=0), t
        x = x_next
    assert torch.allclose(x, x0, atol=1e-5, rtol=0)


def test_the_mean_step_is_the_papers_eq_diff_2():
    """eta = 1, stride 1: x_{t-1} = (x_t - (1 - a_t) / sqrt(1 - abar_t) eps) / sqrt(a_t), as printed."""
    sched = NoiseSchedule(200).double()
    x, eps = torch.randn(3, D, dtype=torch.float64), torch.randn(3, D, dtype=torch.float64)
    for t in (199, 57, 1, 0):
        printed = (x - sched.betas[t] / sched.sqrt_one_minus_alpha_bars[t] * eps) / sched.sqrt_alphas[t]
        # the step's coefficients by other identities of abar (square roots, a cancellation in ce): a few tens of
        # roundings at the update's terms, (|x| + |eps|) / sqrt(a_t) (~4e-14); another step's beta is off by 1e-4
        tol = rounding_tol(32, (x.abs() + eps.abs()) / sched.sqrt_alphas[t])
        torch.testing.assert_close(sched.step(x, eps, t, t - 1, eta=1.0), printed, rtol=0, atol=tol)


@pytest.mark.parametrize("spacing", ["quad", "linspace", "trailing"])
def test_ddim_strided_loop_with_true_noise_stays_on_the_forward_path(sched, data, spacing):
    x0, eps = data
    ts = sched.timesteps(20, spacing)
    x = sched.add_noise(x0, eps, ts[0])
    for t, t_prev in zip(ts, ts[1:] + [-1]):
        x_next = sched.step(x, true_eps(sched, x, x0, t), t, t_prev, eta=0.0)
        if t_prev >= 0:  # DDIM keeps the same noise: x_{t_prev} is exactly add_noise(x0, eps, t_prev)
            assert torch.allclose(x_next, sched.add_noise(x0, eps, t_prev), atol=1e-10)
        x = x_next
    assert torch.allclose(x, x0, atol=1e-9, rtol=0)


def test_predict_x0_inverts_add_noise_per_sample_t(sched, data):
    x0, eps = data
    t = torch.randint(0, sched.n_timesteps, (B,), generator=torch.Generator().manual_seed(1))
    x_t = sched.add_noise(x0, eps, t)
    assert torch.allclose(sched.predict_x0(x_t, eps, t), x0, atol=1e-9, rtol=0)
    # per-sample t really is per sample: row i matches the int-t call at t[i]
    i = 3
    assert torch.allclose(x_t[i], sched.add_noise(x0[i:i + 1], eps[i:i + 1], int(t[i]))[0])


def test_float32_inputs_stay_float32(sched):
    x = torch.randn(B, D)
    assert sched.step(x, x, 10, 9).dtype == torch.float32


@pytest.mark.parametrize("spacing", ["quad", "linspace", "trailing"])
def test_strided_timesteps_are_distinct_and_descending_from_noise(sched, spacing):
    for n in (1, 2, 7, 10, 20, 150, 199, 200):
        steps = sched.timesteps(n, spacing)
        assert len(steps) == n and steps[0] == 199 and all(a > b for a, b in zip(steps, steps[1:]))
        assert steps[-1] >= 0 and (spacing == "trailing" or n == 1 or steps[-1] == 0)
    assert sched.timesteps(200, spacing) == list(range(199, -1, -1))
    assert sum(t < 50 for t in sched.timesteps(20, "quad")) >= 10  # dense at low noise, where guidance settles


@pytest.mark.parametrize("n", [0, -3, 201, 2.5])
def test_bad_n_steps_raises(sched, n):
    with pytest.raises(BodySchemaInputError, match="n_steps"):
        sched.timesteps(n)
    with pytest.raises(BodySchemaInputError, match="spacing"):
        sched.timesteps(20, "cubic")


@pytest.mark.parametrize("T", [1, 0, -5, 10])  # T = 10 would need betas up to 2 after rescaling
def test_bad_T_raises(T):
    with pytest.raises(BodySchemaInputError):
        NoiseSchedule(T)


def test_out_of_range_t_raises(sched, data):
    x0, eps = data
    with pytest.raises(BodySchemaInputError, match="t=200"):
        sched.add_noise(x0, eps, 200)
    with pytest.raises(BodySchemaInputError, match="allowed"):  # -1 would wrap to T-1 silently
        sched.predict_x0(x0, eps, torch.full((B,), -1))
    with pytest.raises(BodySchemaInputError, match="t_prev"):
        sched.step(x0, eps, 10, 10)
    with pytest.raises(BodySchemaInputError, match="eta"):
        sched.step(x0, eps, 10, 9, eta=1.5)
