"""Adaptation to task-space targets: inverse kinematics for q_ref, then the ordinary adaptation pipeline."""
from __future__ import annotations

from typing import Optional

import numpy as np
import torch

from .._numpy import to_numpy
from ..errors import BodySchemaInputError
from ..variants import check_variant
from ..status import Status, status_array
from .command import AdaptationResult


def adapt_to_target(schema, target_xyz, faults, site: str = "hand", variant: str = "default", tol_m: float = 1e-4,
                    ik_options: Optional[dict] = None, **options) -> AdaptationResult:
    """Commands that put ``site`` on ``target_xyz (B, 3)`` [m] under ``faults`` (see ``BodySchema.adapt_to_target``)."""
    twin = schema.kinematic_twin()
    target = to_numpy(twin._check_target(to_numpy(target_xyz) if torch.is_tensor(target_xyz) else target_xyz))
    faults.validate(schema.n_muscles)
    if len(faults) != len(target):
        raise BodySchemaInputError(f"{len(target)} targets but {len(faults)} fault rows; give one row per case")
    check_variant(schema, variant, "adaptation variant")  # refuse before spending time on the inverse kinematics
    with torch.inference_mode(False):
        ik = twin.inverse_kinematics(target, site=site, tol_m=tol_m, **(ik_options or {}))
    q = to_numpy(ik.q)
    error = np.linalg.norm(schema.robot_model.site_position(q, site) - target, axis=1)  # MuJoCo is the judge
    reached = error <= tol_m
    n, m = len(target), schema.n_muscles
    out = AdaptationResult(np.full((n, m), np.nan), np.full((n, m), np.nan), status_array(Status.UNREACHABLE, size=n))
    if reached.any():
        inner = schema.adapt(q[reached], faults.take(reached), variant, **options)
        out.l_motor_m[reached], out.f_n[reached], out.status[reached] = inner.l_motor_m, inner.f_n, inner.status
        for name, value in inner.diagnostics.items():
            value = np.asarray(value)
            full = np.full((n,) + value.shape[1:], np.nan if value.dtype.kind == "f" else 0, value.dtype)
            full[reached] = value
            out.diagnostics[name] = full
    out.diagnostics.update(q_ref=np.where(reached[:, None], q, np.nan), q_closest=q, target_error_m=error)
    return out
