"""Per-muscle term budgets: the lowest degrees rise first; a muscle the budget lifts recovers a polynomial of its new
degree to 1e-9 (which the per-muscle limit alone cannot); moment arms stay exact and zero off the crossed joints;
a schema checkpoint from before the budget answers as before."""
import numpy as np
import pytest
import torch
from physics_checks import central_differences
from physics_checks import fit_structured as _fit

from lightning_bodyschema.data import EquilibriumDataModule
from lightning_bodyschema.errors import BodySchemaInputError
from lightning_bodyschema.networks.per_muscle import PerMusclePath, muscle_degrees
from lightning_bodyschema.schemas import load_schema

CROSSING = np.array([[1, 0, 0], [1, 1, 0], [0, 1, 1], [1, 1, 1]], dtype=bool)  # 4 muscles, 3 joints


@pytest.mark.parametrize("budget, degrees", [(None, [14, 4, 4, 3]), (65, [14, 4, 4, 3]), (80, [14, 4, 4, 4]),
                                             (91, [14, 5, 4, 4]), (92, [14, 5, 5, 4]), (127, [14, 6, 6, 5]),
                                             (200, [14, 7, 7, 6])])
def test_the_budget_raises_the_lowest_degree_first(budget, degrees):
    # terms: C(1 + d, 1), C(2 + d, 2), C(3 + d, 3); with at most 20 each: 15 + 15 + 15 + 20 = 65. Then the 3-joint
    # muscle 3 -> 4 (+15: 80); at degree 4 the cheapest first: the 2-joint ones (+6 each: 86, 92), then the
    # 3-joint one 4 -> 5 (+21: 113), the 2-joint 5 -> 6 (+7 each: 127), the 3-joint 5 -> 6 (+28: 155), the 2-joint
    # 6 -> 7 (+8 each: 171); the 3-joint 6 -> 7 would need +36 (207 > 200)
    assert muscle_degrees(CROSSING, 14, 20, budget).tolist() == degrees
    assert muscle_degrees(CROSSING, 5, 20, 10 ** 6).tolist() == [5, 5, 5, 5]  # never above the degree


@pytest.mark.parametrize("budget", [64, 2.5, True])
def test_a_budget_below_what_the_limit_gives_is_refused(budget):
    with pytest.raises(BodySchemaInputError, match="term budget .* must be an integer >= 65"):
        PerMusclePath(CROSSING, degree=14, n_hidden=0, max_terms=20, term_budget=budget)


def _muscle_degree(path):
    return (path.exponents.sum(1)[None, :] * path.term_mask).amax(1).tolist()


def test_a_muscle_the_budget_lifts_recovers_a_polynomial_of_its_new_degree_to_1e9():
    budgeted = PerMusclePath(CROSSING, degree=14, n_hidden=0, max_terms=20, term_budget=113).double()
    limited = PerMusclePath(CROSSING, degree=14, n_hidden=0, max_terms=20).double()
    assert _muscle_degree(budgeted) == [14, 5, 5, 5] and _muscle_degree(limited) == [14, 4, 4, 3]
    truth = torch.zeros_like(budgeted.coef).normal_(generator=torch.Generator().manual_seed(1)) * budgeted.term_mask
    x = torch.rand(4000, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(2)) * 2 - 1
    y = budgeted.basis(x)[0] @ truth.T
    budgeted.fit_polynomial(x, y)
    limited.fit_polynomial(x, y)
    torch.testing.assert_close(budgeted.coef, truth, atol=1e-9, rtol=0)
    x_new = torch.rand(300, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(3)) * 2 - 1
    y_new = budgeted.basis(x_new)[0] @ truth.T
    torch.testing.assert_close(budgeted(x_new), y_new, atol=1e-9, rtol=0)
    miss = (limited(x_new) - y_new).abs().amax(0)
    assert miss[0] < 1e-9 and (miss[1:] > 1e-3).all()  # the degree-5 parts are out of the limited basis's reach


def test_budgeted_moment_arms_are_central_differences_and_zero_off_the_crossed_joints():
    path = PerMusclePath(CROSSING, degree=14, n_hidden=0, max_terms=20, term_budget=200).double()
    with torch.no_grad():
        path.coef.normal_(generator=torch.Generator().manual_seed(4))
        path.coef.mul_(0.1)
    x = torch.rand(32, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(5)) * 2 - 1
    y, dy = path.with_jacobian(x)
    np.testing.assert_allclose(dy.numpy(), central_differences(path, x), atol=1e-7, rtol=1e-7)
    crossed = torch.as_tensor(CROSSING)
    assert (dy[:, ~crossed] == 0).all() and (dy[:, crossed].abs() > 1e-6).all()


def test_a_schema_checkpoint_from_before_the_budget_answers_as_before(tmp_path):
    schema, trainer = _fit(EquilibriumDataModule(n_samples=600, seed=0, cache_dir=None), length_model="per_muscle",
                           path_degree=10, path_terms=20, path_term_budget=176, torque_model="polynomial",
                           torque_degree=6)
    # 4 x C(11, 1) + 2 x C(12, 2) = 176: the 2-joint muscles lifted from 4 to 10
    assert _muscle_degree(schema.length_net) == [10, 10, 10, 10, 10, 10]
    path = str(tmp_path / "before_budget.ckpt")
    trainer.save_checkpoint(path, weights_only=False)
    checkpoint = torch.load(path, weights_only=True)
    del checkpoint["hyper_parameters"]["path_term_budget"]
    checkpoint["hyper_parameters"]["path_terms"] = 500  # the same degrees without a budget
    torch.save(checkpoint, path)
    loaded = load_schema(path)
    q = torch.tensor([[0.3, 0.8], [-0.2, 1.2]], dtype=torch.float64)
    for a, b in zip(schema.body_si(q), loaded.body_si(q)):
        np.testing.assert_array_equal(a, b)


def test_a_large_batch_evaluated_in_blocks_gives_the_same_body(monkeypatch):
    from lightning_bodyschema.networks import basis, per_muscle, snapshot

    monkeypatch.setattr(snapshot, "FEW_ELEMENTS", 0)  # 50 postures in blocks of rows, not the few-postures path
    monkeypatch.setattr(basis, "DENSE_ROWS", 0)  # every block through the same (grouped) basis: the blocks alone
    path = PerMusclePath(CROSSING, degree=14, n_hidden=0, max_terms=20, term_budget=200).double()
    with torch.no_grad():
        path.coef.normal_(generator=torch.Generator().manual_seed(6))
    x = torch.rand(50, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(7)) * 2.4 - 1.2  # some outside
    whole = path.with_jacobian(x)
    monkeypatch.setattr(per_muscle, "BASIS_ELEMENTS", 7 * path.coef.shape[1])  # blocks of 7 rows
    # the same sums in another order (another BLAS kernel blocks them differently): up to 84 terms of degree-14
    # Legendre products, evaluated through their monomial form (coefficients up to ~1e3), differ by tens of ulps of
    # the largest value (40 measured on one CPU); a block on the wrong rows would differ by O(1) of it
    roundings = 4 * path.coef.shape[1]  # a few per term summed (84 terms: 336 ulps)
    for a, b in zip(whole, path.with_jacobian(x)):
        torch.testing.assert_close(a, b, atol=roundings * torch.finfo(a.dtype).eps * a.abs().max().item(), rtol=0)


def test_with_a_tolerance_only_the_muscle_that_misses_it_gets_the_budget():
    from lightning_bodyschema.networks.per_muscle import degrees_within_tolerance

    truth_path = PerMusclePath(CROSSING, degree=14, n_hidden=0, degrees=[14, 4, 4, 5]).double()
    truth = torch.zeros_like(truth_path.coef).normal_(generator=torch.Generator().manual_seed(8)) * truth_path.term_mask
    x = torch.rand(4000, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(9)) * 2 - 1
    y = truth_path.basis(x)[0] @ truth.T  # muscles 0-2 within the limit's degrees [14, 4, 4]; muscle 3 of degree 5
    scale = torch.ones(4, dtype=torch.float64)
    # muscle 3 alone: 3 -> 4 (+15: 80), 4 -> 5 (+21: 101); 5 -> 6 would need +28 (129 > 113). Without the tolerance
    # the same budget goes to the 2-joint muscles first and muscle 3 ends at degree 5 only with 113 (test above).
    degrees = degrees_within_tolerance(CROSSING, x, y, scale, 14, 20, 113, 1e-6)
    assert degrees.tolist() == [14, 4, 4, 5]
    path = PerMusclePath(CROSSING, n_hidden=0, degrees=degrees).double()
    path.fit_polynomial(x, y)
    torch.testing.assert_close(path.coef, truth, atol=1e-9, rtol=0)
    assert degrees_within_tolerance(CROSSING, x, y, scale, 14, 20, 113, 1e3).tolist() == [14, 4, 4, 3]


@pytest.mark.parametrize("degrees", [[14, 4, 4], [14, 4, 4, 0], [14, 4.5, 4, 3]])
def test_bad_explicit_degrees_are_refused(degrees):
    with pytest.raises(BodySchemaInputError, match="4 integers >= 1, one per muscle"):
        PerMusclePath(CROSSING, degrees=degrees)


def test_the_degrees_a_tolerance_chose_are_stored_and_the_checkpoint_answers_the_same(tmp_path):
    # every muscle within 1 m after the first fit: nobody rises (the paper arm's paths are within reach of the limit's
    # degrees, so the rise itself is tested on a known polynomial above)
    tolerance_mm, degrees = 1e3, [10, 10, 10, 10, 4, 4]
    schema, trainer = _fit(EquilibriumDataModule(n_samples=600, seed=0, cache_dir=None), length_model="per_muscle",
                           path_degree=10, path_terms=20, path_term_budget=176, path_tolerance_mm=tolerance_mm,
                           torque_model="polynomial", torque_degree=6)
    assert schema.hparams.path_degrees == degrees
    path = str(tmp_path / "tolerance.ckpt")
    trainer.save_checkpoint(path, weights_only=False)
    loaded = load_schema(path)
    assert _muscle_degree(loaded.length_net) == degrees
    q = torch.tensor([[0.3, 0.8], [-0.2, 1.2]], dtype=torch.float64)
    for a, b in zip(schema.body_si(q), loaded.body_si(q)):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("options", [{"path_tolerance_mm": 0.1},
                                     {"path_tolerance_mm": -1.0, "path_term_budget": 10 ** 4}])
def test_a_tolerance_without_a_budget_or_not_positive_is_refused(options):
    from lightning_bodyschema.schemas import StructuredSchema

    with pytest.raises(BodySchemaInputError, match="path_tolerance_mm"):
        StructuredSchema(length_model="per_muscle", robot=EquilibriumDataModule(cache_dir=None).robot, **options)


def test_a_trimmed_fit_recovers_a_polynomial_despite_wild_samples():
    path = PerMusclePath(CROSSING, degree=4, n_hidden=0).double()
    truth = torch.zeros_like(path.coef).normal_(generator=torch.Generator().manual_seed(10)) * path.term_mask
    x = torch.rand(3000, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(11)) * 2 - 1
    y = path.basis(x)[0] @ truth.T
    wild = y.clone()
    wild[:5] += 1e4  # five samples a thousand times off, as a moment arm that swings between samples makes
    keep = path.fit_trimmed(x, wild)
    assert keep[5:].all() and not keep[:5].any()
    torch.testing.assert_close(path.coef, truth, atol=1e-9, rtol=0)
    path.fit_polynomial(x, wild)  # the plain least squares follows them
    assert float((path.coef - truth).abs().max()) > 1.0
