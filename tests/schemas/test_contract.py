"""The body-schema contract: capabilities are declared and held to the class; the adapter dispatches on them; what a
BodySchema must do (contract.py) is checked on the schemas, and a subclass that breaks one promise fails the check.

The SI path runs a real architecture: ``ExactBodySchema`` answers ``adapt_si`` with the equilibrium QP (proxsuite)
on the robot's own MuJoCo model, turning each fault constraint into tension bounds through the spring — the
physics oracle as a schema. Through ``Adapter`` it must then return the oracle's commands on every feasible case,
each fault met exactly, and ``infeasible`` where the oracle finds none.
"""
from __future__ import annotations

import numpy as np
import pytest
import torch
from physics_checks import fit_structured, motor_length_tol, torque_residual
from torch import nn

from lightning_bodyschema.contract import (ADAPTS_IN_SI, ADAPTS_NORMALIZED, EPOCH_HOOK, REFRESHES_DERIVED_STATE,
                                           SchemaContract, check_capabilities)
from lightning_bodyschema.evaluation import make_fault_cases, oracle_commands
from lightning_bodyschema.schemas import AutoEncoderSchema, BodySchema, DiffusionSchema, StructuredSchema, VAESchema
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
    f_tol_n = 1e-9
    np.testing.assert_allclose(result.f_n[ok], f_oracle[ok], rtol=0, atol=f_tol_n)
    # the same MuJoCo lengths less the spring's elongation at tensions within f_tol_n (~5e-14 m); a motor off its
    # bound or the elongation left out is off by 1e-5 m or more
    tol_m = motor_length_tol(f_tol_n, schema.spring, l_oracle[ok])
    np.testing.assert_allclose(result.l_motor_m[ok], l_oracle[ok], rtol=0, atol=tol_m)
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


def contract_breaches(schema, q_rad: np.ndarray, x_si: np.ndarray) -> list[str]:
    """What ``schema`` does against what contract.py says a BodySchema must do, at postures ``q_rad (B, N)`` [rad]
    with healthy commands ``x_si (B, 2M)`` [m, N]: one line per broken promise (empty: it keeps the contract)."""
    breaches, cls = [], type(schema)
    b, m, n = len(q_rad), schema.n_muscles, schema.n_joints
    try:
        check_capabilities(cls, BodySchema)
    except TypeError as error:
        breaches.append(f"capabilities: {error}")
    if not isinstance(schema, SchemaContract) or "default" not in schema.VARIANTS:
        breaches.append("attributes: SchemaContract's names, VARIANTS with 'default'")
    q = torch.as_tensor(q_rad)
    q_n, x_n = schema.encode_q(q), schema.normalizer.encode_x(torch.as_tensor(x_si)).to(schema.dtype)
    loss, logs = schema.training_loss(q_n, x_n)
    if not (torch.is_tensor(loss) and loss.dim() == 0 and torch.isfinite(loss)):
        breaches.append(f"training_loss: the loss is {loss!r}, not a finite scalar tensor")
    if not all(not torch.is_tensor(v) or (v.dim() == 0 and not v.requires_grad) for v in logs.values()):
        breaches.append("training_loss: logs hold a tensor that is not a detached scalar")
    with torch.no_grad():
        shaped = schema.generate(q_n)
    if tuple(shaped.shape) != (b, 2 * m):
        breaches.append(f"generate: x_n of shape {tuple(shaped.shape)}, not {(b, 2 * m)}")
    try:
        shapes = [getattr(a, "shape", a) for a in schema.infer(q_rad)]
    except RuntimeError as error:  # the healthy command decoded from a generate of the wrong width
        shapes = [str(error)]
    if shapes != [(b, m), (b, m)]:
        breaches.append(f"infer: not two (B, M) arrays: {shapes}")
    decoded = schema.decode(x_n)  # back in normalized units (scale 1): the schema dtype's rounding, 8 float32 ulps
    back = schema.normalizer.encode_x(decoded) if decoded.dtype == torch.float64 else None
    if back is None or not torch.allclose(back, x_n.to(torch.float64), rtol=0, atol=1e-6):
        breaches.append("decode: does not give the SI command back in float64")
    return breaches + _adaptation_breaches(schema, q, b, m, n)


def _adaptation_breaches(schema, q, b: int, m: int, n: int) -> list[str]:
    """The declared adaptation's outputs (contract.py): adapt_si's (B, M) float64 pair (and a (B,) status), or
    adapt_normalized's (B, 2M) normalized command."""
    from lightning_bodyschema.faults import Faults
    from lightning_bodyschema.faults.bounds import FaultBounds
    from lightning_bodyschema.status import Status

    faults = Faults.none(b, m)
    if ADAPTS_IN_SI in schema.capabilities:
        out = schema.adapt_si(q, FaultBounds.from_faults(faults, schema.spring.f_max_n, schema.spring), "default")
        pair_ok = len(out) in (2, 3) and all(tuple(a.shape) == (b, m) and str(a.dtype).endswith("float64")
                                               for a in out[:2])
        status_ok = len(out) == 2 or (len(out[2]) == b and all(isinstance(s, Status) for s in out[2]))
        return [] if pair_ok and status_ok else ["adapt_si: not (l_motor_m, f_n[, status]) of (B, M) float64"]
    if ADAPTS_NORMALIZED in schema.capabilities:
        penalty = schema.penalty_builder("default")(faults.constraints(schema.spring.f_max_n))
        out = schema.adapt_normalized(schema.encode_q(q), penalty, "default")
        return [] if tuple(out.shape) == (b, 2 * m) else [f"adapt_normalized: shape {tuple(out.shape)}"]
    return []


def test_an_si_schema_is_handed_ordinary_tensors_without_grad_in_inference_mode_or_out_of_it(dm):
    """Lightning's val/test/predict loops run under inference mode: ``adapt_si`` still gets ordinary tensors (a
    schema may build autograd graphs of its own) and no grad, as outside it."""
    seen = []

    class Probe(ExactBodySchema):
        def adapt_si(self, q_rad, bounds, variant, **options):
            seen.append((torch.is_inference_mode_enabled(), torch.is_grad_enabled(), q_rad.is_inference()))
            return super().adapt_si(q_rad, bounds, variant, **options)

    from lightning_bodyschema.faults import Faults

    schema = Probe(robot=dm.robot)
    schema.normalizer.load_state_dict(dm.normalizer.state_dict())
    q = _postures(dm, 2)[0]
    adapter = schema.adapter(Faults.none(len(q), schema.n_muscles), check_physics=False)
    outside = adapter(q)
    with torch.inference_mode():
        inside = adapter(q)
    assert seen == [(False, False, False)] * 2
    np.testing.assert_array_equal(inside.f_n, outside.f_n)


class _NarrowCommand(ExactBodySchema):
    """Breaks ``generate``: the tensions only."""

    def generate(self, q_n):
        return super().generate(q_n)[:, self.n_muscles:]


class _Float32Command(ExactBodySchema):
    """Breaks ``adapt_si``: float32 tensors."""

    def adapt_si(self, q_rad, bounds, variant, **options):
        return tuple(t.float() for t in super().adapt_si(q_rad, bounds, variant, **options))


class _LossPerSample(ExactBodySchema):
    """Breaks ``training_loss``: one loss per sample instead of their mean."""

    def training_loss(self, q_n, x_n):
        return (self.net(q_n) - x_n).pow(2).sum(-1), {}


def _postures(dm, b: int = 5):
    q, x = dm.splits["val"]
    return q[:b].numpy(), x[:b].numpy()


@pytest.mark.parametrize("cls", [ExactBodySchema, DiffusionSchema, StructuredSchema])
def test_every_kind_of_schema_keeps_the_contract(dm, cls):
    """A schema that adapts in SI (the test's QP on the true body, the structured schema's on its learned one) and
    one that adapts normalized commands: every promise of contract.py holds (fresh weights: shapes and units, not
    accuracy)."""
    if cls is StructuredSchema:  # its body is fitted, not trained: one epoch fits it
        schema = fit_structured(dm)[0]
    else:
        schema = cls(robot=dm.robot)
        schema.normalizer.load_state_dict(dm.normalizer.state_dict())
    assert contract_breaches(schema, *_postures(dm)) == []


@pytest.mark.parametrize("cls, promise", [(_NarrowCommand, "generate"), (_Float32Command, "adapt_si"),
                                          (_LossPerSample, "training_loss")])
def test_a_subclass_that_breaks_the_contract_fails_it(dm, cls, promise):
    """The check can fail: a subclass that keeps every declaration (it is a valid class) but breaks one promise."""
    schema = cls(robot=dm.robot)
    schema.normalizer.load_state_dict(dm.normalizer.state_dict())
    breaches = contract_breaches(schema, *_postures(dm))
    assert breaches and breaches[0].startswith(promise), breaches
    assert all(b.startswith((promise, "infer")) for b in breaches), breaches  # infer decodes generate's output


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
