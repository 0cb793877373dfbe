"""Inverse dynamics with the QP on CUDA (marker ``gpu``; skipped without a CUDA device): the same statuses and, to the
solver's tolerance, the same activations and controls as on the CPU; residual actuators and faults included.

Tolerance: the dual Newton stops at a torque residual of ``STATIC_TOL_NM`` (1e-12 N m); two stops of that size on
moment arms of ~1e-2 m and peak forces of ~1e3 N leave the activations within ~1e-9 of each other whatever order the
kernels sum in, and a control is the activation step scaled by tau / h <= ~20: 1e-7 holds both with room.
"""
from __future__ import annotations

import numpy as np
import pytest
import torch

pytestmark = [pytest.mark.gpu, pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")]
pytest.importorskip("myo_sim")
ACTIVATION_ATOL = 1e-7


@pytest.mark.parametrize("options", [{}, {"faults": {"cut": ["BRA_tendon"]}},
                                     {"residual_dofs": ["r_shoulder_elev", "r_elbow_flex"]}])
def test_cuda_answers_are_the_cpus(options):
    from lightning_bodyschema.statics import StaticBody, inverse_dynamics

    body = StaticBody("myo:myoelbow_2dof")
    t = np.arange(0.0, 1.0, 0.002)
    lo, hi = body.model.q_range.T
    phase = 2 * np.pi * np.array([0.7, 1.1]) * t[:, None]
    amp = (hi - lo) / 4
    q, qvel = (lo + hi) / 2 + amp * np.sin(phase), amp * 2 * np.pi * np.array([0.7, 1.1]) * np.cos(phase)
    qacc = -amp * (2 * np.pi * np.array([0.7, 1.1])) ** 2 * np.sin(phase)
    cpu = inverse_dynamics(body, q, qvel, qacc, t=t, **options)
    cuda = inverse_dynamics(body, q, qvel, qacc, t=t, device="cuda", **options)
    np.testing.assert_array_equal(cpu.status, cuda.status)
    assert cpu.ok.sum() >= 50
    np.testing.assert_allclose(cuda.activation, cpu.activation, atol=ACTIVATION_ATOL, equal_nan=True)
    np.testing.assert_allclose(cuda.control, cpu.control, atol=20 * ACTIVATION_ATOL, equal_nan=True)
    if cpu.residual_nm is not None:
        np.testing.assert_allclose(cuda.residual_nm, cpu.residual_nm, atol=1e-6, equal_nan=True)
