"""Network sizes match the paper (section IV-A) and the wiring carries q, t and x where it should."""
import pytest
import torch
from torch import nn
from physics_checks import frozen_pass, rounding_tol

from lightning_bodyschema.errors import BodySchemaInputError
from lightning_bodyschema.networks import MLP, Decoder, EpsMLP, VAEEncoder, build_autoencoder, count_parameters

M, N = 6, 2  # paper arm: 6 muscles, 2 joints
X_DIM = 2 * M  # x = [l_motor, f]
PAPER_COUNTS = {("AE", 3): 10_000, ("AE", 10): 11_000, ("AE", 30): 14_000,
                ("VAE", 3): 11_000, ("VAE", 10): 12_000, ("VAE", 30): 15_000}


@pytest.mark.parametrize("kind,latent", list(PAPER_COUNTS))
def test_autoencoder_parameter_count_matches_paper(kind, latent):
    enc, dec = build_autoencoder(X_DIM, N, latent, variational=kind == "VAE")
    n = count_parameters(enc) + count_parameters(dec)
    paper = PAPER_COUNTS[(kind, latent)]
    print(f"{kind}-{latent}: {n} parameters (paper ~{paper})")
    assert abs(n - paper) <= 0.15 * paper


def test_diffusion_parameter_count_matches_paper():
    n = count_parameters(EpsMLP(X_DIM, N))
    print(f"Diff: {n} parameters (paper ~11000)")
    assert abs(n - 11_000) <= 0.15 * 11_000


def test_counts_grow_with_latent_like_the_paper():
    # the paper's ordering: AE < VAE at each size, and each grows with the latent size
    def total(latent, vae):
        return sum(count_parameters(m) for m in build_autoencoder(X_DIM, N, latent, variational=vae))
    for vae in (False, True):
        assert total(3, vae) < total(10, vae) < total(30, vae)
    assert all(total(k, False) < total(k, True) for k in (3, 10, 30))


def test_encoder_shapes():
    x = torch.randn(5, X_DIM)
    enc, _ = build_autoencoder(X_DIM, N, 10)
    z_q, z_lat = enc(x)
    assert z_q.shape == (5, N) and z_lat.shape == (5, 8)
    venc, _ = build_autoencoder(X_DIM, N, 10, variational=True)
    assert isinstance(venc, VAEEncoder)
    assert [t.shape for t in venc(x)] == [(5, N), (5, 8), (5, 8)]


def test_decoder_depends_on_both_joint_angles():
    torch.manual_seed(0)
    dec = Decoder(N, 8, X_DIM)
    q = torch.empty(16, N).uniform_(-1.0, 1.0).requires_grad_(True)  # joint range [-1, 1] rad
    z = torch.randn(16, 8)
    x_hat = dec(q, z)
    assert x_hat.shape == (16, X_DIM)
    # d x_hat / d q for one sample has rank N: each joint angle moves the command in its own direction,
    # so adapting z_latent with q fixed (eq:latent-opt) really conditions on the posture
    jac = torch.autograd.functional.jacobian(lambda qq: dec(qq, z[:1]), q[:1].detach())  # (1, 2M, 1, N)
    assert torch.linalg.matrix_rank(jac.reshape(X_DIM, N)) == N
    # and for every sample in the batch, not just on average
    grad_q, = torch.autograd.grad(x_hat.pow(2).sum(), q)
    assert torch.all(grad_q.abs().sum(dim=1) > 1e-6)


def test_eps_mlp_uses_x_t_and_q_and_t():
    torch.manual_seed(0)
    net = EpsMLP(X_DIM, N)
    x, q = torch.randn(4, X_DIM), torch.randn(4, N)
    base = net(x, 50, q)
    assert base.shape == (4, X_DIM)
    assert not torch.allclose(net(x, 150, q), base)
    assert not torch.allclose(net(x, 50, q + 0.1), base)
    assert not torch.allclose(net(x + 0.1, 50, q), base)
    assert torch.equal(net(x, torch.full((4,), 50), q), base)  # int t == per-sample t


_LAYER_ROUNDINGS = 64  # one layer: a matrix product over its width (rounded blockwise by the kernel), bias, activation


@pytest.mark.parametrize("activation,n_hidden", [("silu", 2), ("tanh", 3), ("silu", 1)])
def test_frozen_eps_mlp_forward_and_vjp_match_the_module_and_autograd(activation, n_hidden):
    """The one hand-written forward/backward (FrozenMLP) against the module and autograd, in float64."""
    torch.manual_seed(0)
    net = EpsMLP(X_DIM, N, n_hidden=n_hidden, activation=activation).double()
    x, q, v = (torch.randn(7, d, dtype=torch.float64) for d in (X_DIM, N, X_DIM))
    steps = [199, 120, 7, 0]
    frozen = net.frozen()
    biases = net.step_biases(frozen, q, steps)
    for i, t in enumerate(steps):
        x_req = x.clone().requires_grad_(True)
        eps_ref = net(x_req, t, q)
        vjp_ref, = torch.autograd.grad(eps_ref, x_req, v)
        # the same layers by hand, other kernels: a few tens of roundings per layer at the output's scale (~6e-14);
        # a wrong activation slope or a transposed weight is off by O(0.1)
        tol = rounding_tol(_LAYER_ROUNDINGS * (n_hidden + 1), 1.0, eps_ref, vjp_ref)  # activations of order 1
        eps, vjp = frozen_pass(frozen, x, biases[i], v)
        torch.testing.assert_close(eps, eps_ref.detach(), rtol=0, atol=tol)
        torch.testing.assert_close(vjp, vjp_ref, rtol=0, atol=tol)


def test_a_frozen_snapshot_does_not_follow_later_weight_changes():
    """A snapshot is a copy: its owner (the schema's inference cache) decides when to rebuild it."""
    torch.manual_seed(0)
    net = EpsMLP(X_DIM, N).double()
    x, q = torch.randn(3, X_DIM, dtype=torch.float64), torch.randn(3, N, dtype=torch.float64)
    frozen = net.frozen()
    before = frozen_pass(frozen, x, net.step_biases(frozen, q, [50])[0])
    with torch.no_grad():
        for p in net.parameters():
            p.add_(0.1)
    torch.testing.assert_close(frozen_pass(frozen, x, net.step_biases(frozen, q, [50])[0]), before)
    fresh = net.frozen()
    torch.testing.assert_close(frozen_pass(fresh, x, net.step_biases(fresh, q, [50])[0]), net(x, 50, q))


def test_an_activation_without_a_hand_written_derivative_has_no_snapshot():
    assert EpsMLP(X_DIM, N, activation="relu").frozen() is None


@pytest.mark.parametrize("kwargs", [dict(in_dim=0, hidden=4, out_dim=2), dict(in_dim=3, hidden=4, out_dim=2.0),
                                    dict(in_dim=3, hidden=4, out_dim=2, activation="swish!")])
def test_bad_mlp_arguments_raise(kwargs):
    with pytest.raises(BodySchemaInputError):
        MLP(**kwargs)


def test_latent_must_exceed_q_dim():
    with pytest.raises(BodySchemaInputError, match="latent_dim=2"):
        build_autoencoder(X_DIM, N, 2)


def test_mlp_accepts_activation_class():
    mlp = MLP(3, 4, 2, 2, nn.SiLU)
    assert sum(isinstance(m, nn.SiLU) for m in mlp.modules()) == 2
