"""Fault cases for the evaluation (paper section IV-B): CUT, FIX and BOTH, seeded and saved as .npz.

Two protocols draw them (``PROTOCOLS``): ``paper`` (``make_fault_cases``, the default, below) and
``binding`` (``make_binding_cases``: every case has a physical solution and the healthy command breaks
every fault, so adaptation always has work to do; see its docstring).

A case is a target posture ``q_ref`` plus the faulty muscles: ruptured (``cut``, f_i = 0) and jammed
(``fix``, l_motor_j <= l_fixed_j). Paper: 40 cases per condition; CUT = 2 ruptured, FIX = 2 jammed,
BOTH = 1 + 1, out of 6 muscles; faulty muscles distinct and uniformly drawn. ``l_fixed`` is the motor
length "at the moment of jamming": we take the motor lengths of a random *other* posture of the same
pool, i.e. the arm was elsewhere when the motor jammed and must now reach q_ref.

Beyond the paper, two optional arrays: ``f_max`` (B, M) a weakened muscle's own tension limit [N]
(NaN where not weakened) and ``l_band`` (B, M, 2) a motor that can move only inside [lo, hi] [m] (NaN
where free). Files without them load with both None, and cases without them save the five arrays only.

Files written by other programs often fill "no fault here" with 0 instead of NaN, so a value is
ignored (set to NaN) where the muscle has no such fault: ``l_fixed`` where ``fix`` is False, ``f_max`` on
a cut muscle, and, when the file carries the optional bool masks ``weak`` / ``band`` (B, M), ``f_max`` /
``l_band`` where the mask is False. Without those masks a finite ``f_max`` / ``l_band`` itself marks the
weakened / banded muscle (NaN elsewhere). A jammed muscle without a finite ``l_fixed`` stays an error.
"""
from __future__ import annotations

import os
from collections import Counter
from dataclasses import dataclass

import numpy as np

from ..errors import BodySchemaInputError
from ..faults.faults import Faults
from ..npz import load_npz, save_npz
from ..sim.model import MusculoskeletalModel
from ..sim.spring import SpringParams
from .feasibility import feasible_tensions

CONDITIONS = ("CUT", "FIX", "BOTH", "NONE", "WEAK", "BAND", "MIXED")  # NONE: healthy, for checks and baselines
# WEAK / BAND: only weakened / only length-banded muscles; MIXED: any other mix with those (see ``condition_of``)
DEFAULT_N_CUT = {"CUT": 2, "FIX": 0, "BOTH": 1}
DEFAULT_N_FIX = {"CUT": 0, "FIX": 2, "BOTH": 1}
_ARRAYS = ("q_ref", "cut", "fix", "l_fixed", "cond")
_OPTIONAL = ("f_max", "l_band")  # new faults (not in the paper): saved only when present
_MASKS = {"weak": "f_max", "band": "l_band"}  # optional bool masks a file may carry: which muscles the values mean


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
        _check_shapes(self, None, None)
        _check_dtypes(self)
        _ignore_values_without_fault(self)
        _check_values(self)

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
    out = {k: arrays[k] for k in _ARRAYS + _OPTIONAL if k in arrays}
    for mask_name, values_name in _MASKS.items():
        if mask_name in arrays and values_name in out:
            mask, values = arrays[mask_name], out[values_name]
            _require(mask.dtype == bool and mask.shape == values.shape[:2],
                     f"case file {path}: {mask_name} must be a bool (B, M) mask matching {values_name} {values.shape}; got "
                     f"{mask.dtype} {mask.shape}")
            out[values_name] = np.where(mask.reshape(mask.shape + (1,) * (values.ndim - 2)), values, np.nan)
    return out


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
    unknown = sorted(set(c.cond.tolist()) - set(CONDITIONS))
    _require(not unknown, f"cond has unknown conditions {unknown}; allowed: {list(CONDITIONS)}")


def _ignore_values_without_fault(c: FaultCases):
    """NaN where a muscle has no such fault (module docstring), whatever another program wrote there."""
    c.l_fixed = np.where(c.fix, c.l_fixed, np.nan)
    if c.f_max is not None:
        c.f_max = np.where(c.cut, np.nan, c.f_max)


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
    _require(n_cut < n_muscles and n_cut + n_fix <= n_muscles,
             f"{n_cut} cut + {n_fix} jammed muscles do not fit a robot of {n_muscles} muscles (at least one must be "
             f"left uncut to hold the arm)")
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


# ---------------------------------------------------------------------------- the binding protocol
PROTOCOLS = ("paper", "binding")
BINDING_CONDITIONS = ("CUT", "FIX", "BOTH", "WEAK", "BAND")
# condition -> faulty muscles per case: (cut, jammed, weakened, banded); distinct muscles, uniform
BINDING_FAULTS = {"CUT": (2, 0, 0, 0), "FIX": (0, 2, 0, 0), "BOTH": (1, 1, 0, 0), "WEAK": (0, 0, 1, 0),
                  "BAND": (0, 0, 0, 1)}
MIN_PULL_N = 0.5  # a cut / weakened muscle binds when its healthy tension exceeds zero / its new limit by this
MIN_PAYOUT_M = 0.5e-3  # a jammed / banded motor binds when its healthy length is this far outside what it can reach
BAND_WIDTH_M = (0.5e-3, 4e-3)  # width of a drawn length band, uniform in this range
REJECT_REASONS = ("cut muscle slack", "no jam window", "weak muscle slack", "no band window", "infeasible")


@dataclass
class HealthyPool:
    """The healthy samples binding cases are drawn from (a dataset's test split): q (P, N) [rad],
    l_motor (P, M) [m], f (P, M) [N]; row p is the healthy command at posture q[p]."""

    q: np.ndarray
    l_motor: np.ndarray
    f: np.ndarray

    def __post_init__(self):
        self.q, self.l_motor, self.f = (np.asarray(a, float) for a in (self.q, self.l_motor, self.f))
        _require(self.q.ndim == 2 and self.l_motor.ndim == 2 and self.l_motor.shape == self.f.shape
                 and len(self.q) == len(self.f) >= 1,
                 f"pool q {self.q.shape}, l_motor {self.l_motor.shape}, f {self.f.shape} must be (P, N), (P, M), "
                 f"(P, M) with P >= 1")


def _fault_roles(rng, batch, n_muscles, counts):
    """(B, M) masks cut, fix, weak, band: sum(counts) distinct muscles per case, uniformly drawn."""
    _require(sum(counts) <= n_muscles, f"{sum(counts)} faulty muscles per case > {n_muscles} muscles")
    order = np.argsort(rng.random((batch, n_muscles)), axis=1)
    rank = np.argsort(order, axis=1)
    edges = np.cumsum((0,) + tuple(counts))
    return tuple((rank >= lo) & (rank < hi) for lo, hi in zip(edges[:-1], edges[1:]))


def _draw_binding(rng, model, pool: HealthyPool, counts, batch: int, spring: SpringParams):
    """``batch`` candidate cases of one condition, every fault drawn inside its binding window.

    Returns (FaultCases-ready arrays, reason (B,) str: "" for a candidate whose every fault binds, else
    the first broken rule of ``REJECT_REASONS``). A fixed number of random numbers per call, whatever
    the outcome, so the draw is reproducible.

    Windows, with l_h, f_h the healthy command and l_tight = l_geo(q_ref) - delta(f_max) the shortest motor
    length at which the muscle's spring stays within f_max (no command can be shorter):
    * cut: f_h > MIN_PULL_N (the cut muscle was pulling);
    * jam: l_fixed uniform in [l_tight, l_h - MIN_PAYOUT_M] (the motor must pay out >= 0.5 mm);
    * weak: f_max' uniform in [0, f_h - MIN_PULL_N];
    * band: below the healthy length (hi uniform in [l_tight, l_h - MIN_PAYOUT_M]) or, half of the time when
      the muscle pulls, above it (lo uniform in [l_h + MIN_PAYOUT_M, l_geo], up to where the wire goes slack);
      width uniform in ``BAND_WIDTH_M``.
    """
    n_muscles = pool.l_motor.shape[1]
    pick = rng.integers(0, len(pool.q), size=batch)
    cut, fix, weak, band = _fault_roles(rng, batch, n_muscles, counts)
    u_where, u_width, u_side = (rng.random((batch, n_muscles)) for _ in range(3))
    q_ref, l_h, f_h = pool.q[pick], pool.l_motor[pick], pool.f[pick]
    l_geo = model.kinematics(q_ref)[0]
    l_tight = l_geo - spring.delta_max_m
    below_top = l_h - MIN_PAYOUT_M  # the longest motor length that still makes the healthy one pay out
    below_room, above_room = below_top - l_tight, np.maximum(0.0, l_geo - l_h - MIN_PAYOUT_M)
    pulls = f_h > MIN_PULL_N
    l_fixed = np.where(fix, l_tight + u_where * np.maximum(below_room, 0.0), np.nan)
    f_max = np.where(weak, u_where * np.maximum(f_h - MIN_PULL_N, 0.0), np.nan)
    above = (u_side < 0.5) & pulls | (below_room <= 0)
    width = BAND_WIDTH_M[0] + u_width * (BAND_WIDTH_M[1] - BAND_WIDTH_M[0])
    hi_below = l_tight + u_where * np.maximum(below_room, 0.0)
    lo_above = l_h + MIN_PAYOUT_M + u_where * above_room
    lo = np.where(above, lo_above, hi_below - width)
    l_band = np.where(band[..., None], np.stack([lo, np.where(above, lo_above + width, hi_below)], -1), np.nan)
    broken = {"cut muscle slack": (cut & ~pulls).any(1), "no jam window": (fix & (below_room <= 0)).any(1),
              "weak muscle slack": (weak & ~pulls).any(1),
              "no band window": (band & above & ~pulls).any(1)}
    reason = np.full(batch, "", dtype="<U20")
    for name in reversed(list(broken)):  # the first broken rule wins
        reason[broken[name]] = name
    return dict(q_ref=q_ref, cut=cut, fix=fix, l_fixed=l_fixed, f_max=f_max, l_band=l_band), reason


def _binding_condition(rng, model, pool, cond, n, spring, max_draws):
    """(arrays of n accepted cases, Counter of rejections): draw, keep the binding ones, ask the feasibility
    QP about those in one batch, repeat until n are accepted."""
    kept, rejected, drawn = [], Counter(), 0
    while sum(len(k["q_ref"]) for k in kept) < n:
        missing = n - sum(len(k["q_ref"]) for k in kept)
        batch = max(2 * missing, 32)
        if drawn + batch > max_draws:
            raise BodySchemaInputError(
                f"binding protocol, {cond}: only {n - missing} of {n} cases after {drawn} draws (rejected: "
                f"{dict(rejected)}); this robot's healthy samples rarely allow a binding, feasible {cond} case")
        arrays, reason = _draw_binding(rng, model, pool, BINDING_FAULTS[cond], batch, spring)
        drawn += batch
        rejected.update(reason[reason != ""].tolist())
        binds = np.flatnonzero(reason == "")
        sub = {k: v[binds] for k, v in arrays.items()}
        faults = Faults(sub["cut"], sub["fix"], sub["l_fixed"], sub["f_max"], sub["l_band"])
        feasible = feasible_tensions(model, sub["q_ref"], faults, spring)[0] if binds.size else np.zeros(0, bool)
        rejected["infeasible"] += int((~feasible).sum())
        kept.append({k: v[feasible][:missing] for k, v in sub.items()})
    return {k: np.concatenate([part[k] for part in kept]) for k in kept[0]}, rejected


def make_binding_cases(model: MusculoskeletalModel, pool: HealthyPool, n_per_condition: int = 100, seed: int = 0,
                       spring: SpringParams = SpringParams(), conditions=BINDING_CONDITIONS,
                       max_draws_per_case: int = 200) -> tuple[FaultCases, dict]:
    """Seeded binding fault cases: every case has a physical solution and its healthy command breaks every fault.

    Conditions (``BINDING_FAULTS``): CUT 2 cut, FIX 2 jammed, BOTH 1 + 1, WEAK 1 weakened, BAND 1 banded muscle,
    distinct and uniform over the muscles; ``n_per_condition`` cases each, postures drawn with replacement
    from ``pool`` (the test split; "healthy command" = the pool's (l_motor, f) at that posture). A case is kept
    when (1) the healthy command breaks every fault by a margin (a cut muscle pulled > 0.5 N; a jammed motor
    must pay out >= 0.5 mm, l_fixed <= l_h - 0.5 mm; a weakened muscle's healthy tension exceeds its new limit
    by > 0.5 N; a banded motor sits >= 0.5 mm outside its band), the faults being drawn inside those windows
    (``_draw_binding``), and (2) the feasibility QP (``feasibility.feasible_tensions``, physical reading: a
    jammed winch reels in but never pays out, its wire pulls) finds a command that realizes q_ref.

    Returns (cases, {condition: {reason: rejected draws}}). Same inputs and seed -> same arrays, bit for bit.
    """
    _require(int(n_per_condition) == n_per_condition and n_per_condition > 0,
             f"n_per_condition={n_per_condition!r} must be a positive integer")
    unknown = sorted(set(conditions) - set(BINDING_CONDITIONS))
    _require(not unknown, f"unknown binding conditions {unknown}; allowed: {list(BINDING_CONDITIONS)}")
    _require(pool.l_motor.shape[1] == model.n_muscles and pool.q.shape[1] == model.n_joints,
             f"pool has {pool.q.shape[1]} joints and {pool.l_motor.shape[1]} muscles; the model has "
             f"{model.n_joints} and {model.n_muscles}")
    rng = np.random.default_rng(seed)
    parts, rejections = [], {}
    for cond in conditions:
        arrays, rejected = _binding_condition(rng, model, pool, cond, int(n_per_condition), spring,
                                              max_draws_per_case * int(n_per_condition))
        parts.append(arrays)
        rejections[cond] = {r: rejected[r] for r in REJECT_REASONS if rejected[r]}
    merged = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    cond = np.repeat(np.array(list(conditions), dtype="<U5"), int(n_per_condition))
    optional = {"f_max": merged["f_max"] if "WEAK" in conditions else None,
                "l_band": merged["l_band"] if "BAND" in conditions else None}
    cases = FaultCases(merged["q_ref"], merged["cut"], merged["fix"], merged["l_fixed"], cond, **optional)
    return cases, rejections
