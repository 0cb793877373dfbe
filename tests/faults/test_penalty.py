"""The adaptation loss as a value: the box penalty equals the paper's L_adapt (eq:latent-opt) and its gradient is exact."""
import numpy as np
import pytest
import torch
from physics_checks import rounding_tol

from lightning_bodyschema.faults import AdaptWeights, Faults, PenaltyBuilder, Rupture
from lightning_bodyschema.faults.constraints import LengthBand

M = 6
rng = np.random.default_rng(0)
MEAN = np.concatenate([rng.uniform(0.2, 0.5, M), rng.uniform(30, 90, M)])  # l_motor [m], f [N]
STD = np.concatenate([rng.uniform(0.003, 0.01, M), rng.uniform(10, 40, M)])


def paper_loss(l_motor, f, faults, f_max, w: AdaptWeights, l_scale, f_scale):
    """eq:latent-opt written out in SI units (plus the band term), per case: the yardstick."""
    relu = lambda a: np.maximum(a, 0.0)  # noqa: E731
    term = lambda mask, r: np.where(mask, r ** 2, 0.0).sum(-1)  # noqa: E731
    lo, hi = np.moveaxis(np.nan_to_num(faults.l_band_m), -1, 0)
    healthy = ~faults.cut
    return (w.c_cut * term(faults.cut, f / f_scale)
            + w.c_fix * term(faults.fix, relu(l_motor - np.nan_to_num(faults.l_fixed_m)) / l_scale)
            + w.c_fmin * term(healthy, relu(-f) / f_scale)
            + w.c_fmax * term(healthy, relu(f - f_max) / f_scale)
            + w.c_band * term(faults.band, (relu(lo - l_motor) + relu(l_motor - hi)) / l_scale))


def some_faults(n):
    cut, fix = np.zeros((n, M), bool), np.zeros((n, M), bool)
    cut[np.arange(n), rng.integers(0, 3, n)] = True
    fix[np.arange(n), rng.integers(3, 6, n)] = True
    l_fixed = np.where(fix, MEAN[:M] + rng.normal(0, 0.005, (n, M)), np.nan)
    f_max = np.full((n, M), np.nan)
    f_max[::2, 3] = 40.0
    band = np.full((n, M, 2), np.nan)
    j = np.flatnonzero(fix[0])[0]
    band[0, j] = [MEAN[j] - 0.004, MEAN[j] - 0.001]  # a band on a jammed motor: two upper bounds, two slots
    band[1, 1] = [MEAN[1] - 0.002, MEAN[1] + 0.002]
    return Faults(cut, fix, l_fixed, np.where(cut, np.nan, f_max), band)


@pytest.mark.parametrize("variant", ["default", "literal"])
def test_penalty_is_the_papers_loss_and_its_gradient_is_exact(variant):
    n, f_max = 24, 150.0
    faults = some_faults(n)
    weights, l_scale, f_scale = ((AdaptWeights(), 1.0, 1.0) if variant == "literal"
                                 else (AdaptWeights(1.0, 1.0, 1.0, 1.0, 1.0), STD[:M], STD[M:]))
    penalty = PenaltyBuilder(weights, l_scale, f_scale, MEAN, STD, torch.float64)(faults.constraints(f_max))
    assert len(penalty.slots) == 2  # the jam and the band of case 0 cannot share a box
    x_n = torch.tensor(3.0 * rng.standard_normal((n, 2 * M)), requires_grad=True)
    x = x_n.detach().numpy() * STD + MEAN
    expected = paper_loss(x[:, :M], x[:, M:], faults, faults.f_limit(f_max), weights, l_scale, f_scale)
    loss = penalty(x_n)
    # near 0 (a case barely violating): a few roundings per element (to SI, the distance, its scale, the square)
    # and the sum over the elements, at the loss's and the gradient's scale (~5e-12); a term missed is O(1)
    roundings = 8 * x_n.shape[1]
    np.testing.assert_allclose(loss.detach().numpy(), expected, rtol=1e-10, atol=rounding_tol(roundings, expected))
    grad, = torch.autograd.grad(loss.sum(), x_n)
    torch.testing.assert_close(penalty.grad(x_n.detach()), grad, rtol=1e-10, atol=rounding_tol(roundings, grad))


def test_the_usual_loss_is_one_slot_of_uniform_weight():
    """Cuts, jams and the tension bounds under the default units: one box per element, every weight 2 (w2 = 2w)."""
    faults = Faults.from_names([f"m{i}" for i in range(M)], cut=[[0], [1]], jam=[{3: 0.3}, {4: 0.31}])
    penalty = PenaltyBuilder(AdaptWeights(1.0, 1.0, 1.0, 1.0, 1.0), STD[:M], STD[M:], MEAN, STD,
                             torch.float64)(faults.constraints(150.0))
    assert len(penalty.slots) == 1 and penalty.uniform_weight == 2.0
    x = torch.randn(2, 2 * M, dtype=torch.float64)
    torch.testing.assert_close(penalty.grad(x), 2.0 * penalty.residual(x))


def test_any_constraint_that_states_its_bounds_joins_the_penalty():
    """A new fault kind needs no change to the penalty: it states its column, interval and weight."""

    class Brake(Rupture):  # same interval and weight as a rupture under another name
        pass

    faults = some_faults(4)
    constraints = faults.constraints(150.0)
    builder = PenaltyBuilder(AdaptWeights(), 1.0, 1.0, MEAN, STD, torch.float64)
    braked = [Brake(constraints[0].mask)] + constraints[1:]
    x = torch.randn(4, 2 * M, dtype=torch.float64)
    torch.testing.assert_close(builder(braked)(x), builder(constraints)(x))


def test_length_band_states_its_interval_and_violation():
    l_motor = np.array([[0.09, 0.11, 0.13]])
    band = LengthBand(np.ones((1, 3), bool), np.full((1, 3), 0.10), np.full((1, 3), 0.12))
    assert band.weight_name == "c_band" and AdaptWeights().c_band == AdaptWeights().c_fix
    np.testing.assert_allclose(band.violation(l_motor, None), [0.01])
    builder = PenaltyBuilder(AdaptWeights(c_band=2.0), 0.01, 1.0, np.zeros(6), np.ones(6), torch.float64)
    x = torch.tensor([[0.09, 0.11, 0.13, 0.0, 0.0, 0.0]], dtype=torch.float64, requires_grad=True)
    loss = builder([band])(x)
    torch.testing.assert_close(loss, torch.tensor([4.0], dtype=torch.float64))  # 2 * (1^2 + 0 + 1^2)
    loss.sum().backward()
    assert x.grad[0, 1] == 0 and x.grad[0, 0] < 0 < x.grad[0, 2]
