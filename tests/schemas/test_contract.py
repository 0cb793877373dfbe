"""The body-schema contract: capabilities are declared and held to the class; the adapter dispatches on them.

The SI path runs a real architecture: ``ExactBodySchema`` answers ``adapt_si`` with the equilibrium QP (proxsuite)
on the robot's own MuJoCo model, turning each fault constraint into tension bounds through the spring — the
physics oracle as a schema. Through ``Adapter`` it must then return the oracle's commands on every feasible case,
each fault met exactly, and ``infeasible`` where the oracle finds none.
"""
from __future__ import annotations

import numpy as np
import pytest
import torch
from physics_checks import torque_residual
from torch import nn

from lightning_bodyschema.contract import (ADAPTS_IN_SI, ADAPTS_NORMALIZED, EPOCH_HOOK, REFRESHES_DERIVED_STATE,
                                           SchemaContract)
from lightning_bodyschema.evaluation import make_fault_cases, oracle_commands
from lightning_bodyschema.schemas import AutoEncoderSchema, BodySchema, DiffusionSchema, VAESchema
from lightning_bodyschema.sim import elongation_from_tension, solve_equilibrium_qp


class ExactBodySchema(BodySchema):
    """Healthy command from a linear map (trainable); adaptation by the equilibrium QP on the true model, in SI."""

    capabilities = frozenset({ADAPTS_IN_SI})

    def __init__(self, robot=None, lr: float = 1e-3, lr_final=None, batch_size: int = 64):
        super().__init__(robot=robot, lr=lr, lr_final=lr_final, batch_size=batch_size)
        self.net = nn.Linear(self.n_joints, self.x_dim)

    def training_loss(self, q_n, x_n):
        return (self.net(q_n) - x_n).pow(2).sum(-1).mean(), {}

    def generate(self, q_n):
        return self.net(q_n)

    def adapt_si(self, q_rad, bounds, variant, **options):
        q = q_rad.numpy()
        l_geo, G, tau_bias = self.robot_model.kinematics(q)
        lo, hi = bounds.on_host().tension_box(l_geo)  # length bounds become tension bounds through the spring
        f_ref = np.full_like(lo, self.spring.f_max_n / 2.0)
        f, ok = solve_equilibrium_qp(G, tau_bias, f_ref, f_lo_n=np.minimum(lo, hi), f_hi_n=hi)
        f = np.where((ok & (lo <= hi).all(1))[:, None], f, np.nan)
        return torch.as_tensor(l_geo - elongation_from_tension(f, self.spring)), torch.as_tensor(f)


def test_si_adaptation_through_the_adapter_is_the_physics_oracle(dm):
    schema = ExactBodySchema(robot=dm.robot)
    schema.normalizer.load_state_dict(dm.normalizer.state_dict())
    q, x = dm.splits["val"]
    m = schema.n_muscles
    cases = make_fault_cases(q.numpy(), x[:, :m].numpy(), 6, seed=3)
    result = schema.adapter(cases.faults)(cases.q_ref)
    feasible, l_oracle, f_oracle = oracle_commands(schema.robot_model, cases, schema.spring)
    assert feasible.any() and (~feasible).any()
    ok = result.status == "ok"
    np.testing.assert_array_equal(ok, feasible)
    assert (result.status[~feasible] == "infeasible").all()
    np.testing.assert_allclose(result.f_n[ok], f_oracle[ok], rtol=0, atol=1e-9)
    np.testing.assert_allclose(result.l_motor_m[ok], l_oracle[ok], rtol=0, atol=1e-12)
    assert torque_residual(schema.robot_model, cases.q_ref[ok], result.f_n[ok]).max() < 1e-6
    faults = cases.faults
    assert np.abs(np.where(faults.cut[ok], result.f_n[ok], 0.0)).max() == 0.0  # cut: exactly no tension
    assert (np.where(faults.fix[ok], result.l_motor_m[ok] - faults.l_fixed_m[ok], -1.0) <= 1e-12).all()  # jam held


def test_adaptation_goes_where_the_capability_says(dm):
    """A declared SI schema is never handed a normalized penalty, a normalized one never SI constraints."""
    si = ExactBodySchema(robot=dm.robot)
    si.normalizer.load_state_dict(dm.normalizer.state_dict())
    from lightning_bodyschema.faults import Faults

    faults = Faults.none(1, si.n_muscles)
    adapter = si.adapter(faults, check_physics=False)
    assert adapter.in_si and not hasattr(adapter, "penalty")
    assert not DiffusionSchema.capabilities & {ADAPTS_IN_SI}


def test_the_architectures_declare_what_they_do():
    assert DiffusionSchema.capabilities == {ADAPTS_NORMALIZED}
    assert AutoEncoderSchema.capabilities == VAESchema.capabilities == {ADAPTS_NORMALIZED, EPOCH_HOOK,
                                                                         REFRESHES_DERIVED_STATE}
    assert BodySchema.capabilities == frozenset()


def test_a_schema_satisfies_the_declared_contract(dm):
    assert isinstance(ExactBodySchema(robot=dm.robot), SchemaContract)


def test_a_capability_must_match_the_methods():
    with pytest.raises(TypeError, match="declares 'adapts_in_si' but defines no adapt_si"):
        type("Declared", (BodySchema,), {"capabilities": frozenset({ADAPTS_IN_SI})})
    with pytest.raises(TypeError, match="defines adapt_normalized but does not declare 'adapts_normalized'"):
        type("Undeclared", (BodySchema,), {"adapt_normalized": lambda self, q_n, penalty, variant: q_n})
    with pytest.raises(TypeError, match="names \\['adapts_in_latin'\\]"):
        type("Unknown", (BodySchema,), {"capabilities": frozenset({"adapts_in_latin"})})
    with pytest.raises(TypeError, match="adapts one way"):
        type("Both", (BodySchema,), {"capabilities": frozenset({ADAPTS_IN_SI, ADAPTS_NORMALIZED}),
                                     "adapt_si": lambda *a: None, "adapt_normalized": lambda *a: None})


def test_a_regressor_declares_no_adaptation_and_adapt_says_so(dm):
    from lightning_bodyschema.faults import Faults

    plain = type("Plain", (ExactBodySchema,), {"capabilities": frozenset(), "adapt_si": BodySchema.adapt_si})
    schema = plain(robot=dm.robot)
    assert not schema.supports_adaptation
    with pytest.raises(NotImplementedError, match="does not implement adaptation"):
        schema.adapt(np.zeros((1, schema.n_joints)), Faults.none(1, schema.n_muscles))
