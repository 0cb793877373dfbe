"""Checks and fixtures-in-code shared by several test files (imported as ``from physics_checks import ...``)."""
import glob
import warnings

import mujoco
import numpy as np
import pytest


def assert_G_matches_finite_differences(model, q, h=1e-6, atol=1e-6):
    """G = d l_geo / d q at postures q (B, N) against central differences of MuJoCo's tendon lengths."""
    _, G, _ = model.kinematics(q)
    for j in range(model.n_joints):
        step = np.zeros(model.n_joints)
        step[j] = h
        l_plus, _, _ = model.kinematics(q + step)
        l_minus, _, _ = model.kinematics(q - step)
        np.testing.assert_allclose(G[:, :, j], (l_plus - l_minus) / (2 * h), atol=atol)


def assert_drawn_muscles_match_mujoco(model, qs, rel=1e-3):
    """The drawn muscle paths (plots.arm) are as long as MuJoCo's tendons: arcs wrap the way MuJoCo wraps."""
    from lightning_bodyschema.plots.arm import muscle_polylines

    m, d = model.mj_model, mujoco.MjData(model.mj_model)
    for q in qs:
        d.qpos[:] = q
        mujoco.mj_forward(m, d)
        for tendon in model.muscle_ids:
            drawn_m = sum(np.linalg.norm(np.diff(p, axis=0), axis=1).sum() for p in muscle_polylines(m, d, tendon))
            assert drawn_m == pytest.approx(d.ten_length[tendon], rel=rel)


def fit_tiny_checkpoint(root, *args, epochs=3) -> str:
    """Train a few epochs through the real CLI into ``root``; return the newest checkpoint path."""
    from lightning_bodyschema.cli import main as cli_main

    with warnings.catch_warnings():  # "args and sys.argv both given": pytest's argv, expected here
        warnings.filterwarnings("ignore", message=".*LightningCLI's args parameter.*")
        cli_main(["fit", "--model=DiffusionSchema", f"--trainer.max_epochs={epochs}",
                  f"--trainer.check_val_every_n_epoch={epochs}", f"--trainer.default_root_dir={root}",
                  f"--data.cache_dir={root}/cache", *args])
    ckpts = sorted(glob.glob(f"{root}/lightning_logs/version_*/checkpoints/*.ckpt"))  # epoch=... then last.ckpt
    assert ckpts, "fit wrote no checkpoint"
    return ckpts[-1]
