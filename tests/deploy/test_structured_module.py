"""The structured schema's tensor-only package module (eager, and traced by torch.export): the statuses and commands
of the Python adapter, the faults' bounds met, bad input refused row by row."""
import numpy as np
import pytest
import torch
from physics_checks import motor_length_tol, rounding_tol
from test_module import module_inputs

from lightning_bodyschema.adaptation.command import FAULT_TOL_M
from lightning_bodyschema.deploy.structured import StructuredAdapterModule
from lightning_bodyschema.faults.bounds import FaultBounds
from lightning_bodyschema.status import Status, status_array
from lightning_bodyschema.errors import BodySchemaInputError


def _run(module, q, faults, seed=0):
    with torch.no_grad():
        l_motor, f, status = module(*module_inputs(q, faults, seed))
    return l_motor.numpy(), f.numpy(), status_array(status.numpy().tolist())


FIXTURES = {"mlp": ("struct30", "struct_cases"), "per_muscle": ("struct_paths", "paths_cases"),
            "polynomial_torque": ("struct_poly", "poly_cases")}


@pytest.mark.parametrize("which", list(FIXTURES))
def test_structured_module_equals_the_python_adapter(which, request):
    """The dense body (schema.body), the per-muscle body (its frozen BodySnapshot) and a per-muscle body with a
    polynomial torque (schema.body) alike."""
    schema, (q, faults) = (request.getfixturevalue(name) for name in FIXTURES[which])
    ref = schema.adapter(faults, check_physics=False)(q)
    module = StructuredAdapterModule(schema)
    assert (module.snapshot is not None) == (which == "per_muscle")
    l_motor, f, status = _run(module, q, faults)
    assert (status == ref.status).all()
    ok = status == Status.OK
    assert 5 <= ok.sum() < len(q) and (status[~ok] == Status.INFEASIBLE_LEARNED).any()
    np.testing.assert_allclose(l_motor[ok], ref.l_motor_m[ok], rtol=0, atol=1e-5)
    np.testing.assert_allclose(f[ok], ref.f_n[ok], rtol=0, atol=1e-2)
    assert np.isnan(l_motor[~ok]).all() and np.isnan(f[~ok]).all()
    # every ok command meets every fault: cut f = 0, jams and bands to FAULT_TOL_M, f within [0, f_limit]
    bounds = FaultBounds.from_faults(faults.take(ok), schema.spring.f_max_n)
    length_m, cut_n = bounds.broken(l_motor[ok], f[ok])
    assert length_m.max() <= FAULT_TOL_M and cut_n.max() == 0.0
    assert (f[ok] >= 0).all() and (f[ok] <= bounds.f_limit_n + 1e-9).all()


def test_structured_module_refuses_bad_rows_and_other_seeds(struct30, struct_cases):
    q, faults = struct_cases
    module = StructuredAdapterModule(struct30)
    tensors = [t.clone() for t in module_inputs(q[:4], faults.take(np.arange(4)))]
    tensors[0][0, 0] = float("nan")  # NaN posture
    tensors[2][1, 0], tensors[3][1, 0] = 1.0, -0.1  # a jam at a negative length
    tensors[5][2, 1], tensors[6][2, 1] = 0.3, 0.2  # a band with lo > hi
    with torch.no_grad():
        l_motor, f, status = module(*tensors)
        _, _, other_seed = module(*module_inputs(q[:4], faults.take(np.arange(4)), seed=3))
    assert (status[:3].numpy() == Status.BAD_INPUT.code).all() and torch.isnan(l_motor[:3]).all()
    ref = struct30.adapter(faults.take([3]), check_physics=False)(q[3:4])
    assert status_array(status[3:].tolist())[0] == ref.status[0]
    assert (other_seed.numpy() == Status.BAD_INPUT.code).all()
    with pytest.raises(BodySchemaInputError, match="structured schema"):
        StructuredAdapterModule(object())


_BODY_ROUNDINGS = 256  # a polynomial's terms or a layer's width summed (a few hundred at most), one rounding each


def test_a_polynomial_torque_body_exports(request):
    """A per-muscle body with a polynomial torque (configs/myoelbow.yaml's kind: ``schema.body``, its paths by their
    snapshots built in the trace) exports at a static batch (the dynamic one: the slow test below), its small
    products fused where they can be."""
    test_the_exported_program_is_the_eager_module("polynomial_torque", 1, request)


@pytest.mark.slow
@pytest.mark.parametrize("which", list(FIXTURES))
@pytest.mark.parametrize("batch", ["dynamic", 1])
def test_the_exported_program_is_the_eager_module(which, batch, request):
    """The package's program (``deploy.package.exported_program``: torch.export, its small float64 products as
    multiply-sums where the batch is static) answers as the eager module: a dynamic batch's at the batch it was traced
    with and at 1, a static batch 1's on each of the first cases."""
    from lightning_bodyschema.deploy.package import exported_program

    schema, (q, faults) = (request.getfixturevalue(name) for name in FIXTURES[which])
    module = StructuredAdapterModule(schema).eval()
    program = exported_program(module, batch).module()
    for rows in (np.arange(len(q)), np.arange(1)) if batch == "dynamic" else np.arange(8)[:, None]:
        inputs = module_inputs(q[rows], faults.take(rows))
        with torch.no_grad():
            got, want = program(*inputs), module(*inputs)
        assert torch.equal(got[2], want[2])
        # the lengths: the body's sums as the exported graph may order them, less the elongation at tensions within
        # f_tol_n (~1e-13 m); the other solve's answer or a fault bound missed is off by 1e-5 m or more
        f_tol_n, lengths = 1e-9, want[0].nan_to_num()
        tol_m = motor_length_tol(f_tol_n, schema.spring, lengths) + rounding_tol(_BODY_ROUNDINGS, lengths)
        torch.testing.assert_close(got[0], want[0], rtol=0, atol=tol_m, equal_nan=True)
        torch.testing.assert_close(got[1], want[1], rtol=0, atol=f_tol_n, equal_nan=True)
