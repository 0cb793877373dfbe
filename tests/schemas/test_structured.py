"""StructuredSchema: its moment arms are the derivative of its own lengths, its fault QP meets every fault exactly,
it trains from a recorded CSV without a model, and its healthy commands hold the paper arm on MuJoCo."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from physics_checks import fit_structured as _fit
from physics_checks import rounding_tol, spring_length_tol

from lightning_bodyschema.apps.dataset_tool import make_dataset_main
from lightning_bodyschema.data import EquilibriumDataModule, RecordedDataModule
from lightning_bodyschema.errors import BodySchemaInputError
from lightning_bodyschema.evaluation.cases import HealthyPool, make_binding_cases
from lightning_bodyschema.faults import Faults
from lightning_bodyschema.faults.qp import INFEASIBLE_LEARNED, OK, balance_residual_nm, fault_command
from lightning_bodyschema.schemas import StructuredSchema, load_schema
from lightning_bodyschema.sim import (MusculoskeletalModel, SpringParams, elongation_from_tension,
                                      tension_from_elongation)

SPRING = SpringParams()  # the paper's: k 1000 N, alpha 20 1/m, f_max 150 N
_BODY_ROUNDINGS = 256  # a learned length's sum over a polynomial's terms or a layer's width, one rounding each


@pytest.fixture(scope="module")
def paper_arm():
    datamodule = EquilibriumDataModule(n_samples=800, seed=0, cache_dir=None)
    schema, trainer = _fit(datamodule, epochs=30)
    return schema, datamodule, trainer


# ---------------------------------------------------------------------------- the learned body
@pytest.mark.parametrize("torque_model", ["potential", "direct"])
def test_moment_arms_and_potential_torque_are_exact_derivatives(torque_model):
    """G = d l_geo/dq (and tau = dV/dq for the potential) against central differences, float64, untrained."""
    datamodule = EquilibriumDataModule(n_samples=50, seed=1, cache_dir=None)
    datamodule.setup("fit")
    torch.manual_seed(0)
    schema = StructuredSchema(robot=datamodule.robot, hidden=32, n_hidden=3, torque_model=torque_model).double()
    schema.normalizer.load_state_dict(datamodule.normalizer.state_dict())
    schema.tau_scale_nm.copy_(schema.torque_scale())
    q = torch.as_tensor(datamodule.splits["val"][0][:16], dtype=torch.float64)
    _, G, tau = (torch.as_tensor(a) for a in schema.body_si(q))
    h = 1e-6
    for j in range(schema.n_joints):
        step = torch.zeros(schema.n_joints, dtype=torch.float64)
        step[j] = h
        l_plus, l_minus = schema.body_si(q + step)[0], schema.body_si(q - step)[0]
        fd = torch.as_tensor((l_plus - l_minus) / (2 * h))
        torch.testing.assert_close(G[:, :, j], fd, atol=1e-9, rtol=1e-6)
        assert G[:, :, j].abs().max() > 1e-4  # a real derivative, not zeros on both sides
    if torque_model == "potential":  # tau_j = c dV_n/dq_j: the same c for every joint, so tau is a gradient
        c = (schema.tau_scale_nm * schema._half_range()).mean()
        V = lambda qq: c * schema.torque_net(schema.normalizer.encode_q(qq))[:, 0]  # noqa: E731
        fd = torch.stack([(V(q + h * e) - V(q - h * e)) / (2 * h)
                          for e in torch.eye(schema.n_joints, dtype=torch.float64)], 1)
        torch.testing.assert_close(tau, fd.detach(), atol=1e-7, rtol=1e-6)


# ---------------------------------------------------------------------------- the fault QP, known answers
def _one_joint_body(batch):
    """Three muscles on one joint: arms +2, -1, +1 cm [m/rad], l_geo 0.2 m, tau -1.4 N m (G^T f = 1.4 N m)."""
    G = np.broadcast_to(np.array([[0.02], [-0.01], [0.01]]), (batch, 3, 1)).copy()
    return np.full((batch, 3), 0.2), G, np.full((batch, 1), -1.4)


def _free(batch, m=3):
    return (np.zeros((batch, m)), np.full((batch, m), 150.0), np.full((batch, m), -np.inf),
            np.full((batch, m), np.inf))


def test_fault_qp_healthy_answer_is_the_projection_onto_the_balance():
    l_geo, G, tau = _one_joint_body(1)
    f_ref = np.full((1, 3), 75.0)
    l_motor, f, status = fault_command(l_geo, G, tau, f_ref, *_free(1), SPRING)
    g = G[0, :, 0]
    expected = f_ref[0] - g * (g @ f_ref[0] + tau[0, 0]) / (g @ g)  # min ||f - f_ref|| s.t. g.f = -tau, inside
    assert (expected > 1).all() and (expected < 149).all()
    np.testing.assert_allclose(f[0], expected, atol=1e-6)
    np.testing.assert_allclose(l_motor, l_geo - elongation_from_tension(f, SPRING), rtol=0,
                               atol=spring_length_tol(l_geo))
    assert status[0] == OK and balance_residual_nm(G, tau, f)[0] <= 1e-6


def test_fault_qp_meets_cut_jam_weak_and_band_exactly():
    batch = 4
    l_geo, G, tau = _one_joint_body(batch)
    f_lo, f_hi, l_lo, l_hi = _free(batch)
    f_hi[0, 0], f_lo[0, 0] = 0.0, 0.0  # case 0: muscle 0 cut
    l_hi[1, 1] = 0.2 - 0.004  # case 1: muscle 1 jammed 4 mm short of l_geo: its spring pulls >= 83 N
    f_hi[2, 1] = 20.0  # case 2: muscle 1 weakened to 20 N
    l_lo[3, 2], l_hi[3, 2] = 0.2 - 0.002, 0.2 - 0.001  # case 3: motor 2 banded 1..2 mm short of l_geo
    l_motor, f, status = fault_command(l_geo, G, tau, np.full((batch, 3), 75.0), f_lo, f_hi, l_lo, l_hi, SPRING)
    assert (status == OK).all()
    assert f[0, 0] == 0.0
    jam_tension = tension_from_elongation(0.004, SPRING)
    assert l_motor[1, 1] <= l_hi[1, 1] and f[1, 1] >= jam_tension - 1e-9 and jam_tension > 80
    assert f[2, 1] <= 20.0
    assert l_lo[3, 2] <= l_motor[3, 2] <= l_hi[3, 2]
    assert tension_from_elongation(0.001, SPRING) - 1e-9 <= f[3, 2] <= tension_from_elongation(0.002, SPRING) + 1e-9
    assert (balance_residual_nm(G, tau, f) <= 1e-6).all()
    assert (f >= 0).all() and (f <= f_hi + 1e-12).all()


def test_unholdable_posture_gets_least_squares_within_bounds_and_a_status():
    l_geo, G, tau = _one_joint_body(2)
    tau[0] = 10.0  # needs G^T f = -10 N m: muscle 1 (-1 cm) alone can give -1.5 N m
    f_lo, f_hi, l_lo, l_hi = _free(2)
    l_hi[1, 1], f_hi[1, 1] = 0.2 - 0.02, 150.0  # case 1: a jam whose spring would pull 1.6 kN > f_max: bounds cross
    l_motor, f, status = fault_command(l_geo, G, tau, np.full((2, 3), 75.0), f_lo, f_hi, l_lo, l_hi, SPRING)
    assert list(status) == [INFEASIBLE_LEARNED, INFEASIBLE_LEARNED]
    np.testing.assert_allclose(f[0], [0.0, 150.0, 0.0], atol=1e-6)  # the closest torque the box can give
    assert np.isfinite(f).all() and np.isfinite(l_motor).all() and (f >= 0).all() and (f <= 150.0).all()


# ---------------------------------------------------------------------------- on the paper arm
def _binding_cases(schema, datamodule, n=6):
    q, x = (a.numpy() for a in datamodule.splits["val"])
    pool = HealthyPool(q, x[:, :6], x[:, 6:])
    cases, _ = make_binding_cases(schema.robot_model, pool, n_per_condition=n, seed=0)
    return cases


def test_adapted_commands_meet_every_fault_and_the_learned_balance(paper_arm):
    schema, datamodule, _ = paper_arm
    cases = _binding_cases(schema, datamodule)
    faults = cases.faults
    result = schema.adapt(cases.q_ref, faults, check_physics=False)
    ok = result.ok
    assert ok.mean() >= 0.9, dict(zip(*np.unique(result.status, return_counts=True)))
    assert set(result.status[~ok]) <= {INFEASIBLE_LEARNED} and np.isnan(result.f_n[~ok]).all()
    l, f = result.l_motor_m[ok], result.f_n[ok]
    fk = faults.take(ok)
    l_geo, G, tau = schema.body_si(torch.as_tensor(cases.q_ref[ok]))
    assert (f[fk.cut] == 0.0).all()
    assert (l[fk.fix] <= fk.l_fixed_m[fk.fix]).all()
    assert (f[fk.fix] >= tension_from_elongation(l_geo[fk.fix] - fk.l_fixed_m[fk.fix], SPRING) - 1e-6).all()
    assert (f[fk.weak] <= fk.f_max_n[fk.weak]).all()
    lo, hi = fk.l_band_m[..., 0], fk.l_band_m[..., 1]
    assert ((l[fk.band] >= lo[fk.band]) & (l[fk.band] <= hi[fk.band])).all()
    assert (balance_residual_nm(G, tau, f) <= 1e-6).all()
    taut = f > 0
    # the body evaluated again on the ok rows (other blocks of rows: its sums in another order) and the spring's
    # roundings (~4e-14 m); a motor not at l_geo - delta(f) is off by 1e-5 m or more
    tol_m = rounding_tol(_BODY_ROUNDINGS, l_geo) + spring_length_tol(l_geo)
    np.testing.assert_allclose((l + elongation_from_tension(f, SPRING))[taut], l_geo[taut], rtol=0, atol=tol_m)
    assert fk.cut.any() and fk.fix.any() and fk.weak.any() and fk.band.any()


def test_healthy_command_holds_the_paper_arm_on_mujoco(paper_arm):
    """After 30 epochs: median equilibrium residual on the true arm 0.13 N m, lengths 0.08 mm (measured); untrained
    (same normalizer) 9.9 N m and 23 mm."""
    schema, datamodule, _ = paper_arm
    q, x = datamodule.splits["val"]
    errors = schema.physical_errors(q, x)
    assert errors["eq_residual_N_m"] < 0.4 and errors["length_residual_mm"] < 0.2, errors
    # the learned body's worst muscle per posture, logged beside them: MuJoCo against body_si, muscle by muscle
    rows = q[:1024].numpy()  # BODY_ERROR_ROWS
    miss_mm = 1e3 * np.abs(schema.body_si(torch.as_tensor(rows))[0] - schema.robot_model.kinematics(rows)[0])
    assert errors["worst_length_mm_p99"] == pytest.approx(np.percentile(miss_mm.max(axis=1), 99), rel=1e-9)
    assert errors["worst_length_mm_p99"] >= np.percentile(miss_mm, 99)  # the pooled figure never shows more
    assert errors["bad_posture_fraction"] == pytest.approx(np.mean(miss_mm.max(axis=1) > 0.1), abs=1e-12)


def test_bad_options_and_variants_are_refused(paper_arm):
    schema = paper_arm[0]
    faults = Faults.none(1, 6)
    with pytest.raises(BodySchemaInputError, match="unknown adaptation option"):
        schema.adapt(np.zeros((1, 2)), faults, n_steps=3)
    with pytest.raises(BodySchemaInputError, match="unknown adaptation variant"):
        schema.adapt(np.zeros((1, 2)), faults, variant="literal")
    with pytest.raises(BodySchemaInputError, match="torque_model"):
        StructuredSchema(robot=schema.hparams.robot, torque_model="spline")
    for bad, named in (({"block": "resnet"}, "block='resnet'; allowed"), ({"norm": "batch"}, "norm='batch'; allowed")):
        with pytest.raises(BodySchemaInputError, match=named):
            StructuredSchema(robot=schema.hparams.robot, **bad)


def test_checkpoint_round_trip_gives_the_same_commands(paper_arm, tmp_path):
    schema, _, trainer = paper_arm
    path = str(tmp_path / "structured.ckpt")
    trainer.save_checkpoint(path, weights_only=False)
    loaded = load_schema(path)
    q = np.array([[0.3, 0.8], [-0.2, 1.2]])
    for a, b in zip(schema.infer(q), loaded.infer(q)):
        np.testing.assert_array_equal(a, b)


# ---------------------------------------------------------------------------- recorded data, no MJCF
def test_trains_end_to_end_from_a_recorded_csv(tmp_path):
    path = str(tmp_path / "arm.csv")
    make_dataset_main(["--n", "400", "--seed", "3", "--out", path])
    schema, _ = _fit(RecordedDataModule(path, seed=3), epochs=30)
    assert not schema.has_physics
    arm = MusculoskeletalModel("paper_arm")  # the true body, for scoring only
    q = arm.sample_q(np.random.default_rng(11), 40)
    l_geo_true, G_true, tau_true = arm.kinematics(q)
    l_geo, G, tau = schema.body_si(torch.as_tensor(q))
    # the body the recorded rows imply, learned without MJCF (measured 0.14 mm, 0.18 N m; untrained ~23 mm)
    assert np.median(np.abs(l_geo - l_geo_true)) < 0.3e-3
    assert np.median(np.abs(tau - tau_true)) < 0.5
    result = schema.adapt(q, Faults.from_names(arm.muscle_names, cut=[[0]] * len(q)))
    assert set(result.status) <= {"unchecked", INFEASIBLE_LEARNED} and (result.status == "unchecked").mean() > 0.9
    unchecked = result.status == "unchecked"
    assert (result.f_n[unchecked, 0] == 0.0).all()


def test_per_muscle_springs_give_the_loss_of_the_same_scalar_spring():
    """myoArm's springs are per muscle (lists): the loss must read them as tensors, and equal lists = the scalar."""
    datamodule = EquilibriumDataModule(n_samples=50, seed=1, cache_dir=None)
    datamodule.setup("fit")
    q, x = datamodule.splits["train"]
    losses = []
    for spring in ({"k_n": 1000.0, "alpha_per_m": 20.0, "f_max_n": 150.0},
                   {"k_n": [1000.0] * 6, "alpha_per_m": [20.0] * 6, "f_max_n": [150.0] * 6}):
        torch.manual_seed(0)
        schema = StructuredSchema(robot={**datamodule.robot, "spring": spring}, hidden=16, n_hidden=1).double()
        schema.normalizer.load_state_dict(datamodule.normalizer.state_dict())
        q_n, x_n = schema.normalizer.encode_q(q.double()), schema.normalizer.encode_x(x.double())
        losses.append(schema.training_loss(q_n, x_n)[0])
    assert torch.isfinite(losses[0]) and losses[0] > 0
    torch.testing.assert_close(losses[0], losses[1], rtol=1e-12, atol=0)
