"""Every path on CUDA (marker ``gpu``; skipped without a CUDA device): ``python -m pytest -m gpu -q``.

A few epochs of each schema kind through the real CLI with ``--trainer.accelerator gpu`` under each precision that
makes sense (fit with end-of-fit validation and the fault benchmark, then validate and test from the checkpoint),
and the adapters on CUDA against the same checkpoint's CPU answers.

Tolerance of CUDA against CPU (float32 weights on both; the kernels sum in other orders): motor lengths within
``L_ATOL_M``, tensions within ``F_ATOL_N``, and the same status on all but ``STATUS_MISMATCH`` of the rows (a case
on the edge of the motors' range may flip).
"""
from __future__ import annotations

import glob
import os

import numpy as np
import pytest
import torch

pytestmark = [pytest.mark.gpu, pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")]

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
# Rounding differs by a few 1e-7 relative per operation. Every weight perturbed by a relative 1e-6 (ten times that)
# moved the CPU answers of briefly trained paper-arm schemas by at most 3e-7 m and 1e-3 N (20- and 200-step diffusion
# adapters, AE, structured QP; statuses unchanged): these bounds are ten and more times that.
L_ATOL_M, F_ATOL_N, STATUS_MISMATCH = 1e-5, 1e-2, 0.01
CONFIGS = {"diff": "diff.yaml", "ae": "ae-10.yaml", "vae": "vae-10.yaml", "structured": "structured.yaml"}
# precision -> kinds it is run with; StructuredSchema refuses 16-bit matmuls (test_structured_refuses_mixed_precision)
PRECISIONS = {"32-true": list(CONFIGS), "bf16-mixed": ["diff", "ae", "vae"], "16-mixed": ["diff", "ae", "vae"]}
SHORT = ["--data.n_samples=400", "--trainer.max_epochs=4", "--trainer.check_val_every_n_epoch=2",
         "--faults.every_n_epochs=4", "--faults.n_per_condition=4", "--faults.binding_n_per_condition=3",
         "--trainer.accelerator=gpu", "--trainer.devices=1"]


def _cli(*args):
    from lightning_bodyschema.cli import main as cli_main

    return cli_main([str(a) for a in args])


def _fit(tmp, kind, precision, *extra):
    config = os.path.join(ROOT, "configs", CONFIGS[kind])
    common = ["--config", config, *SHORT, f"--trainer.precision={precision}", f"--trainer.default_root_dir={tmp}",
              f"--data.cache_dir={tmp}/cache", *extra]
    cli = _cli("fit", *common)
    ckpts = sorted(glob.glob(f"{tmp}/lightning_logs/version_*/checkpoints/*.ckpt"))
    assert ckpts, "fit wrote no checkpoint"
    return cli, common, ckpts[-1]


def _ran_on_cuda(cli) -> bool:
    """Lightning trains on the strategy's root device and hands the module back on the CPU when a fit ends."""
    return cli.trainer.strategy.root_device.type == "cuda"


def _logged_tags(logdir) -> set:
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    events = EventAccumulator(logdir, size_guidance={"scalars": 0})
    events.Reload()
    return set(events.Tags()["scalars"])


@pytest.mark.parametrize("kind,precision", [(k, p) for p, kinds in PRECISIONS.items() for k in kinds])
def test_fit_validate_and_test_on_cuda(tmp_path, kind, precision):
    cli, common, ckpt = _fit(tmp_path / "run", kind, precision)
    assert _ran_on_cuda(cli)
    metrics = cli.trainer.callback_metrics
    assert np.isfinite(float(metrics["val/eq_residual_N_m"])), metrics
    # the fault benchmark ran at the end of the fit, on the CUDA schema
    assert "fault/adapt_ok_fraction" in _logged_tags(cli.trainer.logger.log_dir)
    for command, stage in (("validate", "val"), ("test", "test")):
        run = _cli(command, *common, f"--ckpt_path={ckpt}")
        assert _ran_on_cuda(run)
        assert np.isfinite(float(run.trainer.callback_metrics[f"{stage}/eq_residual_N_m"]))


def test_structured_refuses_mixed_precision(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_:
        _fit(tmp_path / "run", "structured", "bf16-mixed")
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    refusals = [line for line in err.splitlines() if "bf16-mixed" in line]
    assert "Traceback" not in err and len(refusals) == 1 and "32-true" in refusals[0], err


@pytest.fixture(scope="module", params=["diff", "structured"])
def trained(request, tmp_path_factory):
    """(kind, checkpoint) of a 4-epoch CUDA fit."""
    tmp = tmp_path_factory.mktemp(request.param)
    return request.param, _fit(tmp, request.param, "32-true")[2]


def _cases(ckpt, n_muscles, n):
    """n fault cases (the paper's protocol on the checkpoint's test split, repeated up to n): (q_ref, faults)."""
    from lightning_bodyschema.evaluation import make_fault_cases
    from lightning_bodyschema.schemas import load_datamodule

    q, x = (t.numpy() for t in load_datamodule(ckpt).splits["val"])
    cases = make_fault_cases(q, x[:, :n_muscles], 4, 0)
    take = np.resize(np.arange(len(cases.q_ref)), n)
    return cases.q_ref[take], cases.faults.take(take)


def _agree(cuda, cpu):
    assert isinstance(cuda.l_motor_m, np.ndarray) and isinstance(cuda.f_n, np.ndarray)
    assert (cuda.status != cpu.status).mean() <= STATUS_MISMATCH, (cuda.status, cpu.status)
    both = (cuda.status == "ok") & (cpu.status == "ok")
    np.testing.assert_allclose(cuda.l_motor_m[both], cpu.l_motor_m[both], rtol=0, atol=L_ATOL_M)
    np.testing.assert_allclose(cuda.f_n[both], cpu.f_n[both], rtol=0, atol=F_ATOL_N)
    # a briefly trained schema may hold no case: then the tensions each case would have had must agree
    shared = [k for k in ("clipped_f_n", "best_effort_f_n") if k in cuda.diagnostics and k in cpu.diagnostics]
    assert both.any() or shared, (cuda.status, sorted(cuda.diagnostics))
    for key in shared:
        np.testing.assert_allclose(cuda.diagnostics[key], cpu.diagnostics[key], rtol=0, atol=F_ATOL_N)


@pytest.mark.parametrize("batch", [1, 4000])
def test_adaptation_on_cuda_matches_the_cpu(trained, batch):
    from lightning_bodyschema.schemas import load_schema

    kind, ckpt = trained
    cpu, cuda = load_schema(ckpt), load_schema(ckpt, map_location="cuda")
    assert next(cuda.parameters()).device.type == "cuda"
    q, faults = _cases(ckpt, cpu.n_muscles, batch)
    options = {"n_steps": 20} if kind == "diff" else {}
    _agree(cuda.adapter(faults, check_physics=False, **options)(q),
           cpu.adapter(faults, check_physics=False, **options)(q))
    _agree(cuda.adapt(torch.as_tensor(q, device="cuda"), faults, **options), cpu.adapt(q, faults, **options))
    np.testing.assert_allclose(cuda.infer(q)[0], cpu.infer(q)[0], rtol=0, atol=L_ATOL_M)
    if batch == 1:
        target = cpu.robot_model.site_position(q, "hand")
        _agree(cuda.adapt_to_target(target, faults, **options), cpu.adapt_to_target(target, faults, **options))


def test_a_schema_moved_with_to_cuda_adapts(trained):
    from lightning_bodyschema.schemas import load_schema

    kind, ckpt = trained
    schema = load_schema(ckpt).to("cuda")
    q, faults = _cases(ckpt, schema.n_muscles, 4)
    result = schema.adapt(q, faults, check_physics=False, **({"n_steps": 20} if kind == "diff" else {}))
    assert result.l_motor_m.shape == (4, schema.n_muscles) and isinstance(result.l_motor_m, np.ndarray)
    assert np.isfinite(result.l_motor_m[result.ok]).all() and np.isnan(result.l_motor_m[~result.ok]).all()


# the per-muscle body's least squares (in the setup hook, before Lightning moves the module) at a small size
PER_MUSCLE_SMALL = ["--model.path_degree=6", "--model.path_terms=200", "--model.path_term_budget=null"]


@pytest.mark.parametrize("config,extra", [("myoarm-polynomial.yaml", PER_MUSCLE_SMALL),
                                          ("myoarm-dense.yaml", []), ("myoarm-diff.yaml", [])])
def test_myo_configs_fit_on_cuda(tmp_path, config, extra):
    pytest.importorskip("myo_sim")
    from lightning_bodyschema.cli import main as cli_main

    cli = cli_main(["fit", "--config", os.path.join(ROOT, "configs", config), "--data.n_samples=2000",
                    "--trainer.max_epochs=2", "--trainer.check_val_every_n_epoch=2", "--trainer.accelerator=gpu",
                    "--trainer.devices=1", "--faults.every_n_epochs=0", f"--trainer.default_root_dir={tmp_path}",
                    f"--data.cache_dir={tmp_path}/cache", *extra])
    assert _ran_on_cuda(cli)
    assert np.isfinite(float(cli.trainer.callback_metrics["val/eq_residual_N_m"]))
