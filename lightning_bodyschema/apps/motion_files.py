"""Motion files for ``tools/static_opt.py --motion``: a ``t`` column [s] and one column per free joint.

CSV or NPZ as the posture files (``apps.static_opt``), plus optional ``qvel_<joint>`` and ``qacc_<joint>`` columns
(all joints, or none: then the Savitzky-Golay differentiator of ``statics.differentiate`` gives them). OpenSim's
``.mot`` (the storage format MyoSuite's own import reads): header lines up to ``endheader`` (``inDegrees=yes``: the
hinge joints' columns are in degrees), then a ``time`` column and one column per coordinate; coordinates that are not
free joints of the body (locked, coupled, absent) are left out and named. On a body with a floating root, OpenSim's
six pelvis coordinates (``pelvis_tilt`` .. ``pelvis_tz``) move the root (``apps.motion_pelvis``; without a floating
root, or on a model without a ``pelvis`` body, they are left out and named).

A floating root (a free joint ``J`` of the body's source, e.g. myo:myolegs's ``root``; ``statics.root``): columns
``J_px, J_py, J_pz`` [m] and ``J_qw, J_qx, J_qy, J_qz`` (its unit quaternion) per frame, and optionally
``qvel_J_tx .. qvel_J_rz`` and ``qacc_J_tx .. qacc_J_rz`` (MuJoCo's qvel convention: linear velocity in the world,
angular velocity in the root's frame); without them the root moves by the differentiator too. Without the
position columns the root stays welded where the model places it. CSV and NPZ only.
"""
from __future__ import annotations

import os

import numpy as np

from ..errors import BodySchemaInputError
from .posture_files import postures_of, read_posture_columns

DERIVATIVES = ("qvel_", "qacc_")


def read_mot(path: str) -> tuple[dict, bool]:
    """``({column: (B,) values}, in_degrees)`` of an OpenSim ``.mot`` file (module docstring)."""
    with open(path, encoding="utf-8-sig") as fh:
        lines = fh.read().splitlines()
    end = next((i for i, line in enumerate(lines) if line.strip().lower() == "endheader"), None)
    if end is None:
        raise BodySchemaInputError(f"{path}: no 'endheader' line; an OpenSim .mot file has a header ending in it")
    degrees = any(line.replace(" ", "").lower() == "indegrees=yes" for line in lines[:end])
    body = [line.split() for line in lines[end + 1:] if line.strip()]
    if len(body) < 2:
        raise BodySchemaInputError(f"{path}: expected a line of column names and rows of numbers after endheader")
    header = body[0]
    if any(len(row) != len(header) for row in body[1:]):
        bad = next(k for k, row in enumerate(body[1:]) if len(row) != len(header))
        raise BodySchemaInputError(f"{path}: data row {bad + 1} has {len(body[bad + 1])} fields; the header has "
                                   f"{len(header)}")
    try:
        values = np.array(body[1:], dtype=np.float64)
    except ValueError:
        raise BodySchemaInputError(f"{path}: a value after the column names is not a number") from None
    columns = {name: values[:, k] for k, name in enumerate(header)}
    columns["t"] = columns.pop("time", columns.pop("t", None))
    if columns["t"] is None:
        raise BodySchemaInputError(f"{path}: no 'time' column")
    return columns, degrees


def read_motion(path: str, model, roots=(), source=None) -> tuple:
    """``(t (B,), q, qvel, qacc (B, N), root)`` of ``model``'s free joints from a motion file; qvel and qacc None
    where the file gives none (the caller differentiates); ``root``: the floating roots' ``(qpos (B, 7K), qvel,
    qacc (B, 6K) or None)`` of the free joints named ``roots`` (module docstring), None where the file has none;
    ``source``: the model's source (a ``.mot`` file's pelvis columns are put on its root: ``apps.motion_pelvis``)."""
    if not os.path.isfile(path):
        raise BodySchemaInputError(f"--motion {path!r} does not exist")
    if path.lower().endswith(".mot"):
        return _from_mot(path, model, list(roots), source)
    columns = read_posture_columns(path)
    if "t" not in columns:
        raise BodySchemaInputError(f"{path}: no 't' column; a motion needs one, the frame times [s]")
    t = columns.pop("t")
    free = model.joint_names
    root = _root_columns(columns, list(roots), path)
    derivatives = [_derivative(columns, prefix, free, path) for prefix in DERIVATIVES]
    return (t, postures_of(columns, free, path), *derivatives, root)


ROOT_POSE = ("px", "py", "pz", "qw", "qx", "qy", "qz")


def _root_columns(columns: dict, roots: list, path: str):
    """The roots' columns (popped; module docstring) as ``(qpos, qvel, qacc)``, None without any."""
    from ..statics.root import ROOT_DOFS

    groups = [("", ROOT_POSE)] + [(prefix, ROOT_DOFS) for prefix in DERIVATIVES]
    found = [[f"{prefix}{j}_{part}" for j in roots for part in parts] for prefix, parts in groups]
    present = [[name in columns for name in names] for names in found]
    if not any(present[0]):
        stray = [name for names, flags in zip(found[1:], present[1:]) for name, f in zip(names, flags) if f]
        if stray:
            raise BodySchemaInputError(f"{path}: root velocity columns {stray[:3]} without the root's position "
                                       f"columns {found[0]}")
        return None
    arrays = []
    for names, flags in zip(found, present):
        if any(flags) and not all(flags):
            missing = [n for n, f in zip(names, flags) if not f]
            raise BodySchemaInputError(f"{path}: the floating root's columns miss {missing}; give all of {names}")
        arrays.append(np.stack([np.asarray(columns.pop(n), np.float64) for n in names], 1) if all(flags) else None)
    return tuple(arrays)


def _derivative(columns: dict, prefix: str, free: list, path: str):
    """The ``prefix<joint>`` columns (popped) as (B, N), None where there are none; some but not all: refused."""
    named = {name[len(prefix):]: columns.pop(name) for name in list(columns) if name.startswith(prefix)}
    if not named:
        return None
    missing = [j for j in free if j not in named]
    if missing:
        raise BodySchemaInputError(f"{path}: {prefix}<joint> columns miss {missing}; give one for every free joint "
                                   f"{free} or none (then they are computed)")
    return postures_of(named, free, path)


def _from_mot(path: str, model, roots: list, source):
    from .motion_pelvis import pelvis_root

    columns, degrees = read_mot(path)
    t = columns.pop("t")
    root = pelvis_root(columns, degrees, source, roots, path)
    free = model.joint_names
    left = sorted(set(columns) - set(free))
    if left:
        print(f"{path}: left out {len(left)} column(s) that are not free joints of the body: {left}")
    q = postures_of({name: columns[name] for name in columns if name in free}, free, path)
    if degrees:  # OpenSim writes rotations in degrees, translations in metres
        import mujoco

        hinge = model.mj_model.jnt_type[model.joint_map.free] == int(mujoco.mjtJoint.mjJNT_HINGE)
        q = np.where(hinge, np.deg2rad(q), q)
    return t, q, None, None, root
