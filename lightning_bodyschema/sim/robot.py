"""The robot interface a schema uses (``RobotModel``), the robot known by names and limits only
(``ModelFreeRobot``), and the one factory from a schema's ``robot`` hyperparameter (``robot_model_from_dict``).

``sim.MusculoskeletalModel`` (an MJCF compiled by MuJoCo) and ``ModelFreeRobot`` (recorded data, no model) both
implement ``RobotModel``. ``has_physics`` says which parts of a schema can run: with physics, the feasibility
check, kinematics (``kinematics(q) -> (l_geo (B, M) [m], G (B, M, N) [m/rad], tau_bias (B, N) [N m])``), inverse
kinematics and evaluation; without, only what needs names and limits (infer, adapt, checkpoints).
"""
from __future__ import annotations

import hashlib
import json
from typing import Mapping, Protocol, Sequence, runtime_checkable

import numpy as np

from ..errors import BodySchemaInputError, did_you_mean
from .model import MusculoskeletalModel


@runtime_checkable
class RobotModel(Protocol):
    """What every part of the package may ask of a robot. ``xml_hash``: the sha256 that identifies it in
    checkpoints. ``check_q(q, within_range=False)``: q as a (B, N) float64 array, or a ``BodySchemaInputError``
    naming the first bad value (wrong width, NaN/inf, outside ``q_range`` [rad or m] when ``within_range``)."""

    has_physics: bool
    n_joints: int
    n_muscles: int
    joint_names: list
    muscle_names: list
    q_range: np.ndarray
    xml_hash: str

    def check_q(self, q, within_range: bool = False) -> np.ndarray: ...


class ModelFreeRobot:
    """A robot known by names and limits only: joints with ranges, muscles with tension limits and a spring.

    Implements ``RobotModel`` with ``has_physics = False``; ``xml`` is None.
    """

    xml = None
    has_physics = False

    def __init__(self, joints: Sequence[str], q_range, muscles: Sequence[str], l_range=None, f_range=None):
        self.joint_names, self.muscle_names = list(joints), list(muscles)
        self._q_range = np.asarray(q_range, dtype=np.float64).reshape(len(self.joint_names), 2)
        inf = np.array([-np.inf, np.inf])
        self.l_range = np.tile(inf, (self.n_muscles, 1)) if l_range is None else np.asarray(l_range, float)
        self.f_range = np.tile(inf, (self.n_muscles, 1)) if f_range is None else np.asarray(f_range, float)

    def check_q(self, q, within_range: bool = False) -> np.ndarray:
        """q as a (B, N) float64 array; refuses other widths, NaN/inf and (``within_range``) postures outside
        ``q_range``, naming the first bad value, as ``MusculoskeletalModel.check_q`` does."""
        q = np.atleast_2d(np.asarray(q, dtype=np.float64))
        if q.ndim != 2 or q.shape[1] != self.n_joints:
            raise BodySchemaInputError(f"q has shape {q.shape}; expected (B, {self.n_joints}) for joints "
                                       f"{self.joint_names}")
        if not np.all(np.isfinite(q)):
            raise BodySchemaInputError("q contains NaN or inf")
        outside = (q < self._q_range[:, 0]) | (q > self._q_range[:, 1]) if within_range else np.zeros(q.shape, bool)
        if outside.any():
            b, j = np.argwhere(outside)[0]
            raise BodySchemaInputError(f"q[{b}] of joint {self.joint_names[j]!r} is {q[b, j]:.6g}, outside its range "
                                       f"{self._q_range[j].tolist()} ({int(outside.any(1).sum())} posture(s) out "
                                       "of range)")
        return q

    @property
    def n_joints(self) -> int:
        return len(self.joint_names)

    @property
    def n_muscles(self) -> int:
        return len(self.muscle_names)

    @property
    def q_range(self) -> np.ndarray:
        return self._q_range.copy()

    def as_dict(self) -> dict:
        """Plain lists (checkpoint hyperparameters): names and limits."""
        return {"joints": self.joint_names, "q_range": self._q_range.tolist(), "muscles": self.muscle_names,
                "l_range": self.l_range.tolist(), "f_range": self.f_range.tolist()}

    @property
    def xml_hash(self) -> str:
        """sha256 of the description: identifies the robot in checkpoints as a model's XML hash does."""
        return hashlib.sha256(json.dumps(self.as_dict(), sort_keys=True).encode()).hexdigest()

    def __repr__(self):
        return (f"ModelFreeRobot({self.n_joints} joints {self.joint_names}, "
                f"{self.n_muscles} muscles {self.muscle_names})")


def robot_model_from_dict(robot: dict) -> RobotModel:
    """The robot a schema's ``robot`` hyperparameter describes: a ``MusculoskeletalModel`` when it carries
    ``model_xml``, else a ``ModelFreeRobot`` (``joints``, ``q_range``, ``muscles``, limits)."""
    if robot.get("model_xml"):
        return MusculoskeletalModel(robot["model_xml"], muscles=robot["muscles"])
    missing = [key for key in ("joints", "q_range", "muscles") if key not in robot]
    if missing:
        raise BodySchemaInputError(f"robot description lacks {missing}: give model_xml (an MJCF), or joints, "
                                   "q_range and muscles (recorded data)")
    return ModelFreeRobot(robot["joints"], robot["q_range"], robot["muscles"], robot.get("l_range"),
                          robot.get("f_range"))


def check_muscle_joints(muscle_joints: Mapping, muscles: Sequence[str], joints: Sequence[str]) -> dict:
    """``{muscle: [joints]}``, the joints each muscle crosses, checked: every muscle once, known names, each
    muscle crossing at least one joint; one ``BodySchemaInputError`` naming the first bad entry. Joints are
    returned in the robot's order."""
    if not isinstance(muscle_joints, Mapping):
        raise BodySchemaInputError(f"muscle_joints={muscle_joints!r} must be a mapping {{muscle: [joints]}}")
    unknown = [m for m in muscle_joints if m not in muscles]
    if unknown:
        raise BodySchemaInputError(f"muscle_joints names unknown muscle {unknown[0]!r}"
                                   f"{did_you_mean(unknown[0], muscles)}; the muscles are "
                                   f"{list(muscles)}")
    missing = [m for m in muscles if m not in muscle_joints]
    if missing:
        raise BodySchemaInputError(f"muscle_joints has no entry for muscle(s) {missing}; give every muscle's joints")
    out = {}
    for muscle, crossed in muscle_joints.items():
        crossed = [crossed] if isinstance(crossed, str) else list(crossed)
        bad = [j for j in crossed if j not in joints]
        if bad:
            raise BodySchemaInputError(f"muscle_joints[{muscle!r}] names unknown joint {bad[0]!r}"
                                       f"{did_you_mean(bad[0], joints)}; the joints are "
                                       f"{list(joints)}")
        if not crossed:
            raise BodySchemaInputError(f"muscle_joints[{muscle!r}] is empty; a muscle crosses at least one joint")
        out[muscle] = [j for j in joints if j in crossed]
    return {m: out[m] for m in muscles}


def crossing_mapping(crossing, muscles: Sequence[str], joints: Sequence[str]) -> dict:
    """``{muscle: [joints]}`` from a ``(M, N)`` bool array."""
    return {m: [j for j, c in zip(joints, row) if c] for m, row in zip(muscles, np.asarray(crossing, bool))}
