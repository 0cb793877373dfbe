"""The sensor log: what a robot's controller sent and what its sensors read back, as ``diagnose`` takes it.

File format (CSV or NPZ, the layout of ``data/recorded.py``: header, ``# units: SI``, NPZ columns), one row per
sample, SI units:

* what the sensors read: ``q_<joint>`` [rad, or m for a slide joint], ``l_<muscle>`` motor encoder [m],
  ``f_<muscle>`` load cell [N] (optional, per muscle: a robot without a load cell on a muscle leaves its column out);
* what was sent: ``l_cmd_<muscle>`` [m] and ``f_cmd_<muscle>`` [N] (every muscle);
* optional ``t`` [s] (time of the sample) and ``case`` (an integer): rows with the same ``case`` are one log, and
  the logs of a file are answered together (batched); without ``case`` the whole file is one log;
* columns whose name starts with ``x_`` are the user's own (a drill's posture error, a controller's state) and are
  ignored.

Readings are noisy: a tension that reads -0.4 N or 151 N is data, not a bad row (no range filter here, unlike the
training reader). Refused, with one message: a missing column, a column that names no joint or muscle of the robot,
a non-finite value (its row counted from 1, as a user counts), a units flag other than SI.
"""
from __future__ import annotations

import difflib
from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np

from ..column_files import read_columns, write_columns
from ..errors import BodySchemaInputError

SENT = ("l_cmd_", "f_cmd_")  # checked before the reading prefixes: "l_cmd_x" is a command, not muscle "cmd_x"
READ = ("q_", "l_", "f_")
EXTRA = "x_"  # the user's own columns, ignored


@dataclass
class SensorLog:
    """C logs of up to R rows each (shorter logs padded with zeros; ``rows`` marks the real ones), SI units.

    q_rad (C, R, N) joint readings; l_m (C, R, M) motor encoders; f_n (C, R, M) load cells, NaN in the columns of
    muscles without one (``has_f`` (M,) False); l_cmd_m, f_cmd_n (C, R, M) what was sent; rows (C, R) bool;
    t_s (C, R) or None; cases (C,) the file's case labels.
    """

    q_rad: np.ndarray
    l_m: np.ndarray
    f_n: np.ndarray
    l_cmd_m: np.ndarray
    f_cmd_n: np.ndarray
    rows: np.ndarray
    has_f: np.ndarray
    joints: list
    muscles: list
    t_s: Optional[np.ndarray] = None
    cases: Optional[np.ndarray] = None

    def __len__(self) -> int:
        return len(self.rows)

    @classmethod
    def from_rows(cls, joints: Sequence[str], muscles: Sequence[str], q_rad, l_m, l_cmd_m, f_cmd_n, f_n=None,
                  case=None, t_s=None) -> "SensorLog":
        """Logs from flat rows (S, ...) grouped by ``case`` (S,) ints (None: one log); ``f_n`` (S, M) with NaN
        columns for muscles without a load cell, or None (no load cell at all)."""
        q_rad, l_m = np.asarray(q_rad, float), np.asarray(l_m, float)
        n_rows = len(q_rad)
        f_n = np.full(l_m.shape, np.nan) if f_n is None else np.asarray(f_n, float)
        case = np.zeros(n_rows, np.int64) if case is None else np.asarray(case).astype(np.int64)
        labels, index = np.unique(case, return_inverse=True)
        rank = _rank_within(index, len(labels))
        width = int(rank.max()) + 1 if n_rows else 0
        rows = np.zeros((len(labels), width), bool)
        rows[index, rank] = True

        def grouped(a):  # padding rows hold zeros: finite, and masked out by ``rows`` wherever it matters
            out = np.zeros((len(labels), width) + a.shape[1:])
            out[index, rank] = a
            return out
        has_f = ~np.isnan(f_n).all(0) if n_rows else np.zeros(l_m.shape[1], bool)
        return cls(grouped(q_rad), grouped(l_m), grouped(f_n), grouped(np.asarray(l_cmd_m, float)),
                   grouped(np.asarray(f_cmd_n, float)), rows, has_f, list(joints), list(muscles),
                   None if t_s is None else grouped(np.asarray(t_s, float)), labels)

    def flat(self) -> dict:
        """The file's columns (real rows only, case by case) for ``write_sensor_log``."""
        c, r = np.nonzero(self.rows)
        columns = {"case": self.cases[c].astype(np.float64)}
        if self.t_s is not None:
            columns["t"] = self.t_s[c, r]
        columns.update({f"q_{j}": self.q_rad[c, r, i] for i, j in enumerate(self.joints)})
        columns.update({f"l_{m}": self.l_m[c, r, i] for i, m in enumerate(self.muscles)})
        columns.update({f"f_{m}": self.f_n[c, r, i] for i, m in enumerate(self.muscles) if self.has_f[i]})
        columns.update({f"l_cmd_{m}": self.l_cmd_m[c, r, i] for i, m in enumerate(self.muscles)})
        columns.update({f"f_cmd_{m}": self.f_cmd_n[c, r, i] for i, m in enumerate(self.muscles)})
        return columns


def _rank_within(index: np.ndarray, n_groups: int) -> np.ndarray:
    """Each element's position among the earlier elements of its group (file order kept within a log)."""
    order = np.argsort(index, kind="stable")
    starts = np.zeros(n_groups + 1, np.int64)
    np.add.at(starts, index + 1, 1)
    starts = np.cumsum(starts)
    rank = np.empty(len(index), np.int64)
    rank[order] = np.arange(len(index)) - starts[index[order]]
    return rank


def write_sensor_log(path: str, log: SensorLog, extra: Optional[dict] = None) -> None:
    """Write ``log`` as the file ``read_sensor_log`` reads (CSV for ``*.csv``, else NPZ; atomic); ``extra``: columns
    of the user's own, one value per row, written with the ``x_`` prefix."""
    write_columns(path, {**log.flat(), **{f"{EXTRA}{k}": np.asarray(v, float) for k, v in (extra or {}).items()}})


def read_sensor_log(path: str, joints: Sequence[str], muscles: Sequence[str]) -> SensorLog:
    """Read a sensor log for a robot with these joints and muscles (module docstring); refuse a malformed one."""
    columns, _ = read_columns(path, "sensor log")
    _column_names(path, columns, list(joints), list(muscles))
    n_rows = len(next(iter(columns.values()))) if columns else 0
    if n_rows == 0:
        raise BodySchemaInputError(f"{path} has a header but no rows")
    for name, values in columns.items():
        if name.startswith(EXTRA):
            continue
        bad = np.flatnonzero(~np.isfinite(values))
        if bad.size:
            raise BodySchemaInputError(f"{path}: column {name!r} is NaN/inf in row {int(bad[0]) + 1} (rows counted "
                                       f"from 1; {bad.size} row(s) affected): a log holds finite readings only")
    stack = lambda prefix, keys: np.stack([columns[f"{prefix}{k}"] for k in keys], 1)  # noqa: E731
    f_n = np.stack([columns.get(f"f_{m}", np.full(n_rows, np.nan)) for m in muscles], 1)
    case = columns.get("case")
    if case is not None and np.any(case != np.round(case)):
        row = int(np.flatnonzero(case != np.round(case))[0]) + 1
        raise BodySchemaInputError(f"{path}: column 'case' holds {case[row - 1]!r} in row {row}; a case is an integer")
    return SensorLog.from_rows(joints, muscles, stack("q_", joints), stack("l_", muscles), stack("l_cmd_", muscles),
                               stack("f_cmd_", muscles), f_n, case, columns.get("t"))


def _column_names(path, columns: dict, joints: list, muscles: list) -> None:
    """Refuse a column that names nothing of the robot (with a "did you mean") and a missing required column."""
    for name in columns:
        if name in ("t", "case") or name.startswith(EXTRA):
            continue
        prefix = next((p for p in SENT + READ if name.startswith(p)), None)
        known = joints if prefix == "q_" else muscles
        if prefix is None or name[len(prefix):] not in known:
            hint = _did_you_mean(name, prefix, known)
            raise BodySchemaInputError(f"{path}: column {name!r} is not a sensor log column{hint}; columns: q_<joint>, "
                                       f"l_<muscle>, f_<muscle> (optional), l_cmd_<muscle>, f_cmd_<muscle>, t, case, "
                                       f"x_<yours>")
    required = [f"q_{j}" for j in joints] + [f"{p}{m}" for p in ("l_", "l_cmd_", "f_cmd_") for m in muscles]
    missing = [name for name in required if name not in columns]
    if missing:
        raise BodySchemaInputError(f"{path}: missing column(s) {missing[:6]}{' ...' if len(missing) > 6 else ''} "
                                   f"({len(missing)} in all): a sensor log needs q_<joint> for every joint and "
                                   f"l_<muscle>, l_cmd_<muscle>, f_cmd_<muscle> for every muscle")


def check_log_names(log: SensorLog, robot) -> None:
    """Refuse a log whose joints or muscles are not the robot's, in its order."""
    for what, have, need in (("joints", log.joints, robot.joint_names), ("muscles", log.muscles, robot.muscle_names)):
        if list(have) != list(need):
            raise BodySchemaInputError(f"the log's {what} {list(have)[:8]} are not the robot's {list(need)[:8]} (same "
                                       f"names, same order; read the file with read_sensor_log(path, joints, muscles))")


def _did_you_mean(name: str, prefix: Optional[str], known: list) -> str:
    if prefix is None:
        return ""
    close = difflib.get_close_matches(name[len(prefix):], known, n=1)
    return f" (unknown name; did you mean {prefix + close[0]!r}?)" if close else " (unknown name)"
