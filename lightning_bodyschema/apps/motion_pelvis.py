"""OpenSim's pelvis coordinates in a ``.mot`` file onto a MuJoCo model's floating root (e.g. myo:myolegs's ``root``).

OpenSim's gait models join the pelvis to the ground by ``ground_pelvis``: ``pelvis_tx, pelvis_ty, pelvis_tz`` [m]
place the pelvis origin along the ground's X (forward), Y (up) and Z (right), and ``pelvis_tilt, pelvis_list,
pelvis_rotation`` turn it about Z, then the new X, then the new Y (body-fixed Z-X-Y): ``R = Rz(tilt) Rx(list)
Ry(rotation)``; with all six at zero the pelvis frame is the ground frame. A MuJoCo model converted from such a model
(MyoSuite's legs: Z up, forward -Y, right -X) carries OpenSim's pelvis frame on its body ``pelvis``, below the free
joint's body; at the model's rest pose (``qpos0``) that frame's orientation ``P0`` in the world is where OpenSim's
ground axes lie (myoLegs: forward -Y, up +Z, right -X, to 1e-3 rad). So per frame the pelvis's orientation is ``P0 R``
and its origin ``P0 (tx, ty, tz)`` (the ground's origin is the world's), and the free joint's body follows rigidly:
``q_root = q_P0 (x) q_R (x) conj(q_P0) (x) q_root0`` and its position the pelvis origin less the rest offset between
the two bodies, turned. At zero coordinates this is the model's own rest pose (``pelvis_ty`` then sets the height).
MyoSuite's own .mot playback sets only the joints whose names the model has, and the model has no pelvis joints: it
leaves the root where it is. numpy and MuJoCo.
"""
from __future__ import annotations

import mujoco
import numpy as np

from ..errors import BodySchemaInputError
from ..sim.mjcf import compile_spec, load_spec
from ..statics.root import _quat_mul

PELVIS_ROTATIONS = ("pelvis_tilt", "pelvis_list", "pelvis_rotation")  # about the pelvis's Z, then X, then Y
PELVIS_TRANSLATIONS = ("pelvis_tx", "pelvis_ty", "pelvis_tz")
PELVIS_COLUMNS = PELVIS_ROTATIONS + PELVIS_TRANSLATIONS
PELVIS_BODY = "pelvis"
_AXES = {"x": (1.0, 0.0, 0.0), "y": (0.0, 1.0, 0.0), "z": (0.0, 0.0, 1.0)}


def axis_quat(angle_rad: np.ndarray, axis: str) -> np.ndarray:
    """(B, 4) unit quaternions ``(w, x, y, z)`` of turns by ``angle_rad`` (B,) about the axis ``"x"``, ``"y"`` or
    ``"z"``."""
    half = 0.5 * np.asarray(angle_rad, float)[:, None]
    return np.concatenate([np.cos(half), np.sin(half) * np.array(_AXES[axis])], 1)


def opensim_rotation(tilt_rad, list_rad, rotation_rad) -> np.ndarray:
    """(B, 4) the pelvis's orientation in OpenSim's ground frame, ``Rz(tilt) Rx(list) Ry(rotation)``."""
    return _quat_mul(_quat_mul(axis_quat(tilt_rad, "z"), axis_quat(list_rad, "x")), axis_quat(rotation_rad, "y"))


def _rotate(quat: np.ndarray, vec: np.ndarray) -> np.ndarray:
    """(B, 3) ``vec`` (B, 3) or (3,) turned by the unit quaternions ``quat`` (B, 4)."""
    vec = np.broadcast_to(vec, (len(quat), 3))
    pure = np.concatenate([np.zeros((len(quat), 1)), vec], 1)
    return _quat_mul(_quat_mul(quat, pure), quat * np.array([1.0, -1.0, -1.0, -1.0]))[:, 1:]


def rest_frames(source: str, root_body: str):
    """``(q_P0, x_pelvis0, q_root0, x_root0)``: the pelvis's and the free joint's body's world orientation and
    position at the model's rest pose, or None where the model has no body named ``pelvis``."""
    m = compile_spec(load_spec(source))
    pelvis, root = (mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, name) for name in (PELVIS_BODY, root_body))
    if pelvis < 0:
        return None
    d = mujoco.MjData(m)  # qpos = qpos0
    mujoco.mj_kinematics(m, d)
    return d.xquat[pelvis].copy(), d.xpos[pelvis].copy(), d.xquat[root].copy(), d.xpos[root].copy()


def root_qpos(columns: dict, degrees: bool, frames) -> np.ndarray:
    """(B, 7) the free joint's qpos (position, unit quaternion) from the six pelvis columns (B,) (angles in degrees
    where ``degrees``) and ``rest_frames``' answer ``frames`` (module docstring)."""
    q_p0, x_pelvis0, q_root0, x_root0 = frames
    angles = [np.asarray(columns[name], float) for name in PELVIS_ROTATIONS]
    angles = [np.deg2rad(a) if degrees else a for a in angles]
    q_pelvis = _quat_mul(np.broadcast_to(q_p0, (len(angles[0]), 4)), opensim_rotation(*angles))
    q_root = _quat_mul(_quat_mul(q_pelvis, q_p0 * np.array([1.0, -1.0, -1.0, -1.0])), q_root0)
    offset = _rotate(q_root0[None] * np.array([1.0, -1.0, -1.0, -1.0]), x_pelvis0 - x_root0)[0]  # in the root's frame
    x_pelvis = _rotate(np.broadcast_to(q_p0, q_root.shape), np.stack([columns[n] for n in PELVIS_TRANSLATIONS], 1))
    return np.concatenate([x_pelvis - _rotate(q_root, offset), q_root], 1)


def pelvis_root(columns: dict, degrees: bool, source, roots, path: str):
    """The floating root's ``(qpos (B, 7), None, None)`` from the ``.mot`` pelvis columns (popped), or None where the
    file has none, the body has no floating root (``roots``: its free joints; the columns are then left out), or the
    model has no ``pelvis`` body (left out too: no frame to put OpenSim's pelvis on). Some but not all six, on a
    body they would move: refused."""
    present = [name for name in PELVIS_COLUMNS if name in columns]
    if not present or len(roots) != 1 or source is None:
        return None
    from ..statics.root import free_roots

    frames = rest_frames(source, dict(free_roots(source))[roots[0]])
    if frames is None:
        return None
    if len(present) < len(PELVIS_COLUMNS):
        missing = [name for name in PELVIS_COLUMNS if name not in columns]
        raise BodySchemaInputError(f"{path}: the pelvis columns miss {missing}; give all of {list(PELVIS_COLUMNS)} "
                                   "or none")
    qpos = root_qpos(columns, degrees, frames)
    for name in PELVIS_COLUMNS:
        columns.pop(name)
    return qpos, None, None
