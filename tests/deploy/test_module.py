"""The tensor-only adapter module (eager, no compile): the numbers and statuses of the Python adapter."""
import numpy as np
import pytest
import torch

from lightning_bodyschema.deploy.module import FAULT_TOL_M, STATUS_CODES, AdapterModule
from lightning_bodyschema.errors import BodySchemaInputError
from lightning_bodyschema.faults import Faults
from lightning_bodyschema.schemas import AutoEncoderSchema
from lightning_bodyschema.status import status_codes


def module_inputs(q, faults, seed=0):
    nan = np.full(faults.cut.shape, np.nan)
    band = np.stack([nan, nan], -1) if faults.l_band_m is None else faults.l_band_m
    arrays = (q, faults.cut, faults.fix, faults.l_fixed_m, nan if faults.f_max_n is None else faults.f_max_n,
              band[..., 0], band[..., 1])
    return tuple(torch.from_numpy(np.ascontiguousarray(a, dtype=np.float64)) for a in arrays) + (torch.tensor(seed),)


def test_module_equals_the_python_adapter(diff60, mixed_cases):
    schema = diff60[0]
    q, faults = mixed_cases
    ref = schema.adapter(faults, n_steps=20, check_physics=False)(q)
    with torch.no_grad():
        l_motor, f, status = AdapterModule(schema, 20)(*module_inputs(q, faults))
    status = status.numpy()
    ok = status == STATUS_CODES["ok"]
    assert ok.sum() >= 30 and (status_codes(ref.status) == status).all()  # the same status on every case
    np.testing.assert_allclose(l_motor.numpy()[ok], ref.l_motor_m[ok], rtol=0, atol=1e-9)
    np.testing.assert_allclose(f.numpy()[ok], ref.f_n[ok], rtol=0, atol=1e-6)
    # Python calls these ok; their band lies above their jam (an empty box), so the command breaks one of them
    not_met = status == STATUS_CODES["fault_not_met"]
    broken = np.maximum(ref.diagnostics["band_violation_m"], ref.diagnostics["jam_violation_m"])
    assert not_met.any() and (broken[not_met] > FAULT_TOL_M).all() and (broken[ok] <= FAULT_TOL_M).all()
    assert np.isnan(l_motor.numpy()[~ok]).all() and np.isnan(f.numpy()[~ok]).all()


def test_one_module_serves_every_fault_set(diff60, mixed_cases):
    """The same module, healthy then faulted: the healthy call is the adapter of a fault-free batch."""
    schema = diff60[0]
    q, faults = mixed_cases
    healthy = Faults.none(len(q), schema.n_muscles)
    module = AdapterModule(schema, 20)
    with torch.no_grad():
        l_h, f_h, s_h = module(*module_inputs(q, healthy))
        module(*module_inputs(q, faults))
    ref = schema.adapter(healthy, n_steps=20, check_physics=False)(q)
    assert (s_h.numpy() == 0).all() and (ref.status == "ok").all()
    np.testing.assert_allclose(f_h.numpy(), ref.f_n, rtol=0, atol=1e-6)
    np.testing.assert_allclose(l_h.numpy(), ref.l_motor_m, rtol=0, atol=1e-9)


def test_unknown_seed_is_bad_input_and_a_baked_seed_picks_its_draw(diff60, mixed_cases):
    schema = diff60[0]
    q, faults = mixed_cases
    module = AdapterModule(schema, 20, seeds=[0, 7])
    with torch.no_grad():
        _, _, unknown = module(*module_inputs(q, faults, seed=3))
        l0, _, _ = module(*module_inputs(q, faults, seed=0))
        l7, _, s7 = module(*module_inputs(q, faults, seed=7))
    assert (unknown.numpy() == STATUS_CODES["bad_input"]).all()
    both = (s7.numpy() == 0)
    assert both.any() and not np.allclose(l0.numpy()[both], l7.numpy()[both])


def test_other_schemas_are_refused(dm):
    with pytest.raises(BodySchemaInputError, match="diffusion schema"):
        AdapterModule(AutoEncoderSchema(robot=dm.robot))
