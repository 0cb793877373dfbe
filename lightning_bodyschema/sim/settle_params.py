"""The settle check's settings, outcome codes and result (``sim.settle``); numpy only."""
from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np

from ..errors import BodySchemaInputError

MODES = ("length", "tension")
JAM_MODES = ("one_sided", "immobile")  # the same names as evaluation.feasibility.JAM_MODELS


class SettleStatus(enum.IntEnum):
    """How the simulation of one case ended (stored as ints in ``SettleResult.status``)."""

    SETTLED = 0  # came to rest: |qvel| and |qacc| below their tolerances
    NOT_SETTLED = 1  # still moving when max_time_s ran out
    UNSTABLE = 2  # the state blew up (non-finite, MuJoCo bad qacc, or |qvel| > max_qvel_rad_s)
    BEYOND_LIMIT = 3  # came to rest, but more than limit_tol_rad outside the joint range: not physical
    NONFINITE_COMMAND = 4  # l_motor or f has NaN/inf: not simulated, q_settle is NaN


@dataclass(frozen=True)
class SettleParams:
    """Simulation settings; see the module docstring for why these defaults."""

    mode: str = "length"  # "length": motors hold l_motor (spring); "tension": constant commanded f
    jam: str = "one_sided"  # "one_sided": jammed rest length min(l_motor, l_fixed) (paper); "immobile": l_fixed
    max_time_s: float = 3.0  # simulated time limit per case [s]
    timestep_s: float | None = None  # None: the model's timestep [s]
    mass_damping_per_s: float = 8.0  # a in -a M qdot [1/s]
    muscle_damping_s: float = 0.01  # beta in beta * dphi/ddelta * dl/dt [s]
    qvel_tol_rad_s: float = 1e-4  # at rest when max|qvel| is below this [rad/s] ...
    qacc_tol_rad_s2: float = 1e-3  # ... and max|qacc| below this [rad/s^2]
    max_qvel_rad_s: float = 100.0  # faster than this counts as UNSTABLE [rad/s]
    max_torque_nm: float = 1e6  # a larger muscle/damping joint force counts as UNSTABLE [N m]
    check_every_steps: int = 10  # test for rest / blow-up every this many steps
    limit_tol_rad: float = 0.02  # a rest posture further outside the joint range is BEYOND_LIMIT [rad]
    chunk_size: int = 128  # cases stepped in lockstep (one MjData, ~0.5 MB, each)
    n_threads: int | None = None  # threads stepping chunks side by side (None: see THREADS_MIN_DOF)

    def __post_init__(self):
        if self.mode not in MODES:
            raise BodySchemaInputError(f"SettleParams.mode={self.mode!r}; use one of {list(MODES)}")
        if self.jam not in JAM_MODES:
            raise BodySchemaInputError(f"SettleParams.jam={self.jam!r}; use one of {list(JAM_MODES)}")
        positive = ["max_time_s", "qvel_tol_rad_s", "qacc_tol_rad_s2", "max_qvel_rad_s", "max_torque_nm",
                    "check_every_steps", "limit_tol_rad", "chunk_size"]
        positive += [] if self.timestep_s is None else ["timestep_s"]
        for name in positive:
            value = getattr(self, name)
            if not np.isfinite(value) or value <= 0:
                raise BodySchemaInputError(f"SettleParams.{name}={value!r} must be finite and > 0")
        for name in ("mass_damping_per_s", "muscle_damping_s"):
            value = getattr(self, name)
            if not np.isfinite(value) or value < 0:
                raise BodySchemaInputError(f"SettleParams.{name}={value!r} must be finite and >= 0")
        for name in ("check_every_steps", "chunk_size"):
            if int(getattr(self, name)) != getattr(self, name):
                raise BodySchemaInputError(f"SettleParams.{name}={getattr(self, name)!r} must be an integer")
        if self.n_threads is not None and (isinstance(self.n_threads, bool) or not isinstance(self.n_threads, int)
                                           or self.n_threads < 1):
            raise BodySchemaInputError(f"SettleParams.n_threads={self.n_threads!r} must be an integer >= 1 or None")


@dataclass
class SettleResult:
    """Batched settle output; prints nothing, like mujoco's ``minimize``.

    q_settle (B, N) rest posture [rad]; E_q_phys (B,) ``||q_settle - q_ref||`` [rad]; status (B,)
    ``SettleStatus`` ints; time_s (B,) simulated time when the case stopped [s]; qvel_rad_s (B, N)
    final joint velocity; f_settle_n (B, M) muscle tensions in the final state [N] (0 for cut muscles).
    Rows of NONFINITE_COMMAND cases are NaN (time_s 0). UNSTABLE rows hold the last state that passed a
    check (q_ref at rest, f NaN, if the case blew up before its first check) for diagnosis, and E_q_phys +inf.
    A NOT_SETTLED row holds the state at max_time_s, a body still moving: no rest posture (``unsettled``,
    ``E_q_rest``).
    """

    q_settle: np.ndarray
    E_q_phys: np.ndarray
    status: np.ndarray
    time_s: np.ndarray
    qvel_rad_s: np.ndarray
    f_settle_n: np.ndarray

    @property
    def settled(self) -> np.ndarray:
        """(B,) bool: the case came to rest."""
        return self.status == SettleStatus.SETTLED

    @property
    def unsettled(self) -> np.ndarray:
        """(B,) bool: simulated but never at rest (NOT_SETTLED: still moving at max_time_s; UNSTABLE: blew up). Its
        q_settle is no rest posture: a score counts these apart (``E_q_rest``), never as an E_q_phys."""
        return np.isin(self.status, (SettleStatus.NOT_SETTLED, SettleStatus.UNSTABLE))

    @property
    def E_q_rest(self) -> np.ndarray:
        """(B,) E_q_phys [rad] of the cases that came to rest (SETTLED, BEYOND_LIMIT), NaN elsewhere (``unsettled``
        and NONFINITE_COMMAND): what medians of rest postures take, with ``unsettled.sum()`` reported beside."""
        return np.where(self.unsettled, np.nan, self.E_q_phys)

    @property
    def status_names(self) -> list[str]:
        return [SettleStatus(int(s)).name for s in self.status]
