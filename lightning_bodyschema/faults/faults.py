"""``Faults``: which muscles are cut or jammed in each case of a batch, validated against the model."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np
import torch

from ..errors import BodySchemaInputError
from .constraints import Jam, MaxTension, MinTension, Rupture


@dataclass
class Faults:
    """Per-case fault masks, SI units.

    cut (B, M) bool: ruptured muscles (f = 0). fix (B, M) bool: jammed motors (l_motor <= l_fixed).
    l_fixed_m (B, M): motor length when it jammed [m], NaN where not jammed.
    f_max_n (B, M) or None: per-case tension limit [N] (a weakened muscle), default the robot's f_max.
    """

    cut: np.ndarray
    fix: np.ndarray
    l_fixed_m: np.ndarray
    f_max_n: Optional[np.ndarray] = None

    def __len__(self):
        return len(self.cut)

    @classmethod
    def none(cls, n_cases: int, n_muscles: int) -> "Faults":
        """A healthy batch: no constraint but the tension bounds."""
        off = np.zeros((n_cases, n_muscles), bool)
        return cls(off, off.copy(), np.full((n_cases, n_muscles), np.nan))

    @classmethod
    def from_names(cls, muscle_names: Sequence[str], cut: Sequence[Sequence] = (), jam: Sequence[dict] = (),
                   n_cases: Optional[int] = None) -> "Faults":
        """Build from per-case lists: ``cut=[["shoulder_flexor"], [2]]``, ``jam=[{}, {"elbow_flexor": 0.151}]``.

        Muscles may be named or indexed; each list entry is one case.
        """
        n_cases = n_cases or max(len(cut), len(jam))
        faults = cls.none(n_cases, len(muscle_names))
        for b, muscles in enumerate(cut):
            faults.cut[b, [_muscle_index(m, muscle_names) for m in muscles]] = True
        for b, jammed in enumerate(jam):
            for m, l_fixed in jammed.items():
                faults.fix[b, _muscle_index(m, muscle_names)] = True
                faults.l_fixed_m[b, _muscle_index(m, muscle_names)] = l_fixed
        return faults.validate(len(muscle_names))

    def validate(self, n_muscles: int) -> "Faults":
        """Refuse inconsistent faults with a message naming the case and muscle."""
        self.cut, self.fix = np.asarray(self.cut, bool), np.asarray(self.fix, bool)
        self.l_fixed_m = np.asarray(self.l_fixed_m, float)
        for name in ("cut", "fix", "l_fixed_m"):
            shape = getattr(self, name).shape
            if shape != (len(self.cut), n_muscles):
                raise BodySchemaInputError(f"faults.{name} has shape {shape}; expected (B, {n_muscles})")
        _refuse_cases(self.cut & self.fix, "the same muscle is both cut and jammed")
        _refuse_cases(self.cut.all(axis=1)[:, None], "every muscle is cut: nothing can hold the arm")
        _refuse_cases(self.fix & ~np.isfinite(self.l_fixed_m), "a jammed muscle has a NaN/inf l_fixed")
        if self.f_max_n is not None:
            self.f_max_n = np.asarray(self.f_max_n, float)
            _refuse_cases(~np.isfinite(self.f_max_n) | (self.f_max_n < 0), "f_max_n is negative or not finite")
        return self

    def constraints(self, f_max_n, dtype=torch.float64, device=None) -> list:
        """The torch constraints of this batch (tension bounds included), for the adaptation loss."""
        as_t = lambda a: torch.as_tensor(a, dtype=dtype, device=device)  # noqa: E731
        cut = torch.as_tensor(self.cut, device=device)
        f_max = self.f_max_n if self.f_max_n is not None else np.broadcast_to(f_max_n, self.cut.shape).copy()
        healthy = ~cut
        return [Rupture(cut), Jam(torch.as_tensor(self.fix, device=device), as_t(self.l_fixed_m)),
                MinTension(healthy, as_t(np.zeros(self.cut.shape))), MaxTension(healthy, as_t(f_max))]


def _muscle_index(muscle, names) -> int:
    if isinstance(muscle, (int, np.integer)) and not isinstance(muscle, bool):
        if not 0 <= muscle < len(names):
            raise BodySchemaInputError(f"muscle index {muscle} is out of range 0..{len(names) - 1}")
        return int(muscle)
    if muscle not in names:
        raise BodySchemaInputError(f"unknown muscle {muscle!r}; the model's muscles are {list(names)}")
    return list(names).index(muscle)


def _refuse_cases(bad: np.ndarray, what: str):
    cases = np.flatnonzero(bad.any(axis=1))
    if cases.size:
        muscles = np.flatnonzero(bad[cases[0]])
        raise BodySchemaInputError(f"{what} (case {int(cases[0])}, muscle index {muscles.tolist()}; "
                                   f"{cases.size} case(s) affected)")
