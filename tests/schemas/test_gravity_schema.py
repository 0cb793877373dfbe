"""StructuredSchema(torque_model="gravity"): the MJCF tree's gravity torque fitted on the learned moment arms, its
checkpoint, and the one-line refusal without an MJCF."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from physics_checks import fit_structured as _fit

from lightning_bodyschema.data import EquilibriumDataModule
from lightning_bodyschema.errors import BodySchemaInputError
from lightning_bodyschema.schemas import StructuredSchema, load_schema
from lightning_bodyschema.sim.robot import ModelFreeRobot

GRAVITY = dict(length_model="per_muscle", path_degree=10, torque_model="gravity")


@pytest.fixture(scope="module")
def paper_arm():
    return _fit(EquilibriumDataModule(n_samples=1000, seed=0, cache_dir=None), **GRAVITY)


def test_the_fitted_gravity_torque_matches_mujoco(paper_arm):
    schema, _ = paper_arm
    assert not any(True for _ in schema.parameters())  # lengths and torque by least squares: nothing to train
    q = schema.robot_model.sample_q(np.random.default_rng(5), 300)
    tau_true = schema.robot_model.kinematics(q)[2]
    tau = schema.body_si(torch.as_tensor(q))[2]
    # on -G_hat^T f of moment arms learned to micrometres, the tree's torque is as close (measured 6e-8 relative)
    assert np.median(np.linalg.norm(tau - tau_true, axis=1)) < 1e-4 * np.median(np.linalg.norm(tau_true, axis=1))


def test_checkpoint_round_trip_answers_the_same(paper_arm, tmp_path):
    schema, trainer = paper_arm
    path = str(tmp_path / "gravity.ckpt")
    trainer.save_checkpoint(path, weights_only=False)
    loaded = load_schema(path)
    assert loaded.hparams.torque_model == "gravity"
    q = torch.as_tensor(schema.robot_model.sample_q(np.random.default_rng(6), 20))
    for a, b in zip(schema.body_si(q), loaded.body_si(q)):
        np.testing.assert_array_equal(a, b)


def test_gravity_needs_the_mjcf_and_the_per_muscle_lengths(paper_arm):
    robot = dict(ModelFreeRobot(["shoulder", "elbow"], [[-1, 1], [0, 2]], ["a", "b"]).as_dict(),
                 spring=paper_arm[0].hparams.robot["spring"])  # what recorded data gives: names, limits, a spring
    with pytest.raises(BodySchemaInputError) as err:
        StructuredSchema(robot=robot, **GRAVITY)
    message = str(err.value)
    assert "\n" not in message and "'gravity'" in message
    assert all(f"'{alt}'" in message for alt in ("polynomial", "direct", "potential"))
    with pytest.raises(BodySchemaInputError, match="needs length_model='per_muscle'"):
        StructuredSchema(robot=paper_arm[0].hparams.robot, torque_model="gravity")


def test_the_body_snapshot_answers_the_same_in_numpy_and_in_torch_and_as_body(paper_arm, monkeypatch):
    """``StructuredSchema.body_snapshot()``: one code on torch tensors and (``on_host()``) on numpy arrays, within a
    few roundings of the schema's dtype of each other and of ``body`` (the per-muscle path's blocks of rows, the
    gravity torque), inside the sampled range and beyond it."""
    from lightning_bodyschema.networks import snapshot as snapshot_module

    schema, _ = paper_arm
    q = torch.as_tensor(schema.robot_model.sample_q(np.random.default_rng(3), 16))
    q[:4] += 0.2  # beyond the sampled range: the first-order extension
    snapshot = schema.body_snapshot()
    eps = torch.finfo(schema.dtype).eps
    with torch.no_grad():
        on_torch = snapshot(q)
        monkeypatch.setattr(snapshot_module, "FEW_ELEMENTS", 0)  # body's path by blocks of rows, not the snapshot
        schema.clear_caches()
        expected = schema.body(schema.normalizer.encode_q(q).to(schema.dtype))
    monkeypatch.undo()
    schema.clear_caches()  # the snapshots keep the budget they were built with
    for rows in (1, 16):
        for got, same, want in zip(snapshot.on_host()(q[:rows].numpy()), on_torch, expected):
            scale = float(want.abs().max())
            np.testing.assert_allclose(got, same[:rows].numpy(), rtol=0, atol=4 * eps * scale)
            np.testing.assert_allclose(got, want[:rows].double().numpy(), rtol=0, atol=64 * eps * scale)


def test_body_si_at_a_few_postures_on_the_cpu_is_the_host_evaluation_and_answers_as_body(paper_arm, monkeypatch):
    """Up to HOST_ROWS postures (in eval mode) ``body_si`` takes its numpy ``BodySnapshot``: each step and cast of
    ``StructuredSchema.body``; more postures, or training, the torch evaluation."""
    from lightning_bodyschema.networks.snapshot import BodySnapshot
    from lightning_bodyschema.schemas import structured_body

    schema, _ = paper_arm
    calls = []
    original = BodySnapshot.__call__
    monkeypatch.setattr(BodySnapshot, "__call__", lambda self, q: calls.append((len(q), self.xp)) or original(self, q))
    q = torch.as_tensor(schema.robot_model.sample_q(np.random.default_rng(9), 17))
    q[0] += 0.2  # beyond the sampled range: the first-order extension
    for rows in (1, 16, 17):
        l_geo, G, tau = schema.body_si(q[:rows])
        with torch.no_grad():
            expected = [t.double().numpy() for t in schema.body(schema.normalizer.encode_q(q[:rows]).to(schema.dtype))]
        for got, want in zip((l_geo, G, tau), expected):
            np.testing.assert_allclose(got, want, rtol=0, atol=1e-6 * np.abs(want).max())
    assert calls == [(1, np), (16, np)] and structured_body.HOST_ROWS == 16
    schema.train()
    try:
        schema.body_si(q[:1])
    finally:
        schema.eval()
    assert calls == [(1, np), (16, np)]
