"""GravityTorque: the MJCF tree's gravity torque with fitted masses and first moments, against MuJoCo (float64)."""
from __future__ import annotations

import mujoco
import numpy as np
import pytest
import torch
import yaml

from lightning_bodyschema.networks.gravity import GravityTorque
from lightning_bodyschema.networks.snapshot import GravitySnapshot
from lightning_bodyschema.sim import MusculoskeletalModel
from lightning_bodyschema.sim.gravity_tree import gravity_tree


@pytest.fixture(scope="module", params=["paper_arm", "myoarm", "myolegs"])
def robot(request):
    """The paper arm; myoArm (the hand locked, couplings kept); myoLegs on a fixed base (its knees' slide joints,
    coupled to the knee angles, translate without rotating)."""
    if request.param == "paper_arm":
        return MusculoskeletalModel("paper_arm")
    pytest.importorskip("myo_sim")
    config = {"myoarm": "configs/myoarm.yaml", "myolegs": "configs/myolegs-per-muscle.yaml"}[request.param]
    data = yaml.safe_load(open(config))["data"]
    return MusculoskeletalModel(data["model"], **{k: data[k] for k in ("locked_joints", "fixed_base") if k in data})

_CHAIN_ROUNDINGS = 8192  # roundings allowed along a kinematic chain of a few tens of frames (~1.8e-12 at 1 m)


def _postures(robot, n, seed):
    q = robot.sample_q(np.random.default_rng(seed), n)
    return torch.as_tensor(q), torch.as_tensor(robot.kinematics(q)[2])


def _relative(a, b) -> float:
    return float((a - b).abs().max() / b.abs().max())


def test_fit_on_mujoco_tau_bias_matches_held_out_postures(robot):
    gravity = GravityTorque(gravity_tree(robot))
    q, tau = _postures(robot, 300, 0)
    gravity.fit_trimmed(q, tau)
    q_new, tau_new = _postures(robot, 100, 1)
    assert _relative(gravity(q_new), tau_new) < 1e-9  # gravity is linear in the masses: exact if the FK is right
    assert _relative(gravity.features(q_new) @ gravity.coef, tau_new) < 1e-9


def test_the_numpy_torque_answers_as_the_torch_one_and_as_mujoco(robot):
    """``GravitySnapshot.on_host()`` (pointer jumping at any batch) against the torch snapshot (node by node above
    JUMP_ROWS) and the exported program's kinematics: the couplings (myoArm), the slides (myoLegs)."""
    gravity = GravityTorque(gravity_tree(robot))
    gravity.fit_trimmed(*_postures(robot, 300, 0))
    host = GravitySnapshot(gravity).on_host()
    q, tau = _postures(robot, 9, 1)
    traced = gravity.features(q) @ gravity.coef  # the regressor's path, not the snapshot's factored torque
    for rows in (1, 4, 9):
        assert _relative(torch.as_tensor(host(q[:rows].numpy())), gravity(q[:rows])) < 1e-12
        assert _relative(gravity(q[:rows]), traced[:rows]) < 1e-12
    assert _relative(torch.as_tensor(host(q.numpy())), tau) < 1e-9


@pytest.mark.parametrize("jump", [True, False], ids=["pointer-jumping", "node-by-node"])
def test_kinematics_and_features_match_mujoco(robot, jump, monkeypatch):
    """Frame poses, joint anchors and axes as mj_kinematics (both ways of composing the tree: a few postures jump
    pointers, many go node by node); each frame's columns the gradients of its potential features ``-g . p`` and
    ``-g . R[:, k]`` by MuJoCo's body Jacobians, through the couplings' tangent ``E``."""
    from lightning_bodyschema.networks import snapshot as snapshot_module

    monkeypatch.setattr(snapshot_module, "JUMP_ROWS", 64 if jump else 0)
    m, data, tree = robot.mj_model, mujoco.MjData(robot.mj_model), gravity_tree(robot)
    gravity = GravityTorque(tree)
    q = robot.sample_q(np.random.default_rng(2), 4)
    full, tangent = robot.joint_map.full_q(q), robot.joint_map.tangent(q)
    snapshot = GravitySnapshot(gravity)
    frames, o, a = snapshot.kinematics(snapshot.full(torch.as_tensor(q)))
    p, R, o, a = (t.numpy() for t in (frames[..., :3, 3], frames[..., :3, :3], o, a))
    Y = gravity.features(torch.as_tensor(q)).numpy()
    bodies = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, name) for name in tree.frame_names]
    jp, jr, g = np.zeros((3, m.nv)), np.zeros((3, m.nv)), m.opt.gravity
    for i in range(len(q)):
        data.qpos[:] = full[i]
        mujoco.mj_kinematics(m, data)
        mujoco.mj_comPos(m, data)
        # the same chain of frame products in another order: each a few roundings per joint of the chain, on
        # positions of up to ~1 m and unit rotations
        tol = _CHAIN_ROUNDINGS * np.finfo(float).eps * max(1.0, np.abs(data.xpos[bodies]).max())
        np.testing.assert_allclose(p[i], data.xpos[bodies], rtol=0, atol=tol)
        np.testing.assert_allclose(R[i], data.xmat[bodies].reshape(-1, 3, 3), rtol=0, atol=tol)
        np.testing.assert_allclose(o[i], data.xanchor[tree.moving_joint], rtol=0, atol=tol)
        np.testing.assert_allclose(a[i], data.xaxis[tree.moving_joint], rtol=0, atol=tol)
        for f, body in enumerate(bodies):
            mujoco.mj_jacBody(m, data, jp, jr, body)
            # d(-g . p)/dq = -J_p^T g and d(-g . R[:, k])/dq = -g . (w x R[:, k]) = J_r^T (g x R[:, k])
            columns = [-jp.T @ g] + [jr.T @ np.cross(g, data.xmat[body].reshape(3, 3)[:, k]) for k in range(3)]
            expected = tangent[i].T @ np.stack(columns, 1)  # g times lever arms: the chain's roundings at its scale
            tol_y = _CHAIN_ROUNDINGS * np.finfo(float).eps * max(1.0, np.abs(expected).max())
            np.testing.assert_allclose(Y[i, :, 4 * f:4 * f + 4], expected, rtol=0, atol=tol_y)
    n = robot.n_joints  # then an offset and a spring rate per free joint
    np.testing.assert_array_equal(Y[:, :, -2 * n:-n], np.broadcast_to(np.eye(n), (len(q), n, n)))
    np.testing.assert_array_equal(Y[:, :, -n:], np.einsum("bn,nk->bnk", q, np.eye(n)))


def test_trimmed_fit_recovers_the_exact_coefficients_despite_wild_samples():
    robot = MusculoskeletalModel("paper_arm")
    q, tau = _postures(robot, 300, 3)
    clean = GravityTorque(gravity_tree(robot))
    clean.fit_trimmed(q, tau, rounds=0)
    wild = tau.clone()
    wild[:6] += 50.0 * torch.randn(6, robot.n_joints, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    trimmed = GravityTorque(gravity_tree(robot))
    keep = trimmed.fit_trimmed(q, wild, factor=3.0, rounds=8)
    assert not keep[:6].any() and keep[6:].float().mean() > 0.5
    # the same exact data less six rows: the least squares' sums over the rows kept round differently, by up to one
    # rounding per row and joint of the largest coefficient (measured: 63 ulps); wild rows kept would move it by O(1)
    roundings = q.numel()
    np.testing.assert_allclose(trimmed.coef, clean.coef, rtol=0,
                               atol=roundings * np.finfo(float).eps * clean.coef.abs().max().item())
    untrimmed = GravityTorque(gravity_tree(robot))
    untrimmed.fit_trimmed(q, wild, rounds=0)
    assert _relative(untrimmed.coef, clean.coef) > 1e-3  # without the trim the wild samples pull the fit


def test_state_dict_holds_the_coefficients_only_dtype_casts_keep_float64_and_it_exports():
    robot = MusculoskeletalModel("paper_arm")
    gravity = GravityTorque(gravity_tree(robot))
    q, tau = _postures(robot, 50, 4)
    gravity.fit_trimmed(q, tau)
    assert list(gravity.state_dict()) == ["coef"]
    other = GravityTorque(gravity_tree(robot))
    other.load_state_dict(gravity.state_dict())
    other.float()
    assert all(b.dtype == torch.float64 for b in other.buffers() if b.is_floating_point())  # (and index buffers)
    torch.testing.assert_close(other(q), gravity(q), rtol=0, atol=0)
    exported = torch.export.export(gravity, (q[:7],), dynamic_shapes=({0: torch.export.Dim("batch")},))
    # the exported graph may compose the chain's frames in another order: its roundings at the torque's scale
    tol = _CHAIN_ROUNDINGS * torch.finfo(torch.float64).eps * max(1.0, gravity(q).abs().max().item())
    torch.testing.assert_close(exported.module()(q), gravity(q), rtol=0, atol=tol)
    with torch.device("meta"):  # a checkpoint's skeleton
        assert GravityTorque(gravity_tree(robot)).coef.shape == gravity.coef.shape


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_runs_on_cuda():
    robot = MusculoskeletalModel("paper_arm")
    gravity = GravityTorque(gravity_tree(robot))
    q, tau = _postures(robot, 100, 5)
    gravity.fit_trimmed(q, tau)
    on_gpu = gravity.to("cuda")
    torch.testing.assert_close(on_gpu(q.cuda()).cpu(), tau, rtol=0, atol=1e-9)


def test_the_torque_exports_with_a_dynamic_batch_and_answers_as_eager_down_to_one_posture():
    """Exported with a dynamic batch (how ``deploy.structured`` exports a body the snapshot does not cover: every
    posture at once): the snapshot built in the trace keeps the batch symbolic, and the program answers as the eager
    snapshot within the chain's roundings at the torque's scale, at the traced batch and at one posture."""
    robot = MusculoskeletalModel("paper_arm")
    gravity = GravityTorque(gravity_tree(robot))
    gravity.fit_trimmed(*_postures(robot, 300, 0))
    q, _ = _postures(robot, 7, 4)
    batch = torch.export.Dim("batch", min=1, max=1024)
    program = torch.export.export(gravity, (q,), dynamic_shapes={"q": {0: batch}}).module()
    for rows in (1, 7):
        want = gravity(q[:rows])
        tol = _CHAIN_ROUNDINGS * np.finfo(float).eps * want.abs().max().item()
        torch.testing.assert_close(program(q[:rows]), want, rtol=0, atol=tol)
