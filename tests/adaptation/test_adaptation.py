"""Fault adaptation on real (briefly) trained schemas: constraints met, safety of the returned command."""
import copy

import numpy as np
import pytest
from physics_checks import torque_residual, train_schema

from lightning_bodyschema.adaptation.command import FAULT_TOL_N
from lightning_bodyschema.errors import BodySchemaInputError
from lightning_bodyschema.faults import Faults
from lightning_bodyschema.schemas import AutoEncoderSchema, VAESchema


@pytest.fixture(scope="module")
def diffusion(diff400):
    return diff400  # conftest: one 400-epoch schema for tests/adaptation and tests/faults


def _torque_residual(schema, q, f):
    return torque_residual(schema.robot_model, q, f)


def test_unguided_denoising_is_the_healthy_command(diffusion):
    schema, dm = diffusion
    q = dm.splits["val"][0][:8].numpy()
    result = schema.adapt(q, Faults.none(8, schema.n_muscles))
    np.testing.assert_allclose(result.f_n, np.clip(schema.infer(q)[1], 0, 150), atol=0.2)  # only f-bounds guide


def test_default_guidance_cuts_the_tension_and_others_take_over(diffusion):
    schema, dm = diffusion
    q = dm.splits["val"][0][:20].numpy()
    names = schema.robot_model.muscle_names
    faults = Faults.from_names(names, cut=[["biarticular_flexor"]] * 10 + [["shoulder_extensor"]] * 10)
    plain_l, plain_f = schema.infer(q)
    result = schema.adapt(q, faults)
    # the true physics decides which cases any command could hold; exactly those carry a command
    feasible = result.diagnostics["feasible"]
    assert 0 < (~feasible).sum() < len(q) // 2
    assert (result.status == np.where(feasible, "ok", "infeasible")).all() and np.isnan(result.f_n[~feasible]).all()
    best_effort = result.diagnostics["best_effort_f_n"]
    assert np.abs(best_effort[faults.cut]).max() < 1.0 and np.abs(plain_f[faults.cut]).min() > 5.0
    # the arm is still held: the remaining muscles supply the lost torque (no worse than the healthy estimate + 1 N m)
    ok = result.status == "ok"
    assert np.median(_torque_residual(schema, q[ok], result.f_n[ok])) < \
        np.median(_torque_residual(schema, q[ok], plain_f[ok])) + 1.0
    assert (result.f_n[ok] >= 0).all() and (result.f_n[ok] <= 150).all()


def test_default_guidance_respects_a_jammed_motor(diffusion):
    schema, dm = diffusion
    q = dm.splits["val"][0][:12].numpy()
    plain_l, _ = schema.infer(q)
    l_fixed = np.full_like(plain_l, np.nan)
    l_fixed[:, 2] = plain_l[:, 2] - 0.002  # the elbow flexor jammed 2 mm short of the healthy command
    faults = Faults(np.zeros_like(plain_l, bool), np.isfinite(l_fixed), l_fixed)
    result = schema.adapt(q, faults, check_physics=False)  # the guidance itself, feasible or not
    assert (result.l_motor_m[:, 2] <= l_fixed[:, 2] + 1e-4).all()
    assert result.diagnostics["jam_violation_m"].max() < 1e-4


def test_literal_recipe_diverges_and_is_never_returned_as_a_command(diffusion):
    schema, dm = diffusion
    q = dm.splits["val"][0][:4].numpy()
    faults = Faults.from_names(schema.robot_model.muscle_names, cut=[["shoulder_flexor"]] * 4)
    result = schema.adapt(q, faults, variant="literal")
    assert (result.status == "non_finite").all()  # measured: SI-unit loss, lr 0.01 -> NaN (docs/design.md, guidance step)
    assert np.isnan(result.f_n).all() and np.isnan(result.l_motor_m).all()
    stable = schema.adapt(q, faults, variant="literal", step_scale="sqrt_abar")
    sent = stable.diagnostics["clipped_f_n"][:, 0]  # the cut muscle's tension, whatever the status
    assert np.abs(sent).max() < 5.0
    # a cut muscle still pulling more than the package's tolerance is no command (never ok)
    assert (stable.status == np.where(sent > FAULT_TOL_N, "fault_not_met", "ok")).all()
    assert np.isnan(stable.f_n[sent > FAULT_TOL_N]).all()


def test_a_case_adapts_the_same_alone_or_in_a_batch(diffusion):
    """Cases are independent: a command depends on its q and faults, not on its batch (float64 to see it exactly)."""
    schema, dm = diffusion
    schema = copy.deepcopy(schema).double()  # the shared schema stays float32 (no rounding of its buffers)
    q = dm.splits["val"][0][:6].numpy()
    faults = Faults.from_names(schema.robot_model.muscle_names, cut=[[i % 6] for i in range(6)])
    batch = schema.adapt(q, faults)
    for i in (0, 3):
        alone = schema.adapt(q[i:i + 1], Faults(faults.cut[i:i + 1], faults.fix[i:i + 1], faults.l_fixed_m[i:i + 1]))
        np.testing.assert_allclose(alone.f_n[0], batch.f_n[i], atol=1e-6)
        np.testing.assert_allclose(schema.infer(q[i:i + 1])[1][0], schema.infer(q)[1][i], atol=1e-9)


def test_bad_adaptation_requests_are_refused(diffusion):
    schema, _ = diffusion
    names = schema.robot_model.muscle_names
    with pytest.raises(BodySchemaInputError, match="unknown adaptation variant"):
        schema.adapt(np.zeros((1, 2)), Faults.none(1, 6), variant="magic")
    with pytest.raises(BodySchemaInputError, match="one row per case"):
        schema.adapt(np.zeros((2, 2)), Faults.none(1, 6))
    with pytest.raises(BodySchemaInputError, match="both cut and jammed"):
        Faults.from_names(names, cut=[["elbow_flexor"]], jam=[{"elbow_flexor": 0.1}])
    with pytest.raises(BodySchemaInputError, match="every muscle is cut"):
        Faults.from_names(names, cut=[names])
    with pytest.raises(BodySchemaInputError, match="out of range"):
        Faults.from_names(names, cut=[[6]])
    with pytest.raises(BodySchemaInputError, match="NaN"):
        schema.adapt(np.array([[np.nan, 0.0]]), Faults.none(1, 6))


@pytest.mark.parametrize("cls", [AutoEncoderSchema, VAESchema])
def test_latent_adaptation_reduces_the_constraint_loss(cls):
    schema, _, dm = train_schema(cls, 150)
    q = dm.splits["val"][0][:10].numpy()
    faults = Faults.from_names(schema.robot_model.muscle_names, cut=[["biarticular_extensor"]] * 10)
    before = np.abs(schema.infer(q)[1][:, 5])
    after = schema.adapt(q, faults, n_steps=400)
    sent = after.diagnostics["clipped_f_n"][:, 5]  # a cut still pulling beyond FAULT_TOL_N is fault_not_met
    assert (after.status == np.where(sent > FAULT_TOL_N, "fault_not_met", "ok")).all()
    assert np.median(np.abs(sent)) < 0.5 * np.median(before)
