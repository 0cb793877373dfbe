"""Which joints each muscle crosses, for the per-muscle path model: from the MJCF, the user, or the data."""
from __future__ import annotations

import sys
import warnings
from typing import Optional

import numpy as np
import torch

from .._numpy import to_numpy
from ..networks.per_muscle import PerMusclePath
from ..sim.robot import check_muscle_joints, crossing_mapping

#: a slope of a muscle's length on a joint above this RMS over the data [m/rad] is a moment arm (0.1 mm/rad) ...
ARM_THRESHOLD_M = 1e-4
#: ... when it is also at least this share of the muscle's largest (a cubic's misfit leaks onto every joint)
ARM_SHARE = 0.1
_DETECT_DEGREE = 3


def resolve_crossing(robot_model, robot: dict, muscle_joints: Optional[dict]) -> Optional[dict]:
    """``{muscle: [joints]}``: ``muscle_joints`` if given, else the recorded data's (``robot["muscle_joints"]``),
    else the MJCF's (nonzero pattern of MuJoCo's tendon Jacobian); None: to be detected from the data."""
    muscles, joints = robot_model.muscle_names, robot_model.joint_names
    given = muscle_joints if muscle_joints is not None else (robot or {}).get("muscle_joints")
    if given is not None:
        return check_muscle_joints(given, muscles, joints)
    if robot_model.has_physics:
        return crossing_mapping(robot_model.crossing(), muscles, joints)
    return None


def data_arms_m(q_n: torch.Tensor, length_n: torch.Tensor, arm_scale: torch.Tensor) -> torch.Tensor:
    """``(M, N)`` RMS over the samples of each muscle's length slope on each joint [m/rad], from a least-squares
    cubic over every joint (``length_n``: normalized lengths; ``arm_scale (M, N)``: see ``StructuredSchema``)."""
    probe = PerMusclePath(np.ones((length_n.shape[1], q_n.shape[1]), bool), degree=_DETECT_DEGREE, n_hidden=0)
    probe = probe.to(q_n.device, torch.float64)
    probe.fit_polynomial(q_n, length_n)
    slope = probe.with_jacobian(q_n.to(torch.float64))[1]
    return slope.pow(2).mean(0).sqrt() * arm_scale.to(slope)


def crossing_from_data(q_n, length_n, arm_scale, robot_model, given: Optional[dict]) -> dict:
    """The joints the data shows each muscle crossing (RMS moment arm above ``ARM_THRESHOLD_M`` and ``ARM_SHARE``
    of the muscle's largest). Without
    ``given``: said on stderr, and returned. With it: a warning for every pair ``given`` calls uncrossed where the
    data shows a clear moment arm, with the figure; ``given`` returned."""
    muscles, joints = robot_model.muscle_names, robot_model.joint_names
    arms = data_arms_m(q_n, length_n, arm_scale).cpu()
    found = arms > torch.clamp(ARM_SHARE * arms.max(1, keepdim=True).values, min=ARM_THRESHOLD_M)
    found[~found.any(1), arms[~found.any(1)].argmax(1)] = True  # a muscle crosses at least one joint
    if given is None:
        mapping = crossing_mapping(to_numpy(found), muscles, joints)
        print(f"muscle_joints detected from the data (none given; RMS moment arm > {1e3 * ARM_THRESHOLD_M:g} mm/rad "
              f"and > {ARM_SHARE:g} of the muscle's largest):"
              f" {mapping}", file=sys.stderr)
        return mapping
    said = torch.tensor([[j in given[m] for j in joints] for m in muscles])
    for i, n in (found & ~said).nonzero().tolist():
        warnings.warn(f"muscle {muscles[i]!r} is said not to cross joint {joints[n]!r}, but the data shows an RMS "
                      f"moment arm of {1e3 * float(arms[i, n]):.3g} mm/rad there (its length model ignores it)")
    return given
