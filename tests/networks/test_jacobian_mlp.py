"""JacobianMLP (the structured schema's networks): its forward-mode Jacobian is exact for every block and norm."""
from __future__ import annotations

import itertools

import pytest
import torch

from lightning_bodyschema.errors import BodySchemaInputError
from lightning_bodyschema.networks.structured import BLOCKS, JACOBIAN_CHUNK, NORMS, JacobianMLP

COMBINATIONS = list(itertools.product(BLOCKS, NORMS))


def _random_net(block, norm, in_dim=5, out_dim=4, hidden=16, n_hidden=3):
    """float64, every parameter drawn (LayerNorm's affine weight and bias too, which start at 1 and 0)."""
    torch.manual_seed(0)
    net = JacobianMLP(in_dim, out_dim, hidden, n_hidden, block=block, norm=norm).double()
    with torch.no_grad():
        for p in net.parameters():
            p.copy_(torch.randn_like(p) * 0.6)
    return net


def _forward_tol(y, n_layers: int) -> float:
    """The same layers by another kernel (with the Jacobian vs the plain forward): a few roundings per layer at
    the output's scale."""
    return 64 * n_layers * torch.finfo(y.dtype).eps * max(1.0, y.abs().max().item())


@pytest.mark.parametrize("n_hidden", [1, 2, 4])
@pytest.mark.parametrize("block, norm", COMBINATIONS)
def test_with_jacobian_equals_autograd_jacobian(block, norm, n_hidden):
    net = _random_net(block, norm, n_hidden=n_hidden)
    x = torch.randn(7, 5, dtype=torch.float64)
    y, J = net.with_jacobian(x)
    expected = torch.func.vmap(torch.func.jacrev(lambda xi: net(xi[None])[0]))(x)  # (B, out, in)
    torch.testing.assert_close(y, net(x), atol=_forward_tol(y, n_layers=n_hidden + 1), rtol=0)
    assert J.shape == (7, 4, 5) and expected.abs().max() > 1e-2  # a real, non-vanishing derivative
    torch.testing.assert_close(J, expected, atol=1e-10, rtol=0)


@pytest.mark.parametrize("block, norm", [("plain", "none"), ("residual", "layer")])
def test_batches_beyond_one_pass_equal_autograd_across_the_pass_boundaries(block, norm):
    """More postures than ``JACOBIAN_CHUNK`` run in several passes: every row (those beside each boundary included)
    is autograd's Jacobian of that posture, and its value the forward pass's."""
    net = _random_net(block, norm)
    x = torch.randn(2 * JACOBIAN_CHUNK + 3, 5, dtype=torch.float64)
    y, J = net.with_jacobian(x)
    rows = [0, JACOBIAN_CHUNK - 1, JACOBIAN_CHUNK, 2 * JACOBIAN_CHUNK - 1, 2 * JACOBIAN_CHUNK, len(x) - 1]
    expected = torch.func.vmap(torch.func.jacrev(lambda xi: net(xi[None])[0]))(x[rows])
    torch.testing.assert_close(y, net(x), atol=_forward_tol(y, n_layers=4), rtol=0)
    assert J.shape == (len(x), 4, 5) and expected.abs().max() > 1e-2
    torch.testing.assert_close(J[rows], expected, atol=1e-10, rtol=0)


@pytest.mark.parametrize("block, norm", COMBINATIONS)
def test_jacobian_is_differentiable_in_the_weights(block, norm):
    """A loss on J trains the weights: its weight gradient equals autograd's through torch.func's Jacobian."""
    net = _random_net(block, norm)
    x = torch.randn(6, 5, dtype=torch.float64)
    net.with_jacobian(x)[1].pow(2).sum().backward()
    params = {name: p.detach() for name, p in net.named_parameters()}
    jacobian = lambda p: torch.func.vmap(torch.func.jacrev(  # noqa: E731
        lambda xi: torch.func.functional_call(net, p, (xi[None],))[0]))(x)
    expected = torch.func.grad(lambda p: jacobian(p).pow(2).sum())(params)
    for name, p in net.named_parameters():  # the output bias alone does not move J (no gradient)
        grad = torch.zeros_like(p) if p.grad is None else p.grad
        assert (grad.abs().max() > 0) == (name != f"layers.{len(net.layers) - 1}.bias")
        torch.testing.assert_close(grad, expected[name], atol=1e-9, rtol=1e-9)


def test_default_network_keeps_its_state_dict_keys():
    """plain + none holds only ``layers`` (checkpoints from before the options load); layer norm adds ``norms``."""
    keys = set(JacobianMLP(3, 2, 8, 3).state_dict())
    assert keys == {f"layers.{i}.{w}" for i in range(4) for w in ("weight", "bias")}
    layer = set(JacobianMLP(3, 2, 8, 3, block="residual", norm="layer").state_dict())
    assert layer - keys == {f"norms.{i}.{w}" for i in range(3) for w in ("weight", "bias")}


def test_residual_block_adds_its_input():
    """With the residual branch's weights zeroed, a residual hidden step is the identity (a plain one gives 0)."""
    for block, expected_zero in (("residual", False), ("plain", True)):
        net = _random_net(block, "none", n_hidden=2)
        x = torch.randn(3, 5, dtype=torch.float64)
        with torch.no_grad():
            net.layers[1].weight.zero_(), net.layers[1].bias.zero_()
            before = net.layers[0](x)
            after = net.layers[2](torch.nn.functional.silu(before if block == "residual" else torch.zeros_like(before)))
        torch.testing.assert_close(net(x), after)
        assert (net(x) == net.layers[2].bias).all().item() is expected_zero


@pytest.mark.parametrize("kwargs, named", [({"block": "resnet"}, "block='resnet'"),
                                           ({"norm": "batch"}, "norm='batch'")])
def test_bad_block_or_norm_is_one_clear_error(kwargs, named):
    with pytest.raises(BodySchemaInputError, match=named) as err:
        JacobianMLP(3, 2, 8, 2, **kwargs)
    assert "allowed" in str(err.value)
