"""Every numpy boundary takes a tensor on any device: without a GPU, two checks that fail on a ``.numpy()`` of a
device tensor (``TypeError: can't convert cuda:0 device type tensor to numpy``).

1. In the source: every ``.numpy()`` call in the package follows ``.cpu()`` or is ``_numpy.to_numpy``'s own.
2. At run time: a schema whose weights and buffers are a ``HostOnly`` tensor (a CPU tensor that, like a CUDA
   tensor, refuses ``.numpy()`` and ``np.asarray`` until ``.cpu()`` is called) runs ``infer``, ``adapt``,
   ``adapter``, ``adapt_to_target``, validation's ``physical_errors``, the fault benchmark and a fit with end-of-fit
   validation, and answers exactly what the plain schema answers.
"""
from __future__ import annotations

import ast
import copy
import os
import types

import lightning as L
import numpy as np
import pytest
import torch

from lightning_bodyschema.callbacks.fault_benchmark import FaultBenchmark
from lightning_bodyschema.faults import Faults
from lightning_bodyschema.schemas import AutoEncoderSchema, DiffusionSchema, StructuredSchema, VAESchema

PACKAGE = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))),
                       "lightning_bodyschema")
# files allowed a bare .numpy(), with the reason
ALLOWED = {"_numpy.py": "the helper itself"}


def _bare_numpy_calls(source: str) -> list[int]:
    """Line numbers of ``X.numpy()`` where X is not a ``.cpu()`` call."""
    lines = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "numpy":
            receiver = node.func.value
            after_cpu = (isinstance(receiver, ast.Call) and isinstance(receiver.func, ast.Attribute)
                         and receiver.func.attr == "cpu")
            if not after_cpu:
                lines.append(node.lineno)
    return lines


def test_every_numpy_call_in_the_package_follows_cpu():
    hits, scanned = [], 0
    for root, _, files in os.walk(PACKAGE):
        for name in files:
            path = os.path.join(root, name)
            rel = os.path.relpath(path, PACKAGE)
            if not name.endswith(".py") or rel in ALLOWED:
                continue
            with open(path) as f:
                hits += [f"{rel}:{line}" for line in _bare_numpy_calls(f.read())]
            scanned += 1
    assert scanned > 50, scanned  # the package was found and walked
    assert not hits, "a .numpy() that fails on a CUDA tensor (use _numpy.to_numpy):\n" + "\n".join(hits)


def test_the_source_check_sees_a_bare_numpy_call():
    assert _bare_numpy_calls("a = x.numpy()\nb = x.detach().numpy()\nc = x.cpu().numpy()\n") == [1, 2]


# ---------------------------------------------------------------------------- a tensor that behaves like a device one
class HostOnly(torch.Tensor):
    """A CPU tensor that refuses numpy like a CUDA tensor does; ``.cpu()`` and ``.to("cpu")`` give a plain tensor."""

    @classmethod
    def __torch_function__(cls, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        name = getattr(func, "__name__", "")
        if name in ("numpy", "__array__"):
            raise TypeError("can't convert HostOnly device type tensor to numpy. Use Tensor.cpu() first")
        if name == "cpu" or (name == "to" and "cpu" in (*args[1:], kwargs.get("device"))):
            with torch._C.DisableTorchFunctionSubclass():
                return func(*args, **kwargs).as_subclass(torch.Tensor)
        return super().__torch_function__(func, types, args, kwargs)


def on_host_only(module):
    """``module`` with every parameter and buffer a ``HostOnly`` tensor (in place)."""
    torch.__future__.set_overwrite_module_params_on_conversion(True)
    try:
        module._apply(lambda t: t.as_subclass(HostOnly))
    finally:
        torch.__future__.set_overwrite_module_params_on_conversion(False)
    return module


def test_host_only_refuses_numpy_like_a_device_tensor():
    t = torch.ones(3).as_subclass(HostOnly)
    for convert in (lambda: t.numpy(), lambda: np.asarray(t), lambda: (2 * t).detach().numpy()):
        with pytest.raises(TypeError, match="Tensor.cpu"):
            convert()
    assert type(t + 1) is HostOnly and t.cpu().numpy().tolist() == [1.0, 1.0, 1.0]
    module = on_host_only(torch.nn.Linear(2, 2))
    assert type(module.weight) is HostOnly and isinstance(module.weight, torch.nn.Parameter)


KINDS = {"diff": (DiffusionSchema, {}, {"n_steps": 20}), "ae": (AutoEncoderSchema, {}, {}),
         "vae": (VAESchema, {}, {}), "structured": (StructuredSchema, {"hidden": 32, "batch_size": 64}, {})}


def _fitted(dm, kind, epochs=1):
    cls, hparams, _ = KINDS[kind]
    L.seed_everything(0, verbose=False)
    schema = cls(robot=dm.robot, **hparams)
    trainer = L.Trainer(max_epochs=epochs, logger=False, enable_checkpointing=False, enable_progress_bar=False,
                        enable_model_summary=False, num_sanity_val_steps=0, limit_train_batches=2)
    trainer.fit(schema, dm)  # ends with a validation (FinalValidation is the CLI's; the default interval is 1)
    return schema.eval()


@pytest.fixture(scope="module", params=list(KINDS))
def pair(request, dm):
    """(kind, plain schema, the same schema on HostOnly tensors)."""
    schema = _fitted(dm, request.param)
    return request.param, schema, on_host_only(copy.deepcopy(schema))


# the same maths; a tensor subclass may take another kernel for a float32 op (one rounding of 6e-8 apart), which
# the structured schema's QP turns into ~1e-5 N of tension
RTOL, F_ATOL_N = 1e-6, 1e-3


def _same(a, b):
    np.testing.assert_array_equal(a.status, b.status)
    np.testing.assert_allclose(a.l_motor_m, b.l_motor_m, rtol=RTOL)
    np.testing.assert_allclose(a.f_n, b.f_n, rtol=RTOL, atol=F_ATOL_N)


def test_infer_and_adaptation_take_device_tensors(pair, dm):
    kind, plain, host_only = pair
    options = KINDS[kind][2]
    q = dm.splits["val"][0][:4].numpy()
    faults = Faults.from_names(plain.robot_model.muscle_names, cut=[[plain.robot_model.muscle_names[0]]] * 4)
    for q_in in (q, torch.as_tensor(q).as_subclass(HostOnly)):  # numpy or device tensors in, numpy out
        l_motor, f = host_only.infer(q_in)
        assert isinstance(l_motor, np.ndarray)
        np.testing.assert_allclose(l_motor, plain.infer(q)[0], rtol=RTOL)
        _same(host_only.adapt(q_in, faults, **options), plain.adapt(q, faults, **options))
    _same(host_only.adapter(faults, check_physics=False, **options)(q),
          plain.adapter(faults, check_physics=False, **options)(q))
    target = plain.robot_model.site_position(q, "hand")
    _same(host_only.adapt_to_target(torch.as_tensor(target).as_subclass(HostOnly), faults, **options),
          plain.adapt_to_target(target, faults, **options))
    q_t, x_t = (t[:8].as_subclass(HostOnly) for t in dm.splits["val"])
    assert host_only.physical_errors(q_t, x_t) == pytest.approx(plain.physical_errors(q_t.cpu(), x_t.cpu()), rel=1e-4)


def test_the_fault_benchmark_takes_device_tensors(pair, dm):
    kind, plain, host_only = pair
    if not plain.supports_adaptation:
        pytest.skip(f"{kind} does not adapt")
    trainer = types.SimpleNamespace(datamodule=dm)
    bench = FaultBenchmark(n_per_condition=2, settle_check=False, protocols=("paper",))
    ours, theirs = (bench.run(trainer, s, oracle=False) for s in (host_only, plain))
    np.testing.assert_array_equal(ours.adapt_status, theirs.adapt_status)
    for reading in ("paper", "phys"):
        np.testing.assert_allclose(ours.metrics["adapted"][reading]["E_tau"],
                                   theirs.metrics["adapted"][reading]["E_tau"], rtol=RTOL)


def test_a_fit_on_device_tensors_validates_and_benchmarks_at_its_end(dm, tmp_path):
    from lightning.pytorch.loggers import CSVLogger

    L.seed_everything(0, verbose=False)
    schema = on_host_only(DiffusionSchema(robot=dm.robot))
    trainer = L.Trainer(max_epochs=1, logger=CSVLogger(tmp_path), enable_checkpointing=False, enable_progress_bar=False,
                        enable_model_summary=False, num_sanity_val_steps=0, limit_train_batches=2,
                        callbacks=[FaultBenchmark(every_n_epochs=1, n_per_condition=2, settle_check=False,
                                                  protocols=("paper",))])
    trainer.fit(schema, dm)
    assert type(next(schema.parameters())) is HostOnly  # the fit ran on HostOnly weights throughout
    assert np.isfinite(float(trainer.callback_metrics["val/eq_residual_N_m"]))
    with open(os.path.join(trainer.logger.log_dir, "metrics.csv")) as f:
        assert "fault/adapt_ok_fraction" in f.readline()  # the benchmark ran and logged
