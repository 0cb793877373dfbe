"""The fast latent descent (the decoder's FrozenMLP, the penalty's residual) returns the autograd reference's z."""
import numpy as np
import pytest
import torch
from physics_checks import assert_same_commands, frozen_pass, mixed_faults

from lightning_bodyschema.samplers import LatentConfig, latent_descent, reference_latent_descent

F64_TOL = 1e-5
F32_TOL_N, F32_TOL_M = 0.05, 2e-5


@pytest.mark.parametrize("options", [{}, {"optimizer": "adam"}, {"variant": "literal"}], ids=["sgd", "adam", "literal"])
def test_fast_latent_descent_returns_the_reference_commands(latent60, latent60_f64, dm, options):
    q, faults = mixed_faults(latent60, dm)
    assert_same_commands(latent60_f64.adapt(q, faults, **options), latent60_f64.adapt(q, faults, fast=False, **options),
                         F64_TOL, F64_TOL)
    assert_same_commands(latent60.adapt(q, faults, **options), latent60.adapt(q, faults, fast=False, **options),
                         F32_TOL_N, F32_TOL_M)


def test_frozen_decoder_matches_the_module_and_autograd(latent60_f64):
    decoder = latent60_f64.decoder
    q, z, v = (torch.randn(4, d, dtype=torch.float64) for d in (decoder.q_dim, decoder.z_latent_dim, 12))
    frozen = decoder.frozen()
    bias = frozen.first_bias(q)
    z_req = z.clone().requires_grad_(True)
    ref = decoder(q, z_req)
    ref_vjp, = torch.autograd.grad(ref, z_req, v)
    out, vjp = frozen_pass(frozen, z, bias, v)
    torch.testing.assert_close(out, ref.detach())
    torch.testing.assert_close(vjp, ref_vjp)


@pytest.mark.parametrize("optimizer", ["sgd", "adam"])
def test_latent_descent_with_a_two_slot_penalty_matches_the_reference(latent60_f64, dm, optimizer):
    """A jam and a band on one motor: the penalty has two slots and no uniform weight."""
    q, faults = mixed_faults(latent60_f64, dm, n=6)
    penalty = latent60_f64.penalty_builder("default")(faults.constraints(latent60_f64.spring.f_max_n))
    assert len(penalty.slots) == 2 and penalty.uniform_weight is None
    q_n = latent60_f64.encode_q(torch.as_tensor(q))
    z0 = latent60_f64.z_latent_ref.expand(len(q), -1)
    config = LatentConfig(lr=0.05, n_steps=50, optimizer=optimizer)
    frozen = latent60_f64.decoder.frozen()
    torch.testing.assert_close(latent_descent(frozen, frozen.first_bias(q_n), z0, penalty, config),
                               reference_latent_descent(latent60_f64.decoder, q_n, z0, penalty, config), rtol=0, atol=F64_TOL)


def test_latent_descent_lowers_the_penalty(latent60, dm):
    q, faults = mixed_faults(latent60, dm)
    penalty = latent60.penalty_builder("default")(faults.constraints(latent60.spring.f_max_n))
    q_n = latent60.encode_q(torch.as_tensor(q))
    start = penalty(latent60.generate(q_n).detach())
    after = penalty(latent60.adapt_normalized(q_n, penalty, "default").detach())
    assert after.sum() < 0.5 * start.sum() and (after <= start + 1e-6).all()
