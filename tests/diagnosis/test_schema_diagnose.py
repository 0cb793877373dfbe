"""A schema's diagnosis: its learned body (explicit or implied by its commands), that body's own error, the
streaming monitor, and a diagnosis handed to adapt."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from physics_checks import fit_structured, motor_length_tol, rounding_tol

from lightning_bodyschema.data import EquilibriumDataModule
from lightning_bodyschema.diagnosis import SensorLog, SensorNoise
from lightning_bodyschema.diagnosis.result import CUT, HEALTHY
from lightning_bodyschema.diagnosis.sensors import noisy, true_readings
from lightning_bodyschema.faults import Faults
from lightning_bodyschema.schemas.base import BodySchema
from lightning_bodyschema.status import Status

NOISE = SensorNoise()
_F32_ROUNDINGS = 16  # a float32 network's output in another batch: a few roundings per layer at its scale


@pytest.fixture(scope="module")
def structured():
    dm = EquilibriumDataModule(n_samples=1000, seed=0, cache_dir=None)
    schema, _ = fit_structured(dm, length_model="per_muscle", path_degree=10, torque_model="gravity")
    return schema, dm


def _pool(schema, dm, n=60):
    q = dm.splits["val"][0].numpy()[:n]
    l_cmd, f_cmd = schema.infer(q)
    keep = f_cmd.min(1) > 5.0
    return q[keep], l_cmd[keep], f_cmd[keep]


def _log(schema, pool, rows, faults, seed=0, load_cells=True):
    arm, spring = schema.robot_model, schema.spring
    q, l_cmd, f_cmd = (a[rows] for a in pool)
    truth = true_readings(arm, spring, q, l_cmd, f_cmd, faults.take(np.zeros(len(rows), int)))
    has_f = None if load_cells else np.zeros(arm.n_muscles, bool)
    read = noisy(truth, spring, NOISE, np.random.default_rng(seed), has_f)
    return SensorLog.from_rows(arm.joint_names, arm.muscle_names, read[0], read[1], l_cmd, f_cmd, read[2])


def test_the_body_error_is_measured_on_held_out_samples(structured):
    schema, _ = structured
    error = schema.body_error()
    assert error.length_m.shape == (schema.n_muscles,) and error.torque_nm.shape == (schema.n_joints,)
    # the per-muscle polynomial paths of the paper arm are micrometre-exact (tests/schemas): so is their error
    assert 0.0 < error.length_m.max() < 1e-5 and np.all(error.torque_nm < 0.05)


def test_the_body_a_schemas_commands_imply_is_its_explicit_body(structured):
    """The generic path (l_motor + delta(f), central differences, -G^T f) on a schema whose body is known."""
    schema, dm = structured
    q = dm.splits["val"][0].numpy()[:20]
    l_geo, G, tau = schema.learned_body_si(q)
    l_imp, G_imp, tau_imp = BodySchema.learned_body_si(schema, q)
    # commands leave the schema as float32 normalized values: ~1e-8 m each (l_std ~ 0.03 m times 2^-24 times |x_n|)
    np.testing.assert_allclose(l_imp, l_geo, rtol=0, atol=5e-8)
    # central differences over +-1 mrad of those: ~2e-8 m / 2e-3 rad = 1e-5 m/rad each side, against arms of 5 cm
    np.testing.assert_allclose(G_imp, G, rtol=0, atol=5e-5)
    np.testing.assert_allclose(tau_imp, tau, atol=1e-3 * np.abs(tau).max())  # the QP balances the learned torque


def test_schema_diagnose_names_a_cut_with_and_without_load_cells(structured):
    schema, dm = structured
    pool = _pool(schema, dm)
    cut = Faults.from_names(schema.robot_model.muscle_names, cut=[["elbow_flexor"]])
    m = schema.robot_model.muscle_names.index("elbow_flexor")
    for load_cells in (True, False):
        d = schema.diagnose(_log(schema, pool, [0, 1, 2], cut, load_cells=load_cells))
        assert d.status[0] == Status.IDENTIFIED and d.kind[0, m] == CUT and (d.kind[0] != HEALTHY).sum() == 1
    result = schema.adapt(pool[0][:1], d.faults)
    assert result.status[0] == "ok" and result.f_n[0, m] == 0.0  # the diagnosis goes to adapt as it is


def test_the_monitor_declares_a_fault_after_its_guard_and_keeps_it(structured):
    schema, dm = structured
    pool = _pool(schema, dm)
    monitor = schema.monitor(window=3, confirm=2)
    healthy = _log(schema, pool, [0] * 4, Faults.none(1, schema.n_muscles), seed=3)
    cut = _log(schema, pool, [0] * 6, Faults.from_names(schema.robot_model.muscle_names, cut=[["elbow_flexor"]]),
               seed=4)

    def tick(log, r):
        return monitor.update((log.l_cmd_m[0, r], log.f_cmd_n[0, r]), (log.q_rad[0, r], log.l_m[0, r], log.f_n[0, r]))
    assert all(tick(healthy, r).status[0] == Status.NO_FAULT for r in range(4))
    statuses = [tick(cut, r).status[0] for r in range(6)]
    # rows before and after the cut share the window for two ticks; then the cut explains it, confirmed on the next
    first = statuses.index(Status.IDENTIFIED)
    assert first == 3 and all(s == Status.NO_FAULT for s in statuses[:first])
    assert monitor.declared_names() == {"elbow_flexor": "cut"}
    assert tick(healthy, 0).status[0] == Status.IDENTIFIED  # latched until reset
    monitor.reset()
    assert tick(healthy, 1).status[0] == Status.NO_FAULT


def test_an_autoencoder_schema_diagnoses_through_the_body_its_commands_imply(latent60, dm):
    """AE and VAE have no explicit body: the one their healthy commands imply (l_motor + delta(f), central
    differences, -G^T f) serves; its lengths are the commands' own, its torques what the commands balance."""
    from lightning_bodyschema.sim.spring import elongation_from_tension

    q = dm.splits["val"][0].numpy()[:6]
    l_geo, G, tau = latent60.learned_body_si(q)
    l_motor, f = latent60.infer(q)
    # the schema is float32 and learned_body_si infers on its stencil's (2N + 1) B postures, another batch than
    # infer's, which another CPU's kernels round differently: float32 roundings of the normalized outputs, in SI
    # (~1e-7 m, ~1e-4 N here); the elongation left out is mm, a stencil row taken for q moves f by 0.1 N or more
    x_n = latent60.normalizer.encode_x(torch.as_tensor(np.c_[l_motor, f]))
    std, m = latent60.normalizer.x_std.numpy(), l_motor.shape[1]
    tol_l_m, tol_f_n = (rounding_tol(_F32_ROUNDINGS, x_n, dtype=torch.float32) * std[part].max()
                        for part in (slice(0, m), slice(m, None)))
    tol_m = tol_l_m + motor_length_tol(tol_f_n, latent60.spring, l_geo)
    np.testing.assert_allclose(l_geo, l_motor + elongation_from_tension(f, latent60.spring), rtol=0, atol=tol_m)
    # -G^T f with those tensions, summed over the muscles in any order (one float64 rounding per muscle)
    terms_nm = np.einsum("bmn,bm->bn", np.abs(G), np.abs(f))
    tol_nm = np.abs(G).sum(1).max() * tol_f_n + rounding_tol(m, terms_nm)
    np.testing.assert_allclose(tau, -np.einsum("bmn,bm->bn", G, f), rtol=0, atol=tol_nm)
    log = SensorLog.from_rows(latent60.robot_model.joint_names, latent60.robot_model.muscle_names, q, l_motor, l_motor,
                              f, f)
    d = latent60.diagnose(log)  # the readings are the commands at q_ref: nothing to find
    assert d.status[0] == Status.NO_FAULT and (d.kind == HEALTHY).all()
