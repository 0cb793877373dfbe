"""networks.snapshot.PathSnapshot: a per-muscle path at few postures (one basis for the whole-box polynomials, the
branches and the cells, one gather of each muscle's choice), the same code in torch and in numpy, answers as the
blockwise evaluation of many postures, with moment arms that are its lengths' derivative, in float64."""
from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch
from physics_checks import central_differences, term_sum_tol
from torch.utils._python_dispatch import TorchDispatchMode

from lightning_bodyschema.networks import snapshot as few_postures
from lightning_bodyschema.networks.per_muscle import PerMusclePath

CROSSING = np.array([[1, 1, 0], [1, 0, 1], [0, 1, 1], [1, 1, 1]], dtype=bool)


def _lengths(x):
    """Muscle 0 jumps by 1.5 across the plane x0 + 0.3 x1 = 0.2 (a wrap switching sides: branches); muscle 1 changes
    polynomial at x2 = 0 (a path smooth in pieces: cells); muscles 2 and 3 are smooth."""
    a, b, c = x[:, 0], x[:, 1], x[:, 2]
    jump = torch.where(a + 0.3 * b > 0.2, 1.5 + a - 0.5 * b ** 2, a * b + 0.2 * a ** 3)
    pieces = torch.where(c > 0, a * c + c ** 2, a * c - c ** 3)
    return torch.stack([jump, pieces, b * c + b ** 3, a * b * c], 1)


@pytest.fixture(scope="module")
def path():
    x = torch.rand(20000, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64) * 1.8 - 0.9
    path = PerMusclePath(CROSSING, degree=6, hidden=1, n_hidden=0, branches=2, gate_degree=2, cells=2)
    path.fit_polynomial(x, _lengths(x))
    assert path.branched_index.tolist() == [0] and path.cell_muscles.tolist() == [1]
    path.cell_fitted[0, 0] = False  # a cell the fit left to the whole-box polynomial (a thin cell's fallback)
    return path


def _postures(n, seed):
    """Postures over the box and beyond it (the box is [-0.9, 0.9]^3: a first-order extension outside)."""
    return torch.rand(n, 3, generator=torch.Generator().manual_seed(seed), dtype=torch.float64) * 2.2 - 1.1


def test_few_postures_answer_as_the_blockwise_evaluation(path, monkeypatch):
    x = _postures(600, 1)
    monkeypatch.setattr(few_postures, "FEW_ELEMENTS", 0)  # blocks of rows, the cells a group and a cell at a time
    y, dy = path.with_jacobian(x)
    assert ((x[:, 0] + 0.3 * x[:, 1] > 0.2).any() and (x[:, 0] + 0.3 * x[:, 1] < 0.2).any()  # both branches,
            and (x.abs() > 0.9).any(1).sum() > 100)  # many postures outside the box
    cell = (path.cell_stride[0] * (x > 0)).sum(1)  # muscle 1's cell (x0, x2 cut at 0)
    assert (cell == 0).sum() > 50  # the unfitted cell: the whole-box polynomial there
    monkeypatch.setattr(few_postures, "FEW_ELEMENTS", 10 ** 18)  # every batch by the few-postures path
    for rows in (1, 7, 48, 600):
        parts = [path.with_jacobian(x[i:i + rows]) for i in range(0, 600 if rows > 1 else 60, rows)]
        n = sum(len(p[0]) for p in parts)
        torch.testing.assert_close(torch.cat([p[0] for p in parts]), y[:n], rtol=0, atol=term_sum_tol(path, y))
        torch.testing.assert_close(torch.cat([p[1] for p in parts]), dy[:n], rtol=0, atol=term_sum_tol(path, dy))
        assert (torch.cat([p[1] for p in parts])[:, ~torch.as_tensor(CROSSING)] == 0).all()  # exactly


def test_the_few_postures_path_is_taken_within_its_work_budget(path, monkeypatch):
    per_posture = len(path.few_terms.exponents) * (1 + 3)  # its stacked basis: whole-box and cell terms x (1 + joints)
    monkeypatch.setattr(few_postures, "FEW_ELEMENTS", 10 * per_posture)
    calls, original = [], few_postures.PathSnapshot.__call__
    monkeypatch.setattr(few_postures.PathSnapshot, "__call__", lambda it, q: calls.append(len(q)) or original(it, q))
    x = _postures(11, 3)
    path.with_jacobian(x[:10])
    path.with_jacobian(x)  # one posture above the budget: blocks of rows
    assert path.snapshot().max_postures == 10 and calls == [10]


def test_few_postures_moment_arms_are_their_lengths_derivative(path):
    x = _postures(40, 2).clamp(-0.89, 0.89)  # inside the box: the polynomials themselves
    x = x[((x[:, 0] + 0.3 * x[:, 1] - 0.2).abs() > 1e-3) & (x[:, 2].abs() > 1e-3) & (x[:, 0].abs() > 1e-3)]
    y, dy = path.with_jacobian(x)  # away from the gate's switch and the cells' edges (finite differences)
    assert 30 < len(x) <= path.snapshot().max_postures
    np.testing.assert_allclose(dy.numpy(), central_differences(path, x), rtol=0, atol=1e-7)


def test_the_numpy_snapshot_answers_as_the_torch_one(path):
    """``PathSnapshot.on_host()``: the same code on numpy arrays (branches, a celled muscle, its unfitted cell, postures
    beyond the box); a NaN posture answers NaN at a valid cell without a warning, in numpy and in torch."""
    host, x = path.snapshot().on_host(), _postures(120, 4)
    for rows in (1, 3, 4):
        for i in range(0, 120, rows):
            y, dy = path.with_jacobian(x[i:i + rows])
            y_host, dy_host, _ = host(x[i:i + rows].numpy())
            np.testing.assert_allclose(y_host, y.numpy(), rtol=0, atol=term_sum_tol(path, y))
            np.testing.assert_allclose(dy_host, dy.numpy(), rtol=0, atol=term_sum_tol(path, dy))
    bad = x[:2].clone()
    bad[0, 2] = float("nan")  # the cut joint of muscle 1's cells
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        y_host = host(bad.numpy())[0]
    assert np.isnan(y_host[0, [1, 2]]).all() and np.isfinite(y_host[1]).all()
    y_torch = path.snapshot()(bad)[0]
    # NaN at the same places; the numbers within a few roundings (numpy's and torch's matrix products may sum in
    # another order: one ulp apart under MKL_CBWR=COMPATIBLE), as the loop above asks
    np.testing.assert_array_equal(np.isnan(y_torch.numpy()), np.isnan(y_host))
    np.testing.assert_allclose(y_torch.numpy(), y_host, rtol=0, atol=term_sum_tol(path, np.nan_to_num(y_host)))


def test_the_snapshot_exports_with_a_dynamic_batch(path):
    """``torch.export`` of the torch snapshot itself (as the exported package evaluates the body: every posture at
    once, no vmap) keeps the batch symbolic and answers as the eager snapshot, beyond the box too."""
    from torch.export import Dim, export

    snapshot = path.snapshot()

    class Frozen(torch.nn.Module):
        def forward(self, x):
            return snapshot(x)

    x = _postures(9, 5)
    program = export(Frozen(), (x[:2],), dynamic_shapes=({0: Dim("batch", min=1, max=4096)},), strict=False)
    for rows in (x[:1], x):
        for exported, eager in zip(program.module()(rows), snapshot(rows)):
            torch.testing.assert_close(exported, eager, atol=term_sum_tol(path, eager.nan_to_num()), rtol=0)


def test_the_host_moment_arms_are_its_lengths_derivative(path):
    host = path.snapshot().on_host()
    x = _postures(40, 6).clamp(-0.89, 0.89)
    x = x[((x[:, 0] + 0.3 * x[:, 1] - 0.2).abs() > 1e-3) & (x[:, 2].abs() > 1e-3) & (x[:, 0].abs() > 1e-3)][:4]
    lengths = lambda rows: torch.as_tensor(host(rows.numpy())[0])  # noqa: E731
    np.testing.assert_allclose(host(x.numpy())[1], central_differences(lengths, x), rtol=0, atol=1e-7)


class _IntegerProducts(TorchDispatchMode):
    """Records the matrix products of integer tensors (CUDA has none: cuBLAS multiplies floating point only)."""
    PRODUCTS = {"mm", "bmm", "addmm", "mv", "addmv", "baddbmm", "dot"}

    def __init__(self):
        super().__init__()
        self.seen = []

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        name = func.__name__.split(".")[0]
        if name in self.PRODUCTS and any(torch.is_tensor(a) and not a.is_floating_point() for a in args):
            self.seen.append(name)
        return func(*args, **(kwargs or {}))


def test_the_fit_and_both_paths_multiply_no_integer_matrices(monkeypatch):
    x = torch.rand(4000, 3, generator=torch.Generator().manual_seed(5), dtype=torch.float64) * 1.8 - 0.9
    path = PerMusclePath(CROSSING, degree=4, hidden=1, n_hidden=0, branches=2, gate_degree=2, cells=2)
    with _IntegerProducts() as products:
        path.fit_polynomial(x, _lengths(x))
        path.with_jacobian(x[:7])  # few postures
        monkeypatch.setattr(few_postures, "FEW_ELEMENTS", 0)
        path.with_jacobian(x)  # blocks of rows, a group and a cell at a time
    assert len(path.cell_muscles) and products.seen == []
