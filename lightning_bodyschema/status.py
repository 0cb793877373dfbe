"""The one status vocabulary: why a row does or does not hold a command, as a name and an integer code.

Every result of the package (``AdaptationResult``, the solvers' ``Solution``, static optimization, the exported
package's ``status`` output, the CSV/NPZ/JSON files the tools write) uses these members. A member is a ``str``
(``Status.OK == "ok"``), so ``result.status == "ok"`` reads as it always has; ``.code`` is its integer, the same
in Python, in the files and in the C++ package (codes never change meaning; new members take new codes).

Only ``ok`` rows carry a command to send. Imports nothing from the package.
"""
from __future__ import annotations

from enum import Enum
from typing import Iterable

import numpy as np


class Status(str, Enum):
    """Why a row does (``OK``) or does not hold a command; ``code`` is the member's integer in every output."""

    OK = "ok"  # a command to send (checked, or the check turned off)
    NON_FINITE = "non_finite"  # the schema's raw output was NaN/inf
    OUT_OF_RANGE = "out_of_range"  # finite but absurd motor lengths (beyond the plausible range)
    FAULT_NOT_MET = "fault_not_met"  # the command breaks a fault bound (a cut, jam, band or weakened limit)
    BAD_INPUT = "bad_input"  # the row's input was NaN or outside the allowed range (exported package)
    INFEASIBLE = "infeasible"  # the true body cannot hold the posture under these faults
    INFEASIBLE_LEARNED = "infeasible_learned"  # the learned body cannot hold it (least-squares best effort)
    UNREACHABLE = "unreachable"  # a task-space target out of reach
    UNCHECKED = "unchecked"  # finite, but the asked-for physics check could not run (no model)
    NOT_CONVERGED = "not_converged"  # a solver stopped at its iteration cap without an answer it can vouch for
    ACTIVATION_ABOVE_ONE = "activation_above_one"  # static optimization: the tension needs more than full activation
    NO_FAULT = "no_fault"  # diagnosis: the log is what a healthy body reads, within the sensor noise
    IDENTIFIED = "identified"  # diagnosis: one explanation of the log (which muscles, which kind, their parameters)
    AMBIGUOUS = "ambiguous"  # diagnosis: two or more explanations fit the log within the sensor noise
    NOT_IDENTIFIABLE = "not_identifiable"  # diagnosis: the log is not a healthy body's, and no explanation fits it

    @property
    def code(self) -> int:
        return _CODES[self]

    @classmethod
    def from_code(cls, code: int) -> "Status":
        try:
            return _BY_CODE[int(code)]
        except KeyError:
            raise ValueError(f"unknown status code {code!r}; known: {sorted(_BY_CODE)}") from None

    def __str__(self) -> str:
        return self.value


# Each member's integer, written out: a contract of every file, exported package and the C++ examples. A code never
# changes meaning and is never reused; a new member takes the next free code (tests/status pins every pair).
_CODES = {Status.OK: 0, Status.NON_FINITE: 1, Status.OUT_OF_RANGE: 2, Status.FAULT_NOT_MET: 3, Status.BAD_INPUT: 4,
          Status.INFEASIBLE: 5, Status.INFEASIBLE_LEARNED: 6, Status.UNREACHABLE: 7, Status.UNCHECKED: 8,
          Status.NOT_CONVERGED: 9, Status.ACTIVATION_ABOVE_ONE: 10, Status.NO_FAULT: 11, Status.IDENTIFIED: 12,
          Status.AMBIGUOUS: 13, Status.NOT_IDENTIFIABLE: 14}
_BY_CODE = {code: member for member, code in _CODES.items()}
STATUS_CODES = {member.value: code for member, code in _CODES.items()}  # name -> code, for files and the package


_MEMBERS = np.array([_BY_CODE[code] for code in range(len(_BY_CODE))], dtype=object)  # code -> member


def status_array(values: Iterable, size: int | None = None) -> np.ndarray:
    """An object array of ``Status`` members from names, codes or members (no fixed width: nothing is cut); an
    integer array of codes is looked up in one indexing op (the hot path of every adapter)."""
    if size is not None and np.ndim(values) == 0:
        values = [values] * size
    if isinstance(values, np.ndarray) and values.dtype.kind in "iu":
        codes = values.ravel().astype(np.int64)
        bad = (codes < 0) | (codes >= len(_MEMBERS))
        if bad.any():
            raise ValueError(f"unknown status code {int(codes[bad][0])}; known: {sorted(_BY_CODE)}")
        return _MEMBERS[codes]
    return np.array([_member(v) for v in np.asarray(values, dtype=object).ravel()] or [], dtype=object)


def _member(value) -> Status:
    if isinstance(value, Status):
        return value
    if isinstance(value, (int, np.integer)):
        return Status.from_code(value)
    return Status(str(value))


def status_codes(values: Iterable) -> np.ndarray:
    """(B,) int32 codes of names, codes or members."""
    return np.array([_member(v).code for v in np.asarray(values, dtype=object).ravel()], dtype=np.int32)


def status_names(values: Iterable) -> np.ndarray:
    """(B,) str array of the names (numpy sizes it to the longest: nothing is cut), for files."""
    names = [_member(v).value for v in np.asarray(values, dtype=object).ravel()]
    return np.array(names, dtype=str)  # numpy sizes a str array to its longest element


__all__ = ["Status", "STATUS_CODES", "status_array", "status_codes", "status_names"]
