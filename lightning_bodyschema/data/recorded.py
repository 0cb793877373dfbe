"""Recorded data: a robot's own logs (joint angles, motor lengths, tensions) as a dataset, with no MJCF.

File format (CSV or NPZ), one row per static posture, SI units (rad or m for joints, m, N):

* columns ``q_<joint>`` (one per joint), ``l_<muscle>`` (motor length) and ``f_<muscle>`` (tension), one
  ``l_`` and one ``f_`` column per muscle; the header names the joints and muscles, and their order is
  the order of the schema's inputs and outputs;
* optional limits of any column: a CSV comment line ``# range <column> <lo> <hi>``; in an NPZ an array
  ``range_<column>`` = ``[lo, hi]``;
* optional units flag: ``# units: SI`` (CSV) or a string array ``units`` = ``"SI"`` (NPZ); any other
  value is refused (convert degrees, millimetres or kgf to SI first);
* CSV: other lines starting with ``#`` are comments; NPZ: each column is a 1-D array, in the order of an optional
  string array ``columns`` (else the archive's order), and arrays named ``meta_*`` are ignored
  (``tools/make_dataset.py`` keeps the generating model and settings there).

Rows with NaN/inf or a value outside a limit are dropped and counted. Joint ranges default to the kept
data's min/max, tension limits to [0, f_max] (``f_max_n``, paper: 150 N). A file that is not such a
table (missing column, unknown muscle, text in a number column, empty, other units) is refused with one
``BodySchemaInputError`` naming the problem.

A sensor log (``diagnosis.log``: which muscles failed) is this table plus the commands sent, ``l_cmd_<muscle>`` and
``f_cmd_<muscle>``, with optional ``t`` and ``case`` columns; there noisy readings are kept, not filtered.

The robot such a file describes is a ``sim.robot.ModelFreeRobot``: names, limits and spring constants, a
``RobotModel`` without physics (infer, adapt, checkpoints); everything that needs physics (the feasibility check,
evaluation, inverse kinematics) needs an MJCF, given separately.
"""
from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Mapping, Optional, Sequence

import numpy as np

from ..column_files import UNITS, read_columns, write_columns
from ..errors import BodySchemaInputError
from ..sim import SpringParams
from ..sim.robot import ModelFreeRobot, check_muscle_joints
from .datamodule import EquilibriumDataModule, check_loader_args, check_split
from .normalizer import Normalizer

PAPER_F_MAX_N = 150.0  # tension limit when neither the file nor the config gives one (the paper's f_max)
_COLUMN = re.compile(r"^([qlf])_(.+)$")
_MIN_ROWS = 10  # fewer kept rows cannot make a train and a validation split


# ---------------------------------------------------------------------------- reading files
@dataclass
class RecordedTable:
    """A recorded file as read: columns (n, ...) in SI units, names in header order, limits found in the file."""

    q: np.ndarray
    l_motor: np.ndarray
    f: np.ndarray
    joints: list
    muscles: list
    ranges: dict  # column name -> (lo, hi)


def read_recorded(path: str) -> RecordedTable:
    """Read a recorded CSV or NPZ file (module docstring), every row, NaN included; refuse a malformed one."""
    columns, ranges = read_columns(path, "recorded data file")
    return _as_table(path, columns, ranges)


def _as_table(path, columns: dict, ranges: dict) -> RecordedTable:
    groups = {"q": [], "l": [], "f": []}
    for name in columns:
        match = _COLUMN.match(name)
        if match is None:
            raise BodySchemaInputError(f"{path}: column {name!r} is not q_<joint>, l_<muscle> or f_<muscle>")
        groups[match.group(1)].append(match.group(2))
    joints, muscles = groups["q"], groups["l"]
    if not joints:
        raise BodySchemaInputError(f"{path}: no q_<joint> column; the header names the joints as q_<joint>")
    for have, need, kind in ((groups["f"], muscles, "f"), (muscles, groups["f"], "l")):
        missing = [name for name in need if name not in have]
        if missing:
            raise BodySchemaInputError(f"{path}: missing column {[f'{kind}_{m}' for m in missing]}; every muscle "
                                       "needs an l_<muscle> (motor length) and an f_<muscle> (tension) column")
    if not muscles:
        raise BodySchemaInputError(f"{path}: no l_<muscle>/f_<muscle> columns; the header names the muscles")
    unknown = [name for name in ranges if name not in columns]
    if unknown:
        raise BodySchemaInputError(f"{path}: a range is given for {unknown}, which are not columns")
    n_rows = len(next(iter(columns.values())))
    if n_rows == 0:
        raise BodySchemaInputError(f"{path} has a header but no rows")

    def stack(prefix, names):
        return np.stack([columns[f"{prefix}_{name}"] for name in names], axis=1)

    return RecordedTable(stack("q", joints), stack("l", muscles), stack("f", muscles), joints, muscles, dict(ranges))


# ---------------------------------------------------------------------------- writing files
def write_recorded(path: str, q, l_motor, f, joints: Sequence[str], muscles: Sequence[str],
                   ranges: Optional[Mapping[str, Sequence[float]]] = None, meta: Optional[dict] = None) -> None:
    """Write the format ``read_recorded`` reads: CSV for ``*.csv`` (17 significant digits: reads back exactly),
    else NPZ; deterministic bytes, written atomically. ``meta``: NPZ ``meta_*`` arrays / CSV comment lines."""
    columns = {f"q_{j}": q[:, i] for i, j in enumerate(joints)}
    columns.update({f"l_{m}": l_motor[:, i] for i, m in enumerate(muscles)})
    columns.update({f"f_{m}": f[:, i] for i, m in enumerate(muscles)})
    write_columns(path, columns, ranges, meta)


# ---------------------------------------------------------------------------- the data module
def _limits(names, prefix, config, file_ranges, default):
    """(n, 2) limits per name: the config's (a dict name -> [lo, hi]) over the file's over ``default (n, 2)``."""
    config = dict(config or {})
    unknown = [name for name in config if name not in names]
    if unknown:
        raise BodySchemaInputError(f"limits given for unknown {'joint' if prefix == 'q' else 'muscle'} {unknown}; "
                                   f"the file's are {list(names)}")
    out = np.array(default, dtype=np.float64)
    for i, name in enumerate(names):
        lim = config.get(name, file_ranges.get(f"{prefix}_{name}"))
        if lim is not None:
            out[i] = lim
    bad = [names[i] for i in range(len(names)) if not out[i, 0] < out[i, 1]]
    if bad:
        raise BodySchemaInputError(f"{prefix} limits of {bad} are not [lo, hi] with lo < hi: {out.tolist()}")
    return out


class RecordedDataModule(EquilibriumDataModule):
    """A robot's recorded (q, l_motor, f) samples from a CSV or NPZ file (format: module docstring); no MJCF.

    ``bodyschema fit --data RecordedDataModule --data.path logs.csv``. Splits, normalizer and loaders are the
    simulation module's; the schema's ``robot`` is a ``ModelFreeRobot`` (names, limits, spring), so the
    checkpoint carries the joint and muscle names and limits instead of a model.

    Args:
        path: the recorded file (``.csv`` or ``.npz``).
        seed, val_fraction, batch_size: the split and the minibatch size, as in ``EquilibriumDataModule``.
        joints, muscles: the expected names (the robot's); the file must have exactly these columns. Default: the
            file's header decides.
        q_range: {joint: [lo, hi]} joint limits; default: the file's ``range`` lines, else the kept data's min/max.
        l_range, f_range: {muscle: [lo, hi]} motor-length [m] and tension [N] limits; default: the file's, else
            no length limit and tensions in [0, f_max_n].
        units: the units of the file; only ``"SI"``.
        k_n, alpha_per_m: spring constants (paper: 1000 N, 20 1/m), scalar or per muscle.
        f_max_n: tension limit [N], scalar or per muscle; default: the upper tension limits, else 150 N.
        muscle_joints: ``{muscle: [joints]}``, the joints each muscle crosses (for ``StructuredSchema``'s
            ``length_model="per_muscle"``, through ``robot``); default: detected from the data when a fit starts.
    """

    def __init__(self, path: str, seed: int = 0, val_fraction: float = 0.2, joints: Optional[Sequence[str]] = None,
                 muscles: Optional[Sequence[str]] = None, q_range: Optional[dict] = None,
                 l_range: Optional[dict] = None, f_range: Optional[dict] = None, units: str = UNITS,
                 k_n: float | list[float] = 1000.0, alpha_per_m: float | list[float] = 20.0,
                 f_max_n: float | list[float] | None = None, batch_size: int = 64,
                 muscle_joints: Optional[dict] = None):
        super(EquilibriumDataModule, self).__init__()  # the simulation module's __init__ builds an MJCF model
        if units != UNITS:
            raise BodySchemaInputError(f"units={units!r} is not supported; recorded data must be in SI units "
                                       f"(rad, m, N): units {UNITS!r}")
        check_loader_args(seed, val_fraction, batch_size)
        self.save_hyperparameters()
        table = read_recorded(str(path))
        _check_names(path, "joint", joints, table.joints)
        _check_names(path, "muscle", muscles, table.muscles)
        self.robot_model, self.spring, self.arrays, self.n_dropped = _robot_and_rows(
            path, table, q_range, l_range, f_range, k_n, alpha_per_m, f_max_n)
        check_split(len(self.arrays["q"]), val_fraction)
        self.normalizer = Normalizer(2 * self.robot_model.n_muscles, self.robot_model.n_joints)
        self.muscle_joints = None if muscle_joints is None else check_muscle_joints(
            muscle_joints, self.robot_model.muscle_names, self.robot_model.joint_names)

    @property
    def robot(self) -> dict:
        """Names, limits and spring constants (and ``muscle_joints`` when given): a schema rebuilds the robot from
        these, with no model."""
        robot = {**self.robot_model.as_dict(), "spring": self.spring.as_dict()}
        return robot if self.muscle_joints is None else {**robot, "muscle_joints": self.muscle_joints}

    def _load(self):
        return self.arrays


def _check_names(path, kind, expected, found):
    if expected is None:
        return
    unknown = [name for name in found if name not in expected]
    if unknown:
        raise BodySchemaInputError(f"{path}: unknown {kind} {unknown}; the robot's {kind}s are {list(expected)}")
    missing = [name for name in expected if name not in found]
    if missing:
        raise BodySchemaInputError(f"{path}: missing columns for {kind}s {missing}")
    if list(expected) != list(found):
        raise BodySchemaInputError(f"{path}: {kind} columns in the order {found}; the robot's order is "
                                   f"{list(expected)}")


def _robot_and_rows(path, table: RecordedTable, q_range, l_range, f_range, k_n, alpha_per_m, f_max_n):
    """The robot (names, limits, spring) and the kept rows; prints how many rows were dropped and why."""
    n, m = len(table.q), len(table.muscles)
    finite = np.isfinite(table.q).all(1) & np.isfinite(table.l_motor).all(1) & np.isfinite(table.f).all(1)
    q_lim = _limits(table.joints, "q", q_range, table.ranges, np.tile([-np.inf, np.inf], (len(table.joints), 1)))
    l_lim = _limits(table.muscles, "l", l_range, table.ranges, np.tile([-np.inf, np.inf], (m, 1)))
    f_default = np.zeros((m, 2))
    f_default[:, 1] = np.broadcast_to(np.asarray(PAPER_F_MAX_N if f_max_n is None else f_max_n, float), (m,))
    f_lim = _limits(table.muscles, "f", f_range, table.ranges, f_default)
    spring = SpringParams(k_n, alpha_per_m, f_lim[:, 1].tolist() if f_max_n is None else f_max_n)
    with np.errstate(invalid="ignore"):
        inside = ((table.q >= q_lim[:, 0]) & (table.q <= q_lim[:, 1])).all(1) \
            & ((table.l_motor >= l_lim[:, 0]) & (table.l_motor <= l_lim[:, 1])).all(1) \
            & ((table.f >= f_lim[:, 0]) & (table.f <= f_lim[:, 1])).all(1)
    keep = finite & inside
    unbounded = np.isinf(q_lim).any(1)  # a joint with no range given: the kept rows' span is its range
    if keep.any():
        q_lim[unbounded] = np.stack([table.q[keep].min(0), table.q[keep].max(0)], axis=1)[unbounded]
    print(f"recorded data {path}: {n} rows, kept {int(keep.sum())}; dropped {int((~finite).sum())} with NaN/inf and "
          f"{int((finite & ~inside).sum())} outside the limits")
    if keep.sum() < _MIN_ROWS:
        raise BodySchemaInputError(f"{path}: only {int(keep.sum())} of {n} rows are finite and inside the limits; "
                                   f"need at least {_MIN_ROWS}")
    robot = ModelFreeRobot(table.joints, q_lim, table.muscles, l_lim, f_lim)
    arrays = {"q": table.q[keep], "l_motor": table.l_motor[keep], "f": table.f[keep]}
    return robot, spring, arrays, int(n - keep.sum())
