"""Two-branch paths (networks.branches): a length that jumps across a known surface, recovered from samples alone."""
import numpy as np
import pytest
import torch
from physics_checks import central_differences, assert_exports_with_a_dynamic_batch

from lightning_bodyschema.errors import BodySchemaInputError
from lightning_bodyschema.networks.branches import otsu_labels
from lightning_bodyschema.networks.per_muscle import PerMusclePath

CROSSING = np.array([[1, 1, 0], [0, 1, 0], [1, 0, 1]], dtype=bool)  # muscle 0 jumps; 1 and 2 are smooth


def _surface(x):
    """The switching surface of muscle 0: its second branch where this is > 0."""
    return x[:, 0] + 0.3 * x[:, 1] - 0.2


def _truth(path):
    """Three random polynomials of degree <= 3 (each on its muscle's joints) and muscle 0's second branch, which
    is its first plus 1.5 and a different slope (a jump of 0.9 to 2.1, the same sign all along the surface)."""
    g = torch.Generator().manual_seed(3)
    low = (path.exponents.sum(1) <= 3)[None, :] & path.term_mask
    first = torch.randn(path.coef.shape, dtype=torch.float64, generator=g) * low
    linear = (path.exponents.sum(1) == 1) & path.term_mask[0]
    second = first[0] + 0.3 * torch.randn(path.coef.shape[1], dtype=torch.float64, generator=g) * linear
    second[0] += 1.5  # the constant term
    return first, second


def _lengths(path, first, second, x):
    phi = path.basis(x)[0]
    y = phi @ first.T
    y[:, 0] = torch.where(_surface(x) > 0, phi @ second, y[:, 0])
    return y


@pytest.fixture(scope="module")
def fitted():
    path = PerMusclePath(CROSSING, degree=8, n_hidden=0, branches=2, gate_degree=2).double()
    first, second = _truth(path)
    x = torch.rand(20000, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(4)) * 2 - 1
    path.fit_polynomial(x, _lengths(path, first, second, x))
    return path, first, second


def test_a_jump_across_a_known_surface_is_recovered_to_1e9_away_from_it(fitted):
    path, first, second = fitted
    assert path.branched.tolist() == [True, False, False]  # only the muscle whose path jumps
    x = torch.rand(4000, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(5)) * 1.98 - 0.99
    x = x[_surface(x).abs() > 0.05]
    torch.testing.assert_close(path(x), _lengths(path, first, second, x), atol=1e-9, rtol=0)
    one = PerMusclePath(CROSSING, degree=8, n_hidden=0).double()  # a smooth polynomial rings around the jump
    one.fit_polynomial(x, _lengths(path, first, second, x))
    assert float((one(x) - _lengths(path, first, second, x))[:, 0].abs().median()) > 1e-3


def test_moment_arms_are_the_active_branch_slope_and_zero_off_the_crossed_joints(fitted):
    path = fitted[0]
    x = torch.rand(500, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(6)) * 1.8 - 0.9
    x = x[_surface(x).abs() > 0.05]
    y, dy = path.with_jacobian(x)
    np.testing.assert_allclose(dy.numpy(), central_differences(path, x), atol=1e-7, rtol=1e-7)
    assert (dy[:, ~torch.as_tensor(CROSSING)] == 0).all()


def test_the_length_jumps_where_the_gate_switches(fitted):
    path, first, second = fitted
    t = torch.linspace(-0.9, 0.9, 2001, dtype=torch.float64)
    x = torch.stack([t, torch.zeros_like(t), torch.zeros_like(t)], 1)  # across the surface at x0 = 0.2
    y = path(x)[:, 0]
    jump = int(torch.argmax((y[1:] - y[:-1]).abs()))
    assert abs(float(t[jump]) - 0.2) < 0.02
    at = torch.tensor([[0.2, 0.0, 0.0]], dtype=torch.float64)
    true_jump = float(path.basis(at)[0] @ (second - first[0]))
    assert abs(float(y[jump + 1] - y[jump]) - true_jump) < 0.01


def test_otsu_splits_two_clusters():
    r = torch.cat([torch.full((90, 1), -0.1), torch.full((10, 1), 2.0)]) + torch.linspace(0, 0.01, 100)[:, None]
    assert otsu_labels(r)[:, 0].tolist() == [False] * 90 + [True] * 10


@pytest.mark.parametrize("kwargs", [dict(branches=3), dict(branches=True), dict(gate_degree=0)])
def test_bad_branch_settings_are_refused(kwargs):
    with pytest.raises(BodySchemaInputError):
        PerMusclePath(CROSSING, **kwargs)


def test_state_dict_round_trip_keeps_the_branches(fitted):
    path = fitted[0]
    copy = PerMusclePath(CROSSING, degree=8, n_hidden=0, branches=2, gate_degree=2).double()
    copy.load_state_dict(path.state_dict())
    assert copy.branched_index.tolist() == [0]  # rebuilt from the loaded ``branched`` (not in the state dict)
    x = torch.rand(100, 3, dtype=torch.float64) * 1.98 - 0.99
    assert torch.equal(copy(x), path(x))
    assert copy.float().coef_alt.dtype == torch.float64  # dtype casts leave the coefficients in float64


@pytest.mark.parametrize("samples_per_term, branched", [(3, False), (0, True)])
def test_a_branch_with_too_few_samples_per_term_is_not_kept(monkeypatch, samples_per_term, branched):
    from lightning_bodyschema.networks import branches

    monkeypatch.setattr(branches, "SAMPLES_PER_TERM", samples_per_term)
    path = PerMusclePath(CROSSING, degree=8, n_hidden=0, branches=2, gate_degree=2).double()
    first, second = _truth(path)
    x = torch.rand(300, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(4)) * 2 - 1
    path.fit_polynomial(x, _lengths(path, first, second, x))
    # muscle 0's smaller branch holds ~100 of the 300 samples, fewer than 3 per term of its 45 (degree 8, 2 joints):
    # it would interpolate them, and swing between them
    assert 45 < int((_surface(x) > 0).sum()) < 3 * 45
    assert path.branched.tolist() == [branched, False, False]


def test_a_branched_path_assert_exports_with_a_dynamic_batch(fitted):
    path = fitted[0]
    assert path.branched_index.tolist() == [0]  # kept in step with ``branched`` by the fit
    assert_exports_with_a_dynamic_batch(path)


def test_the_cells_rank_muscles_with_their_branches_active(monkeypatch):
    """The cells' candidates are the muscles the polynomial and its branches fit worst: when the cells are fitted
    the branched muscles' indices (what ``forward`` evaluates) are already in step with the branch fit (they once
    lagged, and cells replaced branches that followed their jumps: myoArm's PECM3 and LAT1-3)."""
    from lightning_bodyschema.networks import per_muscle

    seen, fit_cells = [], per_muscle.fit_cells

    def spy(path, x, y, chunk=8192):
        seen.append((path.branched_index.tolist(), torch.nonzero(path.branched).flatten().tolist()))
        residual = (y - path(x)).abs().median(0).values
        fit_cells(path, x, y, chunk)
        seen.append(residual)

    monkeypatch.setattr(per_muscle, "fit_cells", spy)
    path = PerMusclePath(CROSSING, degree=8, n_hidden=0, branches=2, gate_degree=2, cells=2).double()
    first, second = _truth(path)
    x = torch.rand(20000, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(4)) * 2 - 1
    path.fit_polynomial(x, _lengths(path, first, second, x))
    (index, branched), residual = seen
    assert index == branched == [0]
    assert residual[0] < 1e-9  # muscle 0's jump is followed: no candidate for cells
    assert path.branched.tolist() == [True, False, False] and 0 not in path.cell_muscles.tolist()
