"""Fault cases for the evaluation (paper section IV-B): CUT, FIX and BOTH, seeded and saved as .npz.

A case is a target posture ``q_ref`` plus the faulty muscles: ruptured (``cut``, f_i = 0) and jammed
(``fix``, l_motor_j <= l_fixed_j). Paper: 40 cases per condition; CUT = 2 ruptured, FIX = 2 jammed,
BOTH = 1 + 1, out of 6 muscles; faulty muscles distinct and uniformly drawn. ``l_fixed`` is the motor
length "at the moment of jamming": we take the motor lengths of a random *other* posture of the same
pool, i.e. the arm was elsewhere when the motor jammed and must now reach q_ref.

Beyond the paper, two optional arrays: ``f_max`` (B, M) a weakened muscle's own tension limit [N]
(NaN where not weakened) and ``l_band`` (B, M, 2) a motor that can move only inside [lo, hi] [m] (NaN
where free). Files without them load as before, and cases without them save the five arrays only.
"""
from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

from ..errors import BodySchemaInputError
from ..npz import load_npz, save_npz

CONDITIONS = ("CUT", "FIX", "BOTH", "NONE", "WEAK", "BAND", "MIXED")  # NONE: healthy, for checks and baselines
# WEAK / BAND: only weakened / only length-banded muscles; MIXED: any other mix with those (see ``condition_of``)
DEFAULT_N_CUT = {"CUT": 2, "FIX": 0, "BOTH": 1}
DEFAULT_N_FIX = {"CUT": 0, "FIX": 2, "BOTH": 1}
_ARRAYS = ("q_ref", "cut", "fix", "l_fixed", "cond")
_OPTIONAL = ("f_max", "l_band")  # new faults (not in the paper): saved only when present


@dataclass
class FaultCases:
    """A batch of B fault cases (arrays, SI units).

    q_ref (B, N) target postures [rad]; cut, fix (B, M) bool; l_fixed (B, M) motor length at jamming
    [m], NaN where not jammed; cond (B,) condition names (``CONDITIONS``).
    Optional: f_max (B, M) weakened muscle's tension limit [N], NaN where not weakened; l_band (B, M, 2)
    [lo, hi] motor-length band [m], NaN where the motor is free. None: no such fault in any case.
    """

    q_ref: np.ndarray
    cut: np.ndarray
    fix: np.ndarray
    l_fixed: np.ndarray
    cond: np.ndarray
    f_max: np.ndarray | None = None
    l_band: np.ndarray | None = None

    def __post_init__(self):
        for name in _ARRAYS + _OPTIONAL:  # accept lists; dtypes are checked, not coerced
            if getattr(self, name) is not None:
                setattr(self, name, np.asarray(getattr(self, name)))
        validate_cases(self)

    @property
    def weak(self) -> np.ndarray:
        """(B, M) bool: weakened muscles (finite ``f_max``)."""
        return self.faults.weak

    @property
    def band(self) -> np.ndarray:
        """(B, M) bool: length-banded motors."""
        return self.faults.band

    def __len__(self) -> int:
        return self.q_ref.shape[0]

    def take(self, idx) -> "FaultCases":
        """The sub-batch ``idx`` (indices or a (B,) bool mask)."""
        optional = {k: getattr(self, k)[idx] for k in _OPTIONAL if getattr(self, k) is not None}
        return FaultCases(*(getattr(self, k)[idx] for k in _ARRAYS), **optional)

    @property
    def faults(self):
        """The fault masks as ``faults.Faults``, what ``BodySchema.adapt`` takes."""
        from ..faults import Faults

        return Faults(self.cut, self.fix, self.l_fixed, self.f_max, self.l_band)

    def save(self, path) -> None:
        """Write the five arrays (and f_max / l_band if present) to ``path`` (.npz): atomic, byte-identical
        for identical cases."""
        save_npz(os.fspath(path), **self.arrays())

    def arrays(self) -> dict:
        """{name: array}: the five case arrays, plus f_max / l_band when present."""
        return {k: getattr(self, k) for k in _ARRAYS + _OPTIONAL if getattr(self, k) is not None}

    @classmethod
    def load(cls, path, n_joints: int | None = None, n_muscles: int | None = None) -> "FaultCases":
        """Read and validate a case file; optionally check N and M against a model."""
        arrays = _read_npz(os.fspath(path))
        try:
            cases = cls(**arrays)
            validate_cases(cases, n_joints, n_muscles)
        except BodySchemaInputError as err:
            raise BodySchemaInputError(f"case file {path}: {err}") from None
        return cases


def _read_npz(path: str) -> dict:
    """The case arrays of an .npz file (f_max / l_band if present), refusing pickles, missing files and arrays."""
    try:
        arrays = load_npz(path, required=_ARRAYS)
    except BodySchemaInputError as err:
        raise BodySchemaInputError(f"case file: {err}; need arrays {list(_ARRAYS)}") from None
    return {k: arrays[k] for k in _ARRAYS + _OPTIONAL if k in arrays}


# ---------------------------------------------------------------------------- validation
def _require(ok: bool, message: str):
    if not ok:
        raise BodySchemaInputError(message)


def _check_shapes(c: FaultCases, n_joints, n_muscles):
    _require(c.q_ref.ndim == 2, f"q_ref must be 2-D (B, N); got shape {c.q_ref.shape}")
    widths = [a.shape[1] for a in (c.cut, c.fix, c.l_fixed) if a.ndim == 2]
    _require(bool(widths), "cut, fix and l_fixed must be 2-D (B, M)")
    # M: the model's, else the width most of the three (B, M) arrays agree on, so the odd one is named
    batch, n_m = c.q_ref.shape[0], n_muscles or max(widths, key=widths.count)
    for name, shape in (("cut", (batch, n_m)), ("fix", (batch, n_m)), ("l_fixed", (batch, n_m)),
                        ("cond", (batch,))):
        got = getattr(c, name).shape
        _require(got == shape, f"{name} has shape {got}; expected {shape} (B = {batch} rows of q_ref, "
                               f"M = {n_m} muscles)")
    for name, tail in (("f_max", ()), ("l_band", (2,))):
        got = None if getattr(c, name) is None else getattr(c, name).shape
        _require(got is None or got == (batch, n_m) + tail,
                 f"{name} has shape {got}; expected {(batch, n_m) + tail} (B = {batch}, M = {n_m})")
    _require(n_joints is None or c.q_ref.shape[1] == n_joints,
             f"q_ref has {c.q_ref.shape[1]} joints; the model has {n_joints}")


def _check_dtypes(c: FaultCases):
    for name in ("q_ref", "l_fixed") + tuple(k for k in _OPTIONAL if getattr(c, k) is not None):
        _require(np.issubdtype(getattr(c, name).dtype, np.floating),
                 f"{name} must be a float array; got dtype {getattr(c, name).dtype}")
    for name in ("cut", "fix"):
        _require(getattr(c, name).dtype == bool, f"{name} must be a bool array; got dtype {getattr(c, name).dtype}")
    _require(c.cond.dtype.kind == "U", f"cond must be a string array; got dtype {c.cond.dtype}")


def _check_values(c: FaultCases):
    _require(bool(np.all(np.isfinite(c.q_ref))), "q_ref contains NaN or inf")
    # cut/fix overlap, every muscle cut, NaN l_fixed of a jammed muscle, bad f_max / band
    c.faults.validate(c.cut.shape[1])
    _require(bool(np.all(np.isnan(c.l_fixed[~c.fix]))), "l_fixed must be NaN where the muscle is not jammed")
    unknown = sorted(set(c.cond.tolist()) - set(CONDITIONS))
    _require(not unknown, f"cond has unknown conditions {unknown}; allowed: {list(CONDITIONS)}")


def validate_cases(cases: FaultCases, n_joints: int | None = None, n_muscles: int | None = None):
    """Raise BodySchemaInputError naming the bad array if shapes, dtypes or values are wrong."""
    _check_shapes(cases, n_joints, n_muscles)
    _check_dtypes(cases)
    _check_values(cases)


def condition_of(cut, fix, weak=None, band=None) -> np.ndarray:
    """(B,) condition labels from (B, M) fault masks: CUT / FIX / BOTH / NONE as in the paper, WEAK or
    BAND when only weakened or only banded muscles are faulty, MIXED for any other mix with those."""
    cut, fix = np.asarray(cut, bool).any(1), np.asarray(fix, bool).any(1)
    weak = np.zeros_like(cut) if weak is None else np.asarray(weak, bool).any(1)
    band = np.zeros_like(cut) if band is None else np.asarray(band, bool).any(1)
    paper = np.where(cut & fix, "BOTH", np.where(cut, "CUT", np.where(fix, "FIX", "NONE")))
    new = np.where(weak & ~band, "WEAK", np.where(band & ~weak, "BAND", "MIXED"))
    return np.where(weak | band, np.where(cut | fix, "MIXED", new), paper).astype("<U5")


# ---------------------------------------------------------------------------- generation
def _random_faults(rng, batch, n_muscles, n_cut, n_fix):
    """(B, M) cut / fix masks: n_cut + n_fix distinct muscles, uniform over muscles, per case."""
    order = np.argsort(rng.random((batch, n_muscles)), axis=1)  # a uniform random permutation per row
    rank = np.argsort(order, axis=1)  # position of muscle i in its row's permutation
    return rank < n_cut, (rank >= n_cut) & (rank < n_cut + n_fix)


def _other_index(rng, pool_idx, n_pool):
    """A uniformly random pool index different from each of ``pool_idx``."""
    other = rng.integers(0, n_pool - 1, size=pool_idx.shape)
    return other + (other >= pool_idx)  # skip the case's own posture


def _one_condition(rng, q_pool, l_motor_pool, n, n_cut, n_fix):
    n_pool, n_muscles = l_motor_pool.shape
    _require(n_cut + n_fix <= n_muscles, f"{n_cut} cut + {n_fix} jammed > {n_muscles} muscles")
    pick = rng.choice(n_pool, size=n, replace=n > n_pool)  # distinct postures while the pool allows
    cut, fix = _random_faults(rng, n, n_muscles, n_cut, n_fix)
    l_fixed = np.where(fix, l_motor_pool[_other_index(rng, pick, n_pool)], np.nan)
    return q_pool[pick], cut, fix, l_fixed


def make_fault_cases(q_pool, l_motor_pool, n_per_condition: int = 40, seed: int = 0,
                     n_cut: dict | None = None, n_fix: dict | None = None) -> FaultCases:
    """Seeded fault cases: ``n_per_condition`` per condition, conditions in the order of ``n_cut``.

    Args:
        q_pool (P, N) [rad], l_motor_pool (P, M) [m]: healthy samples to draw from (the test split).
        n_cut, n_fix: number of ruptured / jammed muscles per condition
            (default CUT 2+0, FIX 0+2, BOTH 1+1, as in the paper).

    Within a condition, postures are distinct while the pool is large enough; each jammed case takes
    l_fixed from one other pool posture (the same one for all its jammed muscles).
    """
    n_cut = dict(DEFAULT_N_CUT if n_cut is None else n_cut)
    n_fix = dict(DEFAULT_N_FIX if n_fix is None else n_fix)
    _require(set(n_cut) == set(n_fix), f"n_cut {sorted(n_cut)} and n_fix {sorted(n_fix)} name different conditions")
    q_pool, l_motor_pool = np.asarray(q_pool, float), np.asarray(l_motor_pool, float)
    _require(q_pool.ndim == 2 and l_motor_pool.ndim == 2 and len(q_pool) == len(l_motor_pool) >= 2,
             f"q_pool {q_pool.shape} and l_motor_pool {l_motor_pool.shape} must be (P, N), (P, M), P >= 2")
    _require(int(n_per_condition) == n_per_condition and n_per_condition > 0, "n_per_condition must be > 0")
    rng = np.random.default_rng(seed)
    parts = [_one_condition(rng, q_pool, l_motor_pool, n_per_condition, n_cut[c], n_fix[c]) for c in n_cut]
    cond = np.repeat(np.array(list(n_cut), dtype=str), n_per_condition)
    q_ref, cut, fix, l_fixed = (np.concatenate(a) for a in zip(*parts))
    return FaultCases(q_ref, cut, fix, l_fixed, cond)
