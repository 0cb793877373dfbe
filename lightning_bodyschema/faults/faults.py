"""``Faults``: which muscles are cut, jammed, weakened or length-banded in each case of a batch, validated
against the model."""
from __future__ import annotations

import functools
import sys
from dataclasses import dataclass
from typing import Mapping, Optional, Sequence

import numpy as np

from ..errors import BodySchemaInputError, did_you_mean


@dataclass
class Faults:
    """Per-case fault masks, SI units.

    cut (B, M) bool: ruptured muscles (f = 0). fix (B, M) bool: jammed motors (l_motor <= l_fixed).
    l_fixed_m (B, M): motor length when it jammed [m], NaN where not jammed.
    f_max_n (B, M) or None: per-case tension limit [N] of a weakened muscle (f <= f_max'); NaN (or None
    for the whole batch) means the robot's own f_max.
    l_band_m (B, M, 2) or None: [lo, hi] motor-length band [m] of a motor that can move only inside it
    (lo <= l_motor <= hi); NaN rows where the motor is free. A banded muscle cannot also be cut.
    """

    cut: np.ndarray
    fix: np.ndarray
    l_fixed_m: np.ndarray
    f_max_n: Optional[np.ndarray] = None
    l_band_m: Optional[np.ndarray] = None

    def __len__(self):
        return len(self.cut)

    @property
    def weak(self) -> np.ndarray:
        """(B, M) bool: muscles with their own tension limit ``f_max_n``."""
        return np.zeros(self.cut.shape, bool) if self.f_max_n is None else ~np.isnan(self.f_max_n)

    @property
    def band(self) -> np.ndarray:
        """(B, M) bool: motors confined to a length band ``l_band_m``."""
        return np.zeros(self.cut.shape, bool) if self.l_band_m is None else ~np.isnan(self.l_band_m).all(-1)

    def f_limit(self, robot_f_max_n) -> np.ndarray:
        """(B, M) tension limit [N]: ``f_max_n`` where weakened, else the robot's f_max (scalar or per muscle)."""
        robot = np.broadcast_to(np.asarray(robot_f_max_n, float), self.cut.shape)
        return robot.copy() if self.f_max_n is None else np.where(self.weak, self.f_max_n, robot)

    def take(self, idx) -> "Faults":
        """The sub-batch ``idx`` (indices or a (B,) bool mask)."""
        pick = lambda a: None if a is None else np.asarray(a)[idx]  # noqa: E731
        return Faults(pick(self.cut), pick(self.fix), pick(self.l_fixed_m), pick(self.f_max_n), pick(self.l_band_m))

    @classmethod
    def none(cls, n_cases: int, n_muscles: int) -> "Faults":
        """A healthy batch: no constraint but the tension bounds."""
        off = np.zeros((n_cases, n_muscles), bool)
        return cls(off, off.copy(), np.full((n_cases, n_muscles), np.nan))

    @classmethod
    def from_names(cls, muscle_names: Sequence[str], cut: Sequence[Sequence] = (), jam=(), weak=(), band=(),
                   n_cases: Optional[int] = None) -> "Faults":
        """Build from per-case lists: ``cut=[["shoulder_flexor"], [2]]``, ``jam=[{}, {"elbow_flexor": 0.151}]``.

        Muscles may be named or indexed; each list entry is one case. ``weak`` ({muscle: f_max' [N]}) and
        ``band`` ({muscle: [lo, hi] [m]}) work like ``jam``. ``jam``, ``weak`` and ``band`` may also be one
        dict, which then applies to every case: ``weak={"elbow_flexor": 60.0}``.
        """
        args = {"jam": jam, "weak": weak, "band": band}
        per_case = {name: [arg] if isinstance(arg, Mapping) else list(arg) for name, arg in args.items()}
        n_cases = n_cases or max(len(cut), *(len(v) for v in per_case.values()))
        for name, arg in args.items():
            if isinstance(arg, Mapping):  # one dict: the same fault in every case
                per_case[name] = per_case[name] * n_cases
            if len(per_case[name]) > n_cases:
                raise BodySchemaInputError(f"{name} has {len(per_case[name])} entries for {n_cases} cases")
        if len(cut) > n_cases:
            raise BodySchemaInputError(f"cut has {len(cut)} entries for {n_cases} cases")
        faults = cls.none(n_cases, len(muscle_names))
        for b, muscles in enumerate(cut):
            faults.cut[b, [muscle_index(m, muscle_names) for m in muscles]] = True
        for b, jammed in enumerate(per_case["jam"]):
            for m, l_fixed in jammed.items():
                faults.fix[b, muscle_index(m, muscle_names)] = True
                faults.l_fixed_m[b, muscle_index(m, muscle_names)] = _number(l_fixed, f"jam[{b}][{m!r}]")
        if any(per_case["weak"]):
            faults.f_max_n = np.full(faults.cut.shape, np.nan)
            for b, weakened in enumerate(per_case["weak"]):
                for m, f_max in weakened.items():
                    faults.f_max_n[b, muscle_index(m, muscle_names)] = _number(f_max, f"weak[{b}][{m!r}]")
        if any(per_case["band"]):
            faults.l_band_m = np.full(faults.cut.shape + (2,), np.nan)
            for b, banded in enumerate(per_case["band"]):
                for m, lo_hi in banded.items():
                    faults.l_band_m[b, muscle_index(m, muscle_names)] = _band(lo_hi, f"band[{b}][{m!r}]")
        return faults.validate(len(muscle_names))

    def validate(self, n_muscles: int, f_max_n=None) -> "Faults":
        """Refuse inconsistent faults with a message naming the case and muscle.

        f_max_n: the robot's healthy tension limit [N] (scalar or per muscle); when given, a weakened limit must lie
        below it (a weakening at or above the healthy strength is a mistake, not a fault).
        """
        batch = len(self.cut)
        for name, dtype, tail in (("cut", bool, ()), ("fix", bool, ()), ("l_fixed_m", float, ()),
                                  ("f_max_n", float, ()), ("l_band_m", float, (2,))):
            if getattr(self, name) is None:
                continue
            setattr(self, name, np.asarray(getattr(self, name), dtype))
            shape = getattr(self, name).shape
            if shape != (batch, n_muscles) + tail:
                expected = ", ".join(["B", str(n_muscles)] + [str(t) for t in tail])
                raise BodySchemaInputError(f"faults.{name} has shape {shape}; expected ({expected})")
        nan = np.full(self.cut.shape, np.nan)
        band = np.stack([nan, nan], -1) if self.l_band_m is None else self.l_band_m
        healthy = None if f_max_n is None else np.broadcast_to(np.asarray(f_max_n, float), self.cut.shape)
        with np.errstate(invalid="ignore"):  # NaN where a fault is off
            rules = fault_rules(self.cut, self.fix, self.l_fixed_m, nan if self.f_max_n is None else self.f_max_n,
                                band[..., 0], band[..., 1], healthy)
        if not functools.reduce(np.logical_or, (bad for _, bad in rules)).any():  # the usual case: no message
            return self
        for name, bad in rules:
            what = RULES[name]
            _refuse_cases(bad, what if name != "weak_not_below" else what.format(_shown(f_max_n)))
        return self

    def constraints(self, f_max_n) -> list:
        """The constraints of this batch (``faults.constraints``: intervals in SI units), tension bounds included and a
        weakened muscle's limit lowered; ``f_max_n`` is the robot's limit (scalar or per muscle)."""
        from .constraints import Jam, LengthBand, MaxTension, MinTension, Rupture

        healthy = ~self.cut
        out = [Rupture(self.cut), Jam(self.fix, self.l_fixed_m), MinTension(healthy, np.zeros(self.cut.shape)),
               MaxTension(healthy, self.f_limit(f_max_n))]
        if self.band.any():  # only when used: a fault-free batch runs exactly the paper's loss
            out.append(LengthBand(self.band, self.l_band_m[..., 0], self.l_band_m[..., 1]))
        return out


# the rules every fault set obeys: Faults.validate refuses a case that breaks one, the exported package answers
# bad_input (both ask ``fault_rules``)
RULES = {"cut_and_jammed": "the same muscle is both cut and jammed",
         "all_cut": "every muscle is cut: nothing can hold the arm",
         "jam_not_finite": "a jammed muscle has a NaN/inf l_fixed",
         "jam_not_positive": "a jammed motor length l_fixed is <= 0 m (a motor length is positive)",
         "weak_bad": "f_max_n of a weakened muscle is negative or inf",
         "weak_not_below": "a weakened f_max_n is at or above the healthy f_max {} N (a weakening lies below it)",
         "band_not_finite": "a length band has a NaN/inf bound",
         "band_crossed": "a length band has lo > hi",
         "band_not_positive": "a length band lies at or below 0 m (a motor length is positive)",
         "cut_and_banded": "the same muscle is both cut and length-banded"}


def fault_rules(cut, jam, l_fixed_m, f_weak_n, band_lo_m, band_hi_m, f_max_n=None) -> list:
    """``[(rule, (B, M) bool)]``: where each rule of ``RULES`` is broken, for numpy arrays or torch tensors alike
    (traceable). ``cut``, ``jam`` bool masks; ``l_fixed_m``, ``f_weak_n``, ``band_lo_m``, ``band_hi_m`` NaN where
    off; ``f_max_n``: the healthy limit (None: the weakening is not compared with it)."""
    xp = sys.modules["torch"] if type(cut).__module__.startswith("torch") else np
    weak, band = ~xp.isnan(f_weak_n), ~(xp.isnan(band_lo_m) & xp.isnan(band_hi_m))
    every = cut.all(1)[:, None]  # (B, 1)
    rules = [("cut_and_jammed", cut & jam), ("all_cut", every), ("jam_not_finite", jam & ~xp.isfinite(l_fixed_m)),
             ("jam_not_positive", jam & (l_fixed_m <= 0)), ("weak_bad", weak & (xp.isinf(f_weak_n) | (f_weak_n < 0)))]
    if f_max_n is not None:
        rules.append(("weak_not_below", weak & (f_weak_n >= f_max_n)))
    finite = xp.isfinite(band_lo_m) & xp.isfinite(band_hi_m)
    rules += [("band_not_finite", band & ~finite), ("band_crossed", band & (band_lo_m > band_hi_m)),
              ("band_not_positive", band & (band_hi_m <= 0)), ("cut_and_banded", band & cut)]
    return rules


def muscle_index(muscle, names) -> int:
    if isinstance(muscle, (int, np.integer)) and not isinstance(muscle, bool):
        if not 0 <= muscle < len(names):
            raise BodySchemaInputError(f"muscle index {muscle} is out of range 0..{len(names) - 1}")
        return int(muscle)
    if muscle not in names:
        raise BodySchemaInputError(f"unknown muscle {muscle!r}{did_you_mean(muscle, names)}; the model's muscles are "
                                   f"{list(names)}")
    return list(names).index(muscle)


def _number(value, where: str) -> float:
    try:
        number = float(value)
    except (TypeError, ValueError):
        number = np.nan
    if isinstance(value, bool) or not np.isfinite(number):
        raise BodySchemaInputError(f"{where} = {value!r}; need a finite number")
    return number


def _band(value, where: str) -> list:
    if isinstance(value, (str, bytes)) or np.ndim(value) != 1 or len(value) != 2:
        raise BodySchemaInputError(f"{where} = {value!r}; a band is [lo, hi] in metres")
    return [_number(v, where) for v in value]


def _shown(values) -> str:
    values = np.unique(np.asarray(values, float))
    return f"{values[0]:g}" if values.size == 1 else f"{values.min():g}..{values.max():g}"


def _refuse_cases(bad: np.ndarray, what: str):
    cases = np.flatnonzero(bad.any(axis=1))
    if cases.size:
        muscles = np.flatnonzero(bad[cases[0]])
        raise BodySchemaInputError(f"{what} (case {int(cases[0])}, muscle index {muscles.tolist()}; "
                                   f"{cases.size} case(s) affected)")
