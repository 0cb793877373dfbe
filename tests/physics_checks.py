"""Checks and fixtures-in-code shared by several test files (imported as ``from physics_checks import ...``)."""
import glob
import warnings

import mujoco
import numpy as np
import pytest
import torch

from lightning_bodyschema.evaluation import make_fault_cases
from lightning_bodyschema.faults import Faults


def rounding_tol(roundings: int, *scales, dtype=torch.float64) -> float:
    """An absolute tolerance of ``roundings`` roundings of ``dtype`` at the largest magnitude in ``scales`` (arrays,
    tensors or numbers: the computation's own scale, 1.0 where its intermediates are of order 1): what another CPU's
    kernels may round differently, never one CPU's last bits."""
    scale = max(float(np.abs(np.asarray(torch.as_tensor(s).detach().double().cpu())).max()) for s in scales)
    return roundings * torch.finfo(dtype).eps * scale


SPRING_ROUNDINGS = 8  # l_geo - delta(f): f / k, a log1p (an ulp or two), a division by alpha, a subtraction


def frozen_pass(frozen, x_free, bias, v=None):
    """A ``FrozenMLP``'s output ``(B, out)`` at free input ``x_free`` and a ``first_bias`` by the blocks the samplers
    run (``trunk``, the output layer, ``back``), and with ``v (B, out)`` also ``v^T d out / d x_free`` (B, n_free)."""
    bufs = frozen.buffers(len(x_free), x_free)
    h, saved = frozen.trunk(x_free, bias, frozen.w1_free_t, bufs, frozen.eager)
    out = torch.addmm(frozen.out_b, h, frozen.out_w_t)
    if v is None:
        return out
    return out, frozen.back(v, frozen.out_w, saved, bufs, frozen.eager) @ frozen.w1_free


def spring_length_tol(*lengths_m) -> float:
    """The same motor length ``l_geo - delta(f)`` [m] written two ways (numpy's or torch's log1p, another order):
    a few roundings at the lengths' scale (~1e-15 m at lengths below 1 m); a spring off by 1% (k or alpha) moves
    it by ~7e-5 m at f_max, a tension off by 1 N by ~5e-5 m."""
    return rounding_tol(SPRING_ROUNDINGS, *lengths_m)


def motor_length_tol(f_tol_n: float, spring, *lengths_m) -> float:
    """Motor lengths ``l_geo - delta(f)`` [m] from tensions that agree within ``f_tol_n`` [N]: the spring's largest
    compliance ``d delta / d f = 1 / (alpha (k + f)) <= 1 / (alpha k)`` times that, plus ``spring_length_tol``."""
    compliance_m_per_n = 1.0 / float(np.min(np.asarray(spring.alpha_per_m) * np.asarray(spring.k_n)))
    return f_tol_n * compliance_m_per_n + spring_length_tol(*lengths_m)


def term_sum_tol(path, *scales) -> float:
    """Two evaluations of a path's same polynomials that may sum its terms in another order (rows in blocks, a cell
    at a time, numpy's or an exported graph's products): one rounding per term at the scale of the lengths or arms
    (~5e-14 for 84 terms at lengths of 3); another branch or cell, or no extension beyond the box, is off by O(0.1)."""
    return rounding_tol(path.coef.shape[1], *scales)


def assert_G_matches_finite_differences(model, q, h=1e-6, atol=1e-6):
    """G = d l_geo / d q at postures q (B, N) against central differences of MuJoCo's tendon lengths."""
    _, G, _ = model.kinematics(q)
    for j in range(model.n_joints):
        step = np.zeros(model.n_joints)
        step[j] = h
        l_plus, _, _ = model.kinematics(q + step)
        l_minus, _, _ = model.kinematics(q - step)
        np.testing.assert_allclose(G[:, :, j], (l_plus - l_minus) / (2 * h), atol=atol)


def central_differences(fn, x, h=1e-6):
    """``d fn / d x`` of a torch function ``fn: (B, N) -> (B, M)`` by central differences: ``(B, M, N)``."""
    columns = []
    for j in range(x.shape[1]):
        step = x.new_zeros(x.shape[1])
        step[j] = h
        columns.append((fn(x + step) - fn(x - step)) / (2 * h))
    return np.stack([c.detach().numpy() for c in columns], -1)


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


def train_schema(cls, epochs, dm=None, **kwargs):
    """A schema of the paper arm trained briefly (seed 0) with a bare Trainer, in eval mode: (schema, trainer, dm)."""
    import lightning as L

    from lightning_bodyschema.data import EquilibriumDataModule

    L.seed_everything(0)
    dm = dm or EquilibriumDataModule(cache_dir=None)
    schema = cls(robot=dm.robot, **kwargs)
    trainer = L.Trainer(max_epochs=epochs, logger=False, enable_checkpointing=False, enable_progress_bar=False,
                        enable_model_summary=False, check_val_every_n_epoch=10 ** 6, num_sanity_val_steps=0)
    trainer.fit(schema, dm)
    return schema.eval(), trainer, dm


def torque_residual(model, q, f):
    """|-G(q)^T f - tau_bias(q)| per posture (B,) [N m]: how far tensions f are from holding q."""
    _, G, tau = model.kinematics(q)
    return np.linalg.norm(np.einsum("bmn,bm->bn", -G, f) - tau, axis=1)


def mixed_faults(schema, dm, n=12, seed=0):
    """Cut, jammed, weakened and length-banded muscles, mixed; one band overlaps a jam (a two-slot penalty)."""
    q, x = dm.splits["val"]
    m = schema.n_muscles
    cases = make_fault_cases(q.numpy(), x[:, :m].numpy(), n // 3, seed)
    faults = cases.faults
    f_max = np.full(faults.cut.shape, np.nan)
    f_max[::4, 3] = 60.0  # a weakened muscle in every fourth case
    band = np.full(faults.cut.shape + (2,), np.nan)
    l_plain = schema.infer(cases.q_ref)[0]
    for i in range(0, len(cases), 3):  # one banded motor per third case, on a jammed motor where there is one
        j = int(np.flatnonzero(faults.fix[i])[0]) if faults.fix[i].any() else int(np.flatnonzero(~faults.cut[i])[0])
        band[i, j] = [l_plain[i, j] - 0.004, l_plain[i, j] - 0.001]
    return cases.q_ref, Faults(faults.cut, faults.fix, faults.l_fixed_m, np.where(faults.cut, np.nan, f_max), band)


def assert_same_commands(fast, ref, tol_n, tol_m):
    assert (fast.status == ref.status).all()
    ok = ref.status == "ok"
    assert ok.any()
    np.testing.assert_allclose(fast.f_n[ok], ref.f_n[ok], rtol=0, atol=tol_n)
    np.testing.assert_allclose(fast.l_motor_m[ok], ref.l_motor_m[ok], rtol=0, atol=tol_m)


def fit_structured(datamodule, epochs=1, **hparams):
    """A ``StructuredSchema`` fitted on ``datamodule`` for ``epochs`` (seed 0, batch 64, no logger, no checkpoints, no
    validation): ``(schema in eval mode, trainer)``."""
    import lightning as L

    from lightning_bodyschema.schemas import StructuredSchema

    L.seed_everything(0, verbose=False)
    schema = StructuredSchema(robot=datamodule.robot, batch_size=64, **hparams)
    trainer = L.Trainer(max_epochs=epochs, logger=False, enable_checkpointing=False, enable_progress_bar=False,
                        enable_model_summary=False, check_val_every_n_epoch=10 ** 6, num_sanity_val_steps=0)
    trainer.fit(schema, datamodule)
    return schema.eval(), trainer


def _rows(path):
    """The path's lengths and moment arms at every posture at once, as ``deploy.structured`` exports a schema's body."""
    class Rows(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.path = path

        def forward(self, x):
            return self.path.with_jacobian(x)
    return Rows()


def assert_exports_with_a_dynamic_batch(path, n_joints=3):
    """``torch.export`` of ``_rows(path)`` with a dynamic batch answers as the eager module at two batch sizes (a
    data-dependent branch, a size taken from the batch or a buffer read as a Python number would break it)."""
    from torch.export import Dim, export

    x = torch.rand(9, n_joints, dtype=torch.float64, generator=torch.Generator().manual_seed(11)) * 1.8 - 0.9
    with torch.no_grad():
        program = export(_rows(path), (x[:2],), dynamic_shapes=({0: Dim("batch", min=1, max=4096)},), strict=False)
        for rows in (x[:1], x):
            for exported, eager in zip(program.module()(rows), _rows(path)(rows)):
                torch.testing.assert_close(exported, eager, atol=term_sum_tol(path, eager), rtol=0)

