"""``Monitor``: the diagnosis as a controller runs it, one tick at a time.

Each tick the controller hands over what it sent and what its sensors read. The monitor keeps the last ``window``
ticks (the body evaluated once per tick, at its reading) and diagnoses them as one log. A fault is **declared** only
when ``confirm`` consecutive ticks give the same explanation (the false-alarm guard); a declared fault stays declared
(after the controller adapts, a cut muscle is commanded slack and its log no longer shows the cut) until ``reset``.
A fault that strikes mid-window shows first as a log no explanation fits (rows before and after it disagree); it is
declared once the window holds only rows after it: the detection delay is about ``window + confirm - 2`` tick periods.

A robot holding a posture reads nearly the same joint angles every tick: within ``reuse_rad`` of the posture where the
body was last evaluated, the body is carried over to first order (``l_geo(q) = l_geo(q0) + G(q0) (q - q0)``; the
second-order rest, under 1 um for myoArm's paths at 5 mrad, lies far below the learned body's own error), so a tick
costs the body's evaluation only when the robot moves.
"""
from __future__ import annotations

from typing import Optional

import numpy as np

from ..errors import BodySchemaInputError
from ..faults import Faults
from ..status import Status
from .explain import diagnose
from .log import SensorLog
from .noise import SensorNoise, Thresholds
from .result import HEALTHY, KINDS, Diagnosis


class Monitor:
    """Streaming diagnosis for one robot (module docstring); build it with ``schema.monitor(...)``.

    load_cells: (M,) bool, the muscles whose load cell the controller reads (None: every muscle's ``f`` reading
    given to ``update``; a reading's NaN also marks a missing load cell).
    """

    def __init__(self, schema, noise: SensorNoise, thresholds: Optional[Thresholds] = None, window: int = 5,
                 confirm: int = 3, load_cells=None, reuse_rad: float = 5e-3):
        for name, value in (("window", window), ("confirm", confirm)):
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise BodySchemaInputError(f"monitor {name}={value!r} must be an integer >= 1")
        self.schema, self.noise, self.thresholds = schema, noise, thresholds or Thresholds()
        self.window, self.confirm, self.reuse_rad = window, confirm, float(reuse_rad)
        self.joints, self.muscles = list(schema.robot_model.joint_names), list(schema.robot_model.muscle_names)
        M = len(self.muscles)
        self.load_cells = np.ones(M, bool) if load_cells is None else np.asarray(load_cells, bool)
        if self.load_cells.shape != (M,):
            raise BodySchemaInputError(f"load_cells has shape {self.load_cells.shape}; expected ({M},)")
        self.error = schema.body_error()
        self.reset()

    def reset(self) -> None:
        """Forget the ticks and every declared fault (after a repair)."""
        self._ticks: list = []
        self._streak, self._last = 0, None
        self.declared: Optional[np.ndarray] = None  # (M,) kinds once a fault is declared
        self.declared_diagnosis = None
        self.declarations: list = []  # (tick, Diagnosis) each time a fault was declared
        self.ticks_seen = 0
        self._anchor = None  # (q0, l_geo, G, tau) where the body was last evaluated

    def update(self, cmd, reading) -> Diagnosis:
        """``cmd = (l_cmd_m (M,), f_cmd_n (M,))`` sent, ``reading = (q_rad (N,), l_m (M,), f_n (M,) or None)`` read.
        Returns the ``Diagnosis`` of the window with the guard applied: ``no_fault`` until a fault is declared
        (``pending`` says how many consistent ticks the current explanation has), then the declared one."""
        row = self._row(cmd, reading)
        self._ticks = (self._ticks + [row])[-self.window:]
        self.ticks_seen += 1
        raw = diagnose(self._log(), self._cached_body, self.schema.spring, self.noise, self.error, self.thresholds)
        return self._guarded(raw)

    def _row(self, cmd, reading) -> dict:
        l_cmd, f_cmd = (np.asarray(v, float).reshape(len(self.muscles)) for v in cmd)
        q, l_m, f = reading
        q = np.asarray(q, float).reshape(len(self.joints))
        f = np.full(len(self.muscles), np.nan) if f is None else np.asarray(f, float).reshape(len(self.muscles))
        values = (l_cmd, f_cmd, q, np.asarray(l_m, float).reshape(len(self.muscles)))
        if not all(np.all(np.isfinite(v)) for v in values):
            raise BodySchemaInputError("monitor.update: a command or reading is NaN/inf (a log holds finite values; "
                                       "mark a missing load cell with f=None or load_cells)")
        body = self._body_at(q)
        return {"q": q, "l": values[3], "f": np.where(self.load_cells, f, np.nan), "l_cmd": l_cmd, "f_cmd": f_cmd,
                "body": body}

    def _body_at(self, q: np.ndarray):
        """The body at one posture: evaluated, or carried over from the anchor to first order (module docstring)."""
        if self._anchor is None or np.max(np.abs(q - self._anchor[0])) > self.reuse_rad:
            self._anchor = (q, *self.schema.learned_body_si(q[None]))
        q0, l_geo, G, tau = self._anchor
        return l_geo + np.einsum("bmn,n->bm", G, q - q0), G, tau

    def _log(self) -> SensorLog:
        stack = lambda key: np.stack([t[key] for t in self._ticks])  # noqa: E731
        return SensorLog.from_rows(self.joints, self.muscles, stack("q"), stack("l"), stack("l_cmd"), stack("f_cmd"),
                                   stack("f"))

    def _cached_body(self, q_rad):
        """The body at the window's rows, evaluated once when each tick arrived (rows come in tick order)."""
        parts = [t["body"] for t in self._ticks]
        return tuple(np.concatenate([p[i] for p in parts]) for i in range(3))

    def _guarded(self, raw):
        key = (str(raw.status[0]), tuple(raw.kind[0]))
        faulted = raw.status[0] in (Status.IDENTIFIED, Status.AMBIGUOUS)
        self._streak = self._streak + 1 if faulted and key == self._last else int(faulted)
        self._last = key
        new = raw.kind[0] != HEALTHY if self.declared is None else (raw.kind[0] != HEALTHY) & (self.declared == HEALTHY)
        if faulted and self._streak >= self.confirm and (self.declared is None or new.any()):
            # a declaration only adds: after adapting, a jam the new command no longer asks to pay out reads healthy
            self.declared = raw.kind[0].copy() if self.declared is None else np.where(new, raw.kind[0], self.declared)
            self.declared_diagnosis = raw
            self.declarations.append((self.ticks_seen, raw))
        raw.pending = self._streak
        if self.declared_diagnosis is not None:
            return self._latched(raw)
        raw.status[0] = Status.NO_FAULT
        raw.kind[0] = HEALTHY
        raw.faults = Faults.none(1, len(self.muscles))
        return raw

    def _latched(self, raw):
        """The latest declaration, kept whatever the window now shows (``declarations`` has every one)."""
        out = self.declared_diagnosis
        out.pending = raw.pending
        return out

    def declared_names(self) -> dict:
        """{muscle: kind} of the declared faults."""
        if self.declared is None:
            return {}
        return {self.muscles[m]: KINDS[k] for m, k in enumerate(self.declared) if k != HEALTHY}
