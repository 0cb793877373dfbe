"""Column files (CSV or NPZ, one column per joint or muscle): read and checked, each bad line or array named.

Light (numpy and the standard library only), so that a tool can check its input file before it imports torch,
Lightning or MuJoCo (``data.recorded`` reads recorded data with these; ``tools/static_opt.py`` its postures).
"""
from __future__ import annotations

import csv
import os
from typing import Mapping, Optional

import numpy as np

from .errors import BodySchemaInputError
from .npz import atomic_write_bytes, load_npz, save_npz

UNITS = "SI"  # the one accepted units flag: rad (or m for slide joints), m, N


def read_csv_columns(path: str) -> tuple[dict, dict, Optional[str]]:
    """``(columns, ranges, units)`` of a CSV: a header of column names, one row per sample (empty cells NaN), ``#``
    comment lines, ``# units: SI`` and ``# range <column> <lo> <hi>`` directives."""
    ranges, units, header, rows = {}, None, None, []
    with open(path, newline="", encoding="utf-8-sig") as fh:  # -sig: a byte-order mark (Excel's "CSV UTF-8")
        for line_no, line in enumerate(fh, start=1):
            text = line.strip()
            if not text:
                continue
            if text.startswith("#"):
                units = _csv_directive(path, line_no, text[1:].strip(), ranges, units)
                continue
            fields = next(csv.reader([text]))
            if header is None:
                header = [name.strip() for name in fields]
                repeated = sorted({name for name in header if header.count(name) > 1})
                if repeated:
                    raise BodySchemaInputError(f"{path}, line {line_no}: columns {repeated} appear more than once; "
                                               "each column must be named once")
                continue
            if len(fields) != len(header):
                raise BodySchemaInputError(f"{path}, line {line_no}: {len(fields)} fields, but the header has "
                                           f"{len(header)} columns")
            rows.append((line_no, fields))
    if header is None:
        raise BodySchemaInputError(f"{path} is empty: expected a header line of q_<joint>, l_<muscle>, "
                                   "f_<muscle> columns and one row per posture")
    values = _numbers(path, header, rows)
    return {name: values[:, i] for i, name in enumerate(header)}, ranges, units


def _csv_directive(path, line_no, text, ranges, units):
    """Parse ``units: SI`` and ``range <column> <lo> <hi>``; other comment lines are free text."""
    if text.lower().startswith("units"):
        return text.split(":", 1)[-1].strip() if ":" in text else text[5:].strip()
    if text.startswith("range "):
        parts = text.split()
        try:
            ranges[parts[1]] = (float(parts[2]), float(parts[3]))
        except (IndexError, ValueError):
            raise BodySchemaInputError(f"{path}, line {line_no}: {text!r} is not 'range <column> <lo> <hi>' "
                                       "with two numbers") from None
    return units


def _numbers(path, header, rows) -> np.ndarray:
    """The rows as floats (empty cells are NaN); a cell that is not a number is named with its line."""
    if not rows:
        return np.empty((0, len(header)))
    cells = np.array([fields for _, fields in rows], dtype=str)
    cells = np.where(np.char.strip(cells) == "", "nan", cells)
    try:
        return cells.astype(np.float64)
    except ValueError:
        pass
    for (line_no, fields), row in zip(rows, cells):  # error path only: find the first bad cell
        for name, cell in zip(header, row):
            try:
                float(cell)
            except ValueError:
                raise BodySchemaInputError(f"{path}, line {line_no}, column {name!r}: {cell.strip()!r} is not a "
                                           "number (give numbers in SI units; empty or nan marks a missing value)"
                                           ) from None
    raise AssertionError("unreachable: a cell failed to convert but none fails alone")


def read_npz_columns(path: str) -> tuple[dict, dict, Optional[str]]:
    """``(columns, ranges, units)`` of an NPZ: one 1-D numeric array per column (in the order of its ``columns``
    array, if any), ``range_<column>`` ``[lo, hi]`` arrays, a ``units`` string; ``meta_*`` arrays skipped."""
    arrays = load_npz(path)
    columns, ranges, units = {}, {}, None
    for name, value in _in_column_order(path, arrays).items():
        if name.startswith("meta_") or name == "columns":
            continue
        if name == "units":
            units = str(value)
        elif name.startswith("range_"):
            value = np.asarray(value)
            if value.shape != (2,) or value.dtype.kind not in "fiu":
                raise BodySchemaInputError(f"{path}: array {name!r} must be [lo, hi], two numbers; it has shape "
                                           f"{value.shape}, dtype {value.dtype}")
            ranges[name[len("range_"):]] = (float(value[0]), float(value[1]))
        else:
            if value.ndim != 1 or value.dtype.kind not in "fiu":
                raise BodySchemaInputError(f"{path}: column {name!r} must be a 1-D array of numbers; it has shape "
                                           f"{value.shape}, dtype {value.dtype}")
            columns[name] = value.astype(np.float64)
    if not columns:
        raise BodySchemaInputError(f"{path} holds no columns: expected arrays q_<joint>, l_<muscle>, f_<muscle>")
    lengths = {name: len(v) for name, v in columns.items()}
    if len(set(lengths.values())) > 1:
        raise BodySchemaInputError(f"{path}: columns have different lengths {lengths}")
    return columns, ranges, units


def _in_column_order(path, arrays: dict) -> dict:
    """The arrays with the columns first, in the order the ``columns`` array names (joint and muscle order)."""
    if "columns" not in arrays:
        return arrays
    order = [str(name) for name in np.atleast_1d(arrays["columns"])]
    missing = [name for name in order if name not in arrays]
    if missing:
        raise BodySchemaInputError(f"{path}: missing column {missing} (named in its 'columns' array)")
    return {**{name: arrays[name] for name in order}, **arrays}


def read_columns(path: str, what: str) -> tuple[dict, dict]:
    """``(columns, ranges)`` of a CSV or NPZ table in this layout (header, ``# range``, ``# units: SI``),
    every row as read; a missing file or a units flag other than SI is refused (``what`` names the file's role)."""
    if not os.path.isfile(path):
        raise BodySchemaInputError(f"{what} {path!r} does not exist")
    if path.endswith(".npz"):
        columns, ranges, units = read_npz_columns(path)
    else:
        columns, ranges, units = read_csv_columns(path)
    if units is not None and units != UNITS:
        raise BodySchemaInputError(f"{path}: units flag {units!r} is not supported; the file must be in SI units "
                                   f"(rad, m, N) and say so with units {UNITS!r} (or give no units flag)")
    return columns, ranges


def write_columns(path: str, columns: Mapping[str, np.ndarray], ranges: Optional[Mapping] = None,
                  meta: Optional[dict] = None) -> None:
    """Write 1-D ``columns`` in this layout: CSV for ``*.csv`` (17 significant digits: reads back exactly),
    else NPZ; deterministic bytes, written atomically. ``meta``: NPZ ``meta_*`` arrays / CSV comment lines."""
    ranges, meta = dict(ranges or {}), dict(meta or {})
    if not path.endswith(".csv"):
        save_npz(path, units=np.array(UNITS), columns=np.array(list(columns)), **columns,
                 **{f"range_{name}": np.asarray(lim, np.float64) for name, lim in ranges.items()},
                 **{f"meta_{name}": np.asarray(value) for name, value in meta.items()})
        return
    lines = [f"# units: {UNITS}"]
    lines += [f"# range {name} {float(lo)!r} {float(hi)!r}" for name, (lo, hi) in ranges.items()]
    lines += [f"# {name}: {' '.join(str(value).split())}" for name, value in meta.items() if name != "model_xml"]
    lines.append(",".join(columns))
    table = np.stack([np.asarray(v, np.float64) for v in columns.values()], axis=1)
    lines += [",".join(f"{v:.17g}" for v in row) for row in table]
    atomic_write_bytes(path, ("\n".join(lines) + "\n").encode())
