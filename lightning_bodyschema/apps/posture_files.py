"""Posture files (CSV or NPZ, one column per free joint) read and checked for what needs no body, and results of
chunks joined: shared by ``tools/static_opt.py``'s postures (``apps.static_opt``) and motions (``apps.motion_opt``)."""
from __future__ import annotations

import os

import numpy as np

from ..errors import BodySchemaInputError, did_you_mean


def read_posture_columns(path: str) -> dict:
    """``{column: (B,) values}`` of a posture file, checked for what needs no body: it exists, parses, has rows,
    and every value is finite (rows counted from 1, the first posture after the header)."""
    from ..column_files import read_csv_columns, read_npz_columns

    if not os.path.isfile(path):
        raise BodySchemaInputError(f"--postures {path!r} does not exist")
    columns = (read_npz_columns(path) if path.endswith(".npz") else read_csv_columns(path))[0]
    names = list(columns)
    q = np.stack([np.asarray(columns[name], dtype=np.float64) for name in names], axis=1) if names else np.zeros((0, 0))
    if not len(q):
        raise BodySchemaInputError(f"{path} has no posture rows")
    bad = np.argwhere(~np.isfinite(q))
    if bad.size:
        row, col = bad[0]
        raise BodySchemaInputError(f"{path}: posture row {row + 1} (counted from 1 after the header), joint "
                                   f"{names[col]!r} is {q[row, col]}; every value must be a finite number "
                                   f"({len(np.unique(bad[:, 0]))} row(s) affected)")
    return columns


def postures_of(columns: dict, free: list, path: str) -> np.ndarray:
    """(B, N) postures in the order of the free joints ``free`` from ``read_posture_columns``' columns."""
    named = {(name[2:] if name.startswith("q_") and name[2:] in free else name): v for name, v in columns.items()}
    unknown = [name for name in columns if (name[2:] if name.startswith("q_") else name) not in free]
    if unknown:
        raise BodySchemaInputError(f"{path}: columns {unknown} are not free joints of the body"
                                   f"{did_you_mean(unknown[0].removeprefix('q_'), free)}; allowed: {free}")
    missing = [name for name in free if name not in named]
    if missing:
        raise BodySchemaInputError(f"{path}: missing columns {missing}; the body's free joints are {free}")
    return np.stack([np.asarray(named[name], dtype=np.float64) for name in free], axis=1)


def concatenate(parts):
    """One ``StaticResult`` (or ``MotionResult``) of the chunks' rows, in order: every array field joined."""
    from dataclasses import fields, replace

    from ..faults.faults import Faults

    def join(objects, name):
        values = [getattr(o, name) for o in objects]
        return None if values[0] is None else np.concatenate(values)

    faults = Faults(*(join([p.faults for p in parts], k) for k in ("cut", "fix", "l_fixed_m", "f_max_n", "l_band_m")))
    rows = [f.name for f in fields(parts[0]) if isinstance(getattr(parts[0], f.name), np.ndarray)]
    return replace(parts[0], faults=faults, **{k: join(parts, k) for k in rows})
