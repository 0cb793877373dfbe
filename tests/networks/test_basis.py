"""ProductTerms: the per-muscle polynomials' basis, dense (few postures) and grouped by support (many), against
the Legendre recurrence's product basis and against autograd, in float64."""
import numpy as np
import pytest
import torch
from physics_checks import rounding_tol

from lightning_bodyschema.networks import basis as basis_module
from lightning_bodyschema.networks.basis import ProductTerms, product_basis
from lightning_bodyschema.networks.polynomial import term_exponents
from lightning_bodyschema.networks.snapshot import TermsSnapshot

BLOCKS = np.array([[0, 0, 0, -1, -1], [-1, -1, -1, 0, 0], [0, -1, -1, 1, -1], [-1, 0, -1, -1, -1]])


@pytest.fixture(scope="module")
def terms():
    exponents = term_exponents(BLOCKS, np.array([16, 12, 16, 16]))  # supports of 0 to 3 joints
    return exponents, ProductTerms(exponents)


def _x(n, seed=0):
    return torch.rand(n, 5, dtype=torch.float64, generator=torch.Generator().manual_seed(seed)) * 2 - 1


@pytest.mark.parametrize("dense", [True, False])
def test_every_term_and_slope_equals_the_recurrence_product_basis(terms, dense):
    exponents, product = terms
    x = _x(64)
    phi, dphi = product_basis(x, torch.as_tensor(exponents), 16, slopes=True)  # (B, P), (B, N, P)
    got = product(x, slopes=True, dense=dense)
    assert got.grouped is not dense
    if dense:
        got_phi, got_dphi = got.phi, got.dphi.transpose(1, 2)
    else:  # (P, B) in the grouped order; per joint the rows of the terms that use it
        got_phi = torch.empty_like(phi).index_copy_(1, product.perm, got.phi.T)
        got_dphi = torch.zeros_like(dphi)
        for j, rows in enumerate(got.dphi):
            got_dphi[:, j].index_copy_(1, getattr(product, f"joint_terms{j}"), rows.T)
    # the power form rounds differently from the recurrence: ~1e-11 on values of order 1 at degree 16 (the slopes'
    # up to 256, so relative to them)
    torch.testing.assert_close(got_phi, phi, atol=1e-10, rtol=0)
    torch.testing.assert_close(got_dphi, dphi, atol=1e-10 * dphi.abs().max().item(), rtol=0)
    assert (got_dphi[:, torch.as_tensor(exponents).T == 0] == 0).all()  # a term's slope on a joint it lacks: exactly 0


@pytest.mark.parametrize("dense", [True, False])
def test_contracted_slopes_are_the_autograd_jacobian_and_both_paths_agree(terms, dense):
    exponents, product = terms
    coef = torch.randn(3, len(exponents), dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    x = _x(40, seed=2).requires_grad_()
    jacobian = torch.autograd.functional.jacobian(lambda z: product.contract(product(z, dense=dense), coef)[0], x)
    jacobian = torch.einsum("bmcn->bmn", jacobian * torch.eye(40, dtype=torch.float64)[:, None, :, None])
    with torch.no_grad():
        y_dense, dy_dense = product.contract(product(x, True, dense=True), coef)
        y_grouped, dy_grouped = product.contract(product(x, True, dense=False), coef)
    torch.testing.assert_close(dy_dense, jacobian, atol=1e-9, rtol=0)
    torch.testing.assert_close(y_grouped, y_dense, atol=1e-11, rtol=0)
    torch.testing.assert_close(dy_grouped, dy_dense, atol=1e-9, rtol=0)


_PRODUCT_ROUNDINGS = 4 * 7  # a few roundings per factor of a product of seven variables' Legendre values


def test_stacked_slopes_follow_the_chain_rule_into_shared_columns():
    """``TermsSnapshot`` (torch and numpy) over variables ``v = (x, 4 x - 1, x_1)`` whose slopes go into x's columns
    with their chain-rule factor: column 0 each term, the others its derivative in x, as autograd gives it."""
    exponents = np.random.default_rng(3).integers(0, 4, (60, 7)) * (np.random.default_rng(4).random((60, 7)) < 0.4)
    product = ProductTerms(exponents, columns=[0, 1, 2, 0, 1, 2, 1])
    scale = torch.tensor([1.0, 1.0, 1.0, 4.0, 4.0, 4.0, 1.0], dtype=torch.float64)
    variables = lambda x: torch.cat([x, 4 * x - 1, x[:, 1:2]], 1) * 0.2  # noqa: E731 (inside [-1, 1])
    x = _x(5)[:, :3]
    stacked = TermsSnapshot(product)
    got = stacked(variables(x), 0.2 * scale)
    host = stacked.on_host()(variables(x).numpy(), 0.2 * scale.numpy())  # numpy's own small products: ulps apart
    # a term is a product of up to 7 Legendre factors of degree <= 3 (or one factor's slope and its chain-rule
    # factor): a few roundings per factor at the basis' scale (~2e-14); a wrong factor or column is off by O(1)
    np.testing.assert_allclose(host, got.numpy(), rtol=0, atol=rounding_tol(_PRODUCT_ROUNDINGS, got))
    phi = lambda z: product_basis(variables(z), torch.as_tensor(exponents), 3)[0]  # noqa: E731
    jacobian = torch.autograd.functional.jacobian(lambda z: phi(z).sum(0), x)  # (P, B, 3): rows are independent
    tol = rounding_tol(_PRODUCT_ROUNDINGS, got)
    torch.testing.assert_close(got[..., 0], phi(x), atol=tol, rtol=0)
    torch.testing.assert_close(got[..., 1:], jacobian.permute(1, 0, 2), atol=tol, rtol=0)


def test_the_number_of_postures_picks_the_path(terms, monkeypatch):
    _, product = terms
    assert not product(_x(basis_module.DENSE_ROWS)).grouped
    assert product(_x(basis_module.DENSE_ROWS + 1)).grouped
    monkeypatch.setattr(basis_module, "DENSE_ROWS", 0)
    assert product(_x(1)).grouped


def test_a_constant_only_basis_and_a_joint_no_term_uses():
    product = ProductTerms(np.zeros((1, 3), dtype=np.int64))
    got = product(_x(40)[:, :3], slopes=True, dense=False)
    assert got.phi.tolist() == [[1.0] * 40] and all(d.shape == (0, 40) for d in got.dphi)
    y, dy = product.contract(got, torch.tensor([[2.5]], dtype=torch.float64))
    assert (y == 2.5).all() and (dy == 0).all() and dy.shape == (40, 1, 3)
