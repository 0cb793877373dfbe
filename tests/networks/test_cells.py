"""networks.cells: a path smooth in pieces recovered cell by cell, moment arms that are the learned length's
derivative, zero on uncrossed joints, thin cells that keep the whole-box polynomial, and a state-dict round trip."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from torch.nn import functional as F

from physics_checks import assert_exports_with_a_dynamic_batch, term_sum_tol

from lightning_bodyschema.errors import BodySchemaInputError
from lightning_bodyschema.networks.basis import product_basis
from lightning_bodyschema.networks.cell_fit import _kept, _trimmed, thin_cell_terms
from lightning_bodyschema.networks.cells import cell_coordinates, cell_cuts, cell_degree
from lightning_bodyschema.networks.per_muscle import PerMusclePath
from lightning_bodyschema.networks.polynomial import term_exponents

CROSSING = np.array([[1, 1, 0], [1, 0, 1], [0, 1, 0], [1, 0, 1], [0, 1, 1], [1, 1, 1], [1, 0, 0]], dtype=bool)


def _lengths(x):
    """Muscle 0 is one cubic for x0 < 0 and another for x0 > 0 (a path that wraps on at x0 = 0: the slope jumps),
    muscles 1 and 3 (the same two joints) change polynomial at x2 = 0; the others are low-degree polynomials a
    whole-box fit represents exactly."""
    a, b, c = x[:, 0], x[:, 1], x[:, 2]
    wrapped = torch.where(a > 0, 1 + a ** 2 - 0.5 * b + a * b ** 2, 0.3 * a ** 3 + b - 0.2 * b ** 3)
    one, three = torch.where(c > 0, a * c + c ** 2, a * c - c ** 3), torch.where(c > 0, a - c, a + 2 * c ** 2)
    return torch.stack([wrapped, one, b ** 2, three, b * c, a * b * c, a ** 3], 1)


@pytest.fixture(scope="module")
def fitted():
    x = torch.rand(6000, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64) * 2 - 1
    path = PerMusclePath(CROSSING, degree=4, hidden=1, n_hidden=0, cells=2)
    path.fit_polynomial(x, _lengths(x))
    return path


def _inside(n, seed, margin=1e-3):
    """Held-out postures inside the fitted box (outside it the model is a first-order extension)."""
    x = torch.rand(n, 3, generator=torch.Generator().manual_seed(seed), dtype=torch.float64) * 2 - 1
    return x.clamp(-1 + margin, 1 - margin)


def test_a_path_smooth_in_pieces_is_recovered_cell_by_cell(fitted):
    assert fitted.cell_muscles.tolist() == [0, 1, 3]  # only the muscles a smooth polynomial cannot fit get cells
    x = _inside(2000, 1)
    np.testing.assert_allclose(fitted(x), _lengths(x), atol=1e-9)
    whole = PerMusclePath(CROSSING, degree=4, hidden=1, n_hidden=0)  # one polynomial over the box: the kink costs ~1e-2 (test can fail)
    whole.fit_polynomial(_inside(6000, 0, 0.0), _lengths(_inside(6000, 0, 0.0)))
    assert ((whole(x) - _lengths(x))[:, [0, 1, 3]].abs().amax(0) > 1e-3).all()


def test_cell_moment_arms_are_the_learned_lengths_derivative_and_zero_off_the_crossed_joints(fitted):
    x = _inside(200, 2)
    x = x[(x.abs() > 1e-3).all(1)]  # central differences must not straddle a cell's edge (x = 0)
    y, dy = fitted.with_jacobian(x)
    h = 1e-6
    for j in range(3):
        step = torch.zeros(3, dtype=torch.float64)
        step[j] = h
        fd = (fitted(x + step) - fitted(x - step)) / (2 * h)
        np.testing.assert_allclose(dy[:, :, j], fd, atol=1e-7)
    assert (dy[:, ~torch.as_tensor(CROSSING)] == 0).all()  # every uncrossed pair, celled muscles too
    true_slope = torch.where(x[:, 0] > 0, 2 * x[:, 0] + x[:, 1] ** 2, 0.9 * x[:, 0] ** 2)
    np.testing.assert_allclose(dy[:, 0, 0], true_slope, atol=1e-8)


def test_a_thin_cell_takes_the_degree_its_samples_allow():
    """The cell x0 > 0, x1 > 0 of muscle 0 holds 33 samples spread over it, too few for its 15 terms of degree 4
    with ``SAMPLES_PER_TERM`` each: it takes degree 3 (10 terms), which is muscle 0's path there, recovered to 1e-9
    where the whole-box polynomial misses it by more than 1e-3 (the test can fail); a cell with fewer samples than a
    plane's terms keeps the whole-box polynomial."""
    generator = torch.Generator().manual_seed(3)
    x = torch.rand(3000, 3, generator=generator, dtype=torch.float64) * 2 - 1
    x = x[(x[:, 0] < 0) | (x[:, 1] < 0) | (torch.rand(3000, generator=generator, dtype=torch.float64) < 0.05)]
    path = PerMusclePath(CROSSING, degree=4, hidden=1, n_hidden=0, cells=2)
    path.fit_polynomial(x, _lengths(x))
    assert path.cell_muscles[0] == 0 and path.cell_fitted[0].all()
    assert path.cell_coef[0, 3, 10:].abs().max() == 0 and path.cell_coef[0, 3, :10].abs().max() > 0
    whole = PerMusclePath(CROSSING, degree=4, hidden=1, n_hidden=0)
    whole.fit_polynomial(x, _lengths(x))
    thin = torch.tensor([[0.5, 0.9, 0.0], [0.2, 0.5, -0.3], [0.9, 0.1, 0.7]], dtype=torch.float64)
    np.testing.assert_allclose(path(thin)[:, 0], _lengths(thin)[:, 0], atol=1e-9)
    assert (whole(thin)[:, 0] - _lengths(thin)[:, 0]).abs().max() > 1e-3
    assert thin_cell_terms([0, 1, 1, 2, 2, 2], 18) == 6 and thin_cell_terms([0, 1, 1, 2, 2, 2], 17) == 3
    assert thin_cell_terms([0, 1, 1, 2, 2, 2], 8) == 0  # not even a plane: the whole-box polynomial stays


def test_cells_survive_a_state_dict_round_trip(fitted):
    loaded = PerMusclePath(CROSSING, degree=4, hidden=1, n_hidden=0, cells=2, cell_degrees=fitted.cell_degrees.tolist())
    loaded.load_state_dict(fitted.state_dict())
    x = _inside(100, 4)
    assert torch.equal(loaded.with_jacobian(x)[1], fitted.with_jacobian(x)[1])


def test_cell_numbering_and_degrees(fitted):
    k, x_local = cell_coordinates(torch.tensor([[-1.0, -0.25, 0.0, 1.0]], dtype=torch.float64), 2)
    assert k.tolist() == [[0, 0, 1, 1]] and x_local.tolist() == [[-1.0, 0.5, -1.0, 1.0]]
    assert fitted.cell_stride.tolist() == [[1, 2, 0], [1, 0, 2], [1, 0, 2]]  # each muscle's 2 joints: cells 0..3
    assert cell_degree(5, 9, 2, 80000) == 7  # C(12, 5) = 792 terms x 3 samples x 32 cells <= 80 000
    assert cell_degree(3, 16, 2, 80000) == 16
    with pytest.raises(BodySchemaInputError, match="cells=0 must be an integer >= 1"):
        PerMusclePath(CROSSING, degree=4, hidden=1, n_hidden=0, cells=0)
    with pytest.raises(BodySchemaInputError, match=r"cell_degrees=\[1, 2\] must be 7 integers >= 0"):
        PerMusclePath(CROSSING, degree=4, hidden=1, n_hidden=0, cells=2, cell_degrees=[1, 2])
    for bad in (1, 0.5, True, "10"):
        with pytest.raises(BodySchemaInputError, match=f"cell_trim={bad!r} must be None or a number > 1"):
            PerMusclePath(CROSSING, degree=4, hidden=1, n_hidden=0, cells=2, cell_trim=bad)


def test_a_path_celled_everywhere_answers_its_cells_at_few_and_many_postures(monkeypatch):
    """Every muscle's every cell fitted (set by hand: no whole-box row is ever chosen): each cell's constant."""
    from lightning_bodyschema.networks import snapshot

    path = PerMusclePath(np.array([[True, True]]), degree=2, hidden=1, n_hidden=0, cells=2, cell_degrees=[1])
    path.cell_fitted[:] = True
    path.cell_coef[0, :, 0] = torch.arange(1.0, 5.0, dtype=torch.float64)  # the constant term: 1, 2, 3, 4
    x = _inside(300, 6)[:, :2]
    cell = (path.cell_stride[0] * (x > 0)).sum(1)
    for elements in (snapshot.FEW_ELEMENTS, 0):  # the snapshot, then blocks of rows and a cell at a time
        monkeypatch.setattr(snapshot, "FEW_ELEMENTS", elements)
        y, dy = path.with_jacobian(x)
        assert y[:, 0].tolist() == (cell + 1.0).tolist() and (dy == 0).all()


def test_many_postures_by_cell_equal_few_postures_gathered(fitted, monkeypatch):
    from lightning_bodyschema.networks import snapshot
    from lightning_bodyschema.networks.basis import DENSE_ROWS

    x = _inside(600, 5)
    monkeypatch.setattr(snapshot, "FEW_ELEMENTS", 0)  # a group of muscles and a cell at a time
    y, dy = fitted.with_jacobian(x)
    monkeypatch.undo()  # in pieces of DENSE_ROWS: every part from one basis (networks.snapshot)
    assert DENSE_ROWS <= fitted.snapshot().max_postures
    parts = [fitted.with_jacobian(x[i:i + DENSE_ROWS]) for i in range(0, 600, DENSE_ROWS)]
    torch.testing.assert_close(y, torch.cat([p[0] for p in parts]), rtol=0, atol=term_sum_tol(fitted, y))
    torch.testing.assert_close(dy, torch.cat([p[1] for p in parts]), rtol=0, atol=term_sum_tol(fitted, dy))


def test_a_nan_posture_answers_nan_in_its_row_only_in_the_blocks_and_the_snapshot(fitted, monkeypatch):
    """A NaN coordinate takes piece 0 (``cell_coordinates``): its row answers NaN, every other row as without it, in
    the blocks (a cell at a time) as in the snapshot (an index cast from NaN is garbage: bincount refused it)."""
    from lightning_bodyschema.networks import snapshot

    x = _inside(300, 7)
    k, _ = cell_coordinates(torch.tensor([[float("nan"), -0.5]], dtype=torch.float64), 2)
    assert k.tolist() == [[0, 0]]
    assert cell_coordinates(np.array([[np.nan, 0.5]]), 2)[0].tolist() == [[0, 1]]  # numpy alike
    bad = x.clone()
    bad[5, 0] = float("nan")
    for elements in (0, snapshot.FEW_ELEMENTS):  # the blocks, then the snapshot (few postures)
        monkeypatch.setattr(snapshot, "FEW_ELEMENTS", elements)
        rows = slice(None) if elements == 0 else slice(0, 20)
        y, dy = fitted.with_jacobian(x[rows])
        y_bad, dy_bad = fitted.with_jacobian(bad[rows])
        keep = torch.arange(len(y)) != 5  # the other rows to a few roundings (a cell's rows in another block)
        torch.testing.assert_close(y_bad[keep], y[keep], rtol=0, atol=term_sum_tol(fitted, y[keep]))
        torch.testing.assert_close(dy_bad[keep], dy[keep], rtol=0, atol=term_sum_tol(fitted, dy[keep]))
        assert y_bad[5].isnan().all()  # the first-order extension's (x - inside) is NaN on every muscle's row


def test_the_cells_spread_coefficients_are_each_muscles_own(fitted):
    """``PathSnapshot.spread``: in each cell, a muscle's coefficients on the cell terms it uses and zero elsewhere, so a
    product with any basis row equals the product with that muscle's own columns; the kept ones answer as the
    ones built per call."""
    spread = fitted.snapshot().spread  # (celled muscles, cells, cell terms)
    assert spread.shape == (3, 4, len(fitted.cell_exponents))
    v = torch.rand(len(fitted.cell_exponents), generator=torch.Generator().manual_seed(7), dtype=torch.float64)
    own = torch.einsum("mk,mck->mc", v[fitted.cell_order] * fitted.cell_valid, fitted.cell_coef)
    torch.testing.assert_close(spread @ v, own, rtol=1e-14, atol=0)
    used = torch.zeros(3, len(v), dtype=torch.bool).scatter_(1, fitted.cell_order, fitted.cell_valid)
    assert (spread[~used[:, None, :].expand_as(spread)] == 0).all()
    x = _inside(40, 6)  # few postures: the dense basis
    for ours, theirs in zip(fitted.with_jacobian(x, fitted.snapshot()), fitted.with_jacobian(x)):
        assert torch.equal(ours, theirs)


def test_a_celled_path_assert_exports_with_a_dynamic_batch(fitted):
    assert_exports_with_a_dynamic_batch(fitted)


def test_a_trimmed_cell_fits_the_larger_side_of_a_jump_exactly():
    """A wrap switching sides inside a cell: a length that jumps by 0.5 on a corner (~6 % of the samples). One
    least squares rings over the whole cell; trimmed, it recovers the polynomial of the larger side to 1e-9 and
    misses the corner by about the jump."""
    x = torch.rand(4000, 2, generator=torch.Generator().manual_seed(4), dtype=torch.float64) * 2 - 1
    exponents = torch.as_tensor(term_exponents(np.zeros((1, 2), np.int64), np.array([4])))
    phi = product_basis(x, exponents, 4)[0]
    true = torch.linspace(-1, 1, len(exponents), dtype=torch.float64)[:, None]  # (K, 1)
    corner = (x[:, 0] > 0.5) & (x[:, 1] > 0.5)
    y = phi @ true + 0.5 * corner[:, None]
    gram, rhs = phi.T @ phi, phi.T @ y
    plain = torch.linalg.solve(gram, rhs)
    assert (plain - true).abs().max() > 1e-3  # the ring (the test can fail)
    trimmed = _trimmed(phi, y, gram, rhs, plain, 10.0, 3 * len(exponents))
    np.testing.assert_allclose(trimmed, true, atol=1e-9)
    miss = (phi @ trimmed - y).abs()[:, 0]
    assert (miss[~corner] < 1e-9).all() and (miss[corner] > 0.49).all()
    kept_all = _trimmed(phi, y, gram, rhs, plain, 10.0, len(x))  # too few samples would stay: none dropped
    torch.testing.assert_close(kept_all, plain, rtol=0, atol=0)


def _corner(x):
    return (x[:, 0] > 0.85) & (x[:, 1] > 0.85)


def _jumping(x):
    """``_lengths`` with muscle 0 jumping by 0.5 on a corner of one of its cells (~0.6 % of the box)."""
    return _lengths(x) + 0.5 * F.one_hot(torch.zeros(len(x), dtype=torch.long), 7) * _corner(x)[:, None]


def test_a_path_with_cell_trim_fits_around_a_jump_inside_a_cell():
    """A wrap switching sides inside a cell: with ``cell_trim`` the cells fit the rest of the box to 1e-8; without,
    the cell's polynomial rings (the test can fail)."""
    x = torch.rand(6000, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64) * 2 - 1
    held_out = _inside(2000, 5)
    held_out = held_out[~_corner(held_out)]
    errors = []
    for trim in (None, 10.0):
        path = PerMusclePath(CROSSING, degree=4, hidden=1, n_hidden=0, cells=2, cell_trim=trim)
        path.fit_polynomial(x, _jumping(x))
        assert 0 in path.cell_muscles.tolist()
        errors.append((path(held_out) - _jumping(held_out))[:, 0].abs().max())
    assert errors[0] > 1e-3 and errors[1] < 1e-8


def _four_pieces(x):
    """Muscle 0 changes polynomial at x0 = -0.5, 0 and 0.5 (four wraps along one joint); muscles 1 and 2 are low-degree
    polynomials a whole-box fit represents exactly."""
    a, b, c = x[:, 0], x[:, 1], x[:, 2]
    piece = torch.clamp(torch.floor(2 * (a + 1)), 0, 3)
    kinked = (piece - 1.5) * a ** 2 + torch.where(piece % 2 == 0, a * b, b ** 3) + 0.3 * piece
    return torch.stack([kinked, b * c + c ** 2, a * c], 1)


def test_four_cells_per_joint_follow_a_path_with_four_pieces():
    """``cells=4``: each joint's range in four; a path that changes polynomial at x0 = -0.5, 0, 0.5 is recovered to
    1e-9 with its moment arms exact, while two cells per joint straddle two of its seams (the test can fail)."""
    crossing = np.array([[1, 1, 0], [0, 1, 1], [1, 0, 1]], dtype=bool)
    x = torch.rand(12000, 3, generator=torch.Generator().manual_seed(8), dtype=torch.float64) * 2 - 1
    held_out = _inside(1000, 9)
    held_out = held_out[((held_out[:, :1] - torch.tensor([-0.5, 0.0, 0.5], dtype=torch.float64)).abs() > 1e-3).all(1)]
    errors = {}
    for pieces in (2, 4):
        path = PerMusclePath(crossing, degree=4, hidden=1, n_hidden=0, cells=pieces)
        path.fit_polynomial(x, _four_pieces(x))
        assert path.cell_muscles.tolist() == [0]
        y, dy = path.with_jacobian(held_out)
        errors[pieces] = (y - _four_pieces(held_out))[:, 0].abs().max()
        if pieces == 4:
            assert path.cell_stride.tolist() == [[1, 4, 0]] and path.cell_fitted.all()  # 16 cells over (x0, x1)
            a, b = held_out[:, 0], held_out[:, 1]
            piece = torch.clamp(torch.floor(2 * (a + 1)), 0, 3)
            slope = 2 * (piece - 1.5) * a + torch.where(piece % 2 == 0, b, torch.zeros_like(b))
            np.testing.assert_allclose(dy[:, 0, 0], slope, atol=1e-8)
    assert errors[4] < 1e-9 and errors[2] > 1e-3


BLOCKED = np.array([[0, 0, 1], [0, 0, -1], [-1, 0, 0], [0, -1, -1]])  # muscle 0: (x0, x1) mixed, plus x2 alone


def _grouped_lengths(x):
    """Muscle 0: a path that wraps on at x0 = 0 over its (x0, x1) group plus a quartic in x2 that adds up; the
    others low-degree polynomials a whole-box fit represents exactly."""
    a, b, c = x[:, 0], x[:, 1], x[:, 2]
    wrapped = torch.where(a > 0, 1 + a ** 2 - 0.5 * b + a * b ** 2, 0.3 * a ** 3 + b - 0.2 * b ** 3)
    return torch.stack([wrapped + c ** 4 - c, a * b, b * c + c ** 2, a ** 3], 1)


def test_cells_over_the_largest_group_leave_the_other_joints_whole():
    """Cut over (x0, x1) only, 4 cells of 100 samples hold muscle 0's degree 4 (19 terms); cut over every crossed
    joint, 8 cells of 50 allow degree 3 only, which misses the quartic in x2 (the test can fail)."""
    crossing = BLOCKED >= 0
    x = torch.rand(400, 3, generator=torch.Generator().manual_seed(6), dtype=torch.float64) * 2 - 1
    held_out = torch.minimum(torch.maximum(_inside(500, 7), x.amin(0) + 1e-5), x.amax(0) - 1e-5)  # the fitted box
    held_out = held_out[(held_out[:, 0].abs() > 1e-3)]  # central differences must not straddle x0 = 0
    errors, paths = {}, {}
    for rule in ("crossed", "largest_group"):
        paths[rule] = path = PerMusclePath(crossing, degree=4, hidden=1, n_hidden=0, cells=2, blocks=BLOCKED, cell_joints=rule)
        path.fit_polynomial(x, _grouped_lengths(x))
        assert path.cell_muscles.tolist() == [0] and bool(path.cell_fitted.all())
        errors[rule] = float((path(held_out) - _grouped_lengths(held_out))[:, 0].abs().max())
    assert errors["crossed"] > 1e-3 and errors["largest_group"] < 1e-9
    path = paths["largest_group"]
    assert path.cell_stride.tolist() == [[1, 2, 0]] and path.cell_extra.tolist() == [2]
    y, dy = path.with_jacobian(held_out)
    h = 1e-6
    for j in range(3):
        step = torch.zeros(3, dtype=torch.float64)
        step[j] = h
        np.testing.assert_allclose(dy[:, :, j], (path(held_out + step) - path(held_out - step)) / (2 * h),
                                   atol=1e-7)
    assert (dy[:, ~torch.as_tensor(crossing)] == 0).all()
    np.testing.assert_allclose(dy[:, 0, 2], 4 * held_out[:, 2] ** 3 - 1, atol=1e-9)  # the whole joint's slope
    parts = [path.with_jacobian(held_out[i:i + 40]) for i in range(0, len(held_out), 40)]  # few postures: dense
    torch.testing.assert_close(dy, torch.cat([p[1] for p in parts]), rtol=0, atol=term_sum_tol(path, dy))
    assert_exports_with_a_dynamic_batch(path)


def test_which_joints_cut_a_box():
    blocks = np.array([[0, 0, 0, 1, 1, -1], [0, 0, 1, 1, -1, -1], [-1, -1, -1, -1, 0, 0]])
    crossing = blocks >= 0
    assert cell_cuts(crossing, blocks, "largest_group").astype(int).tolist() == [
        [1, 1, 1, 0, 0, 0], [1, 1, 1, 1, 0, 0], [0, 0, 0, 0, 1, 1]]  # BIClong's shoulder; a tie cuts both groups
    assert (cell_cuts(crossing, blocks, "crossed") == crossing).all()
    assert cell_degree((3, 2), 16, 2, 80000, cut=3) == 16  # myoArm's BIClong: 8 cells, not 32 (degree 14)
    with pytest.raises(BodySchemaInputError, match=r"cell_joints='shoulder'; allowed: \['crossed', 'largest_group'\]"):
        PerMusclePath(crossing, degree=4, hidden=1, n_hidden=0, cells=2, blocks=blocks, cell_joints="shoulder")


def test_which_cells_are_kept():
    """Muscle 0's cells fit its samples far better but miss 2 % of them (a jump's smaller side) by more than its
    whole-box model does: kept on the median alone, dropped when the p99 may not grow; muscle 1's cells ring everywhere
    (no gain on the median), muscle 2's halve it and lower the p99: kept by both rules."""
    rows = torch.arange(1000, dtype=torch.float64)
    own = torch.stack([torch.full_like(rows, 1e-3), torch.full_like(rows, 1e-3), torch.full_like(rows, 1e-3)], 1)
    own[:20, 0] = 0.2
    miss = torch.stack([torch.full_like(rows, 1e-6), torch.full_like(rows, 0.9e-3), torch.full_like(rows, 0.4e-3)], 1)
    miss[:20, 0] = 0.5
    assert _kept(miss, own, "median").tolist() == [True, False, True]
    assert _kept(miss, own, "median_and_p99").tolist() == [False, False, True]
    with pytest.raises(BodySchemaInputError, match=r"cell_keep='p99'; allowed: \['median_and_p99', 'median'\]"):
        PerMusclePath(CROSSING, degree=4, hidden=1, n_hidden=0, cells=2, cell_keep="p99")


def test_a_thin_cell_worse_than_the_whole_box_polynomial_is_not_used():
    """Muscle 0 kinks (mildly) along x0 = 0 where x1 < 0 (a whole-box polynomial rings a little everywhere); its cell
    x0 > 0, x1 > 0 (where the path is x0 ** 2 + x1 ** 2) holds 14 samples: room for a plane only, which misses the
    curve by far more than the whole-box polynomial does, so that cell keeps the whole-box polynomial (the others
    are cells)."""
    generator = torch.Generator().manual_seed(5)
    x = torch.rand(3000, 3, generator=generator, dtype=torch.float64) * 2 - 1
    x = x[(x[:, 0] < 0) | (x[:, 1] < 0) | (torch.rand(3000, generator=generator, dtype=torch.float64) < 0.016)]
    assert int(((x[:, 0] > 0) & (x[:, 1] > 0)).sum()) == 14

    def lengths(x):
        kinked = x[:, 0] ** 2 + x[:, 1] ** 2 + 0.05 * x[:, 0].abs() * (x[:, 1] < 0)
        return torch.stack([kinked, x[:, 1] * x[:, 2], x[:, 0] * x[:, 2]], 1)
    crossing = np.array([[1, 1, 0], [0, 1, 1], [1, 0, 1]], dtype=bool)
    path = PerMusclePath(crossing, degree=4, hidden=1, n_hidden=0, cells=2)
    path.fit_polynomial(x, lengths(x))
    whole = PerMusclePath(crossing, degree=4, hidden=1, n_hidden=0)
    whole.fit_polynomial(x, lengths(x))
    assert path.cell_muscles.tolist() == [0] and path.cell_fitted[0].tolist() == [True, True, True, False]
    inside = torch.tensor([[0.5, 0.5, 0.0], [0.2, 0.8, -0.3]], dtype=torch.float64)
    torch.testing.assert_close(path(inside)[:, 0], whole(inside)[:, 0], rtol=0, atol=0)
