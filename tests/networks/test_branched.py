"""The branched part of a per-muscle path on its own (gate and second polynomial set by hand, no
fit): the length is the active branch's polynomial, the moment arm its exact derivative, the jump where the gate
changes sign, alike in every evaluation (blocks of rows, the snapshot in torch and in numpy)."""
import numpy as np
import pytest
import torch
from physics_checks import rounding_tol

from lightning_bodyschema.networks import snapshot
from lightning_bodyschema.networks.per_muscle import PerMusclePath

EDGE = 0.25  # the gate is x - EDGE: the second branch above
# a degree-2 Legendre basis, its slopes and three terms summed, each re-rounded: a few roundings at order 1 (~2e-15);
# the other branch's polynomial differs by O(0.1)
_POLY_ROUNDINGS = 8


def _path():
    """One muscle over one joint, Legendre coefficients (P0, P1, P2): first branch 0.1 + 0.2 x, second branch
    0.5 + 0.3 P2(x) = 0.35 + 0.45 x^2, gate x - EDGE; then a muscle that is never branched (-x)."""
    path = PerMusclePath(np.array([[True], [True]]), degree=2, n_hidden=0, branches=2).double()
    assert path.exponents[:, 0].tolist() == [0, 1, 2]
    with torch.no_grad():
        path.coef.copy_(torch.tensor([[0.1, 0.2, 0.0], [0.0, -1.0, 0.0]], dtype=torch.float64))
        path.coef_alt[0] = torch.tensor([0.5, 0.0, 0.3], dtype=torch.float64)
        path.gate[0] = torch.tensor([-EDGE, 1.0, 0.0], dtype=torch.float64)
        path.branched[0] = True
    path.load_state_dict(path.state_dict())  # a load refreshes the branched muscles' indices
    return path


def _expected(x):
    """Lengths and moment arms of both muscles at ``x (B, 1)``."""
    above = x[:, 0] > EDGE
    y0 = torch.where(above, 0.35 + 0.45 * x[:, 0] ** 2, 0.1 + 0.2 * x[:, 0])
    dy0 = torch.where(above, 0.9 * x[:, 0], torch.full_like(x[:, 0], 0.2))
    return torch.stack([y0, -x[:, 0]], 1), torch.stack([dy0, -torch.ones_like(dy0)], 1)[..., None]


def test_the_snapshot_rows_are_the_branched_muscles_masked_second_polynomials_and_gates():
    frozen = snapshot.PathSnapshot(_path())
    assert frozen.gated.tolist() == [True, False]  # muscle 1 is never branched: its whole-box row only
    assert frozen.box[frozen.alt_col[0]].tolist() == [0.5, 0.0, 0.3]
    assert frozen.box[frozen.gate_col[0]].tolist() == [-EDGE, 1.0, 0.0]
    for path in (PerMusclePath(np.array([[True]]), degree=2, n_hidden=0, branches=2),  # none branched
                 PerMusclePath(np.array([[True]]), degree=2, n_hidden=0)):  # no branches
        frozen = snapshot.PathSnapshot(path)
        assert len(frozen.box) == 1 and not frozen.gated.any()


@pytest.mark.parametrize("evaluation", ["blocks", "snapshot", "numpy"])
def test_the_length_jumps_where_the_gate_changes_sign_and_the_moment_arm_is_the_active_branch_slope(
        evaluation, monkeypatch):
    path = _path()
    x = torch.linspace(-1, 1, 401, dtype=torch.float64)[:, None]
    if evaluation == "blocks":
        monkeypatch.setattr(snapshot, "FEW_ELEMENTS", 0)  # never the snapshot
        y, dy = path.with_jacobian(x)
    else:
        frozen = path.snapshot() if evaluation == "snapshot" else path.snapshot().on_host()
        y, dy = (torch.as_tensor(a) for a in frozen(x if evaluation == "snapshot" else x.numpy())[:2])
    y_true, dy_true = _expected(x)
    torch.testing.assert_close(y, y_true, atol=rounding_tol(_POLY_ROUNDINGS, y_true), rtol=0)
    torch.testing.assert_close(dy, dy_true, atol=rounding_tol(_POLY_ROUNDINGS, dy_true), rtol=0)
    step = 1e-9
    below, above = (torch.tensor([[EDGE + s]], dtype=torch.float64) for s in (-step, step))
    jump = (path.with_jacobian(above)[0] - path.with_jacobian(below)[0])[0, 0]
    torch.testing.assert_close(jump, torch.tensor(0.35 + 0.45 * EDGE ** 2 - 0.1 - 0.2 * EDGE, dtype=torch.float64),
                               atol=1e-8, rtol=0)  # the branches' gap, up to their slopes over 2e-9
