"""``Diagnosis``: what the diagnosis says of each log, per muscle and as a whole, in arrays and as records."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..faults import Faults
from ..status import Status

KINDS = ("healthy", "cut", "jam", "weak", "band")  # a muscle's kind: its index in this tuple
HEALTHY, CUT, JAM, WEAK, BAND = range(len(KINDS))


@dataclass
class Diagnosis:
    """C logs, M muscles.

    status (C,) ``Status`` members: ``no_fault``, ``identified``, ``ambiguous`` or ``not_identifiable``.
    kind (C, M) indices into ``KINDS``; where the status is ``ambiguous`` a muscle the explanations disagree on reads
    ``healthy`` here and its alternatives are in ``candidates``. score (C, M): the chi-square evidence for the
    muscle's fault over its being healthy (above ``Thresholds.margin`` for every muscle declared faulted; negative
    favours healthy). observed (C, M): a cut of this muscle would have shown in this log (it pulled in some row).
    l_fixed_m, f_weak_n (C, M), l_band_m (C, M, 2): the parameter estimates (NaN where the kind has none; a band
    edge the log never reached is NaN). faults: the ``Faults`` every explanation of the log agrees on, one row per
    log, ready for ``schema.adapt`` (``no_fault`` and ``not_identifiable``: none). candidates: per log, the
    alternative explanations of an ``ambiguous`` log, each a dict in ``tools/predict.py``'s request keys.
    """

    status: np.ndarray
    kind: np.ndarray
    score: np.ndarray
    observed: np.ndarray
    l_fixed_m: np.ndarray
    f_weak_n: np.ndarray
    l_band_m: np.ndarray
    faults: Faults
    muscles: list
    candidates: list = field(default_factory=list)
    cases: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.status)

    def union_faults(self, c: int) -> Faults:
        """Log ``c``'s faults as one ``Faults`` row: for an ``ambiguous`` log every candidate's faults together (a
        command that meets them all holds under whichever explanation is true; it may ask more than needed), else
        ``faults``' row."""
        if self.status[c] != Status.AMBIGUOUS or not self.candidates[c]:
            return self.faults.take([c])
        request = merge_requests({}, self.candidates[c])
        request["cut"] = sorted(set(request.get("cut", [])), key=self.muscles.index)
        return Faults.from_names(self.muscles, n_cases=1, **{k: [v] if k == "cut" else v for k, v in request.items()})

    def kind_names(self) -> np.ndarray:
        """(C, M) the kinds as names."""
        return np.asarray(KINDS, dtype=object)[self.kind]

    def records(self) -> list:
        """One dict per log: ``case``, ``status``, ``muscles`` ({name: {kind, score, observed, and its parameter}})
        and ``faults`` in ``tools/predict.py``'s keys and units (cut: [..], jam: {name: l_fixed_m}, weak: {name:
        f_max_n}, band: {name: [lo, hi]}), ``candidates`` where ambiguous."""
        return [self.record(c) for c in range(len(self))]

    def record(self, c: int) -> dict:
        muscles = {name: self._muscle(c, m) for m, name in enumerate(self.muscles)}
        out = {"case": int(self.cases[c]) if self.cases is not None else c, "status": str(self.status[c]),
               "muscles": muscles, "faults": fault_request(self.faults, c, self.muscles)}
        if self.status[c] == Status.AMBIGUOUS:
            out["candidates"] = self.candidates[c]
        return out

    def _muscle(self, c: int, m: int) -> dict:
        kind = KINDS[self.kind[c, m]]
        entry = {"kind": kind, "score": round(float(self.score[c, m]), 3), "observed": bool(self.observed[c, m])}
        if kind == "jam":
            entry["l_fixed_m"] = float(self.l_fixed_m[c, m])
        elif kind == "weak":
            entry["f_max_n"] = float(self.f_weak_n[c, m])
        elif kind == "band":
            entry["band_m"] = [None if np.isnan(v) else float(v) for v in self.l_band_m[c, m]]
        return entry


def fault_request(faults: Faults, c: int, muscles: list) -> dict:
    """Row ``c`` of ``faults`` as a request of ``tools/predict.py`` (only the kinds present)."""
    out = {}
    cut = [muscles[m] for m in np.flatnonzero(faults.cut[c])]
    if cut:
        out["cut"] = cut
    jam = {muscles[m]: float(faults.l_fixed_m[c, m]) for m in np.flatnonzero(faults.fix[c])}
    if jam:
        out["jam"] = jam
    weak = {muscles[m]: float(faults.f_max_n[c, m]) for m in np.flatnonzero(faults.weak[c])}
    if weak:
        out["weak"] = weak
    band = {muscles[m]: [float(v) for v in faults.l_band_m[c, m]] for m in np.flatnonzero(faults.band[c])}
    if band:
        out["band"] = band
    return out


def merge_requests(base: dict, parts) -> dict:
    """``base`` (a request's fault keys) with each of ``parts`` added: cut lists joined, the other kinds' dicts
    updated."""
    out = {key: (list(value) if isinstance(value, list) else dict(value)) for key, value in base.items()}
    for part in parts:
        for key, value in part.items():
            if key == "cut":
                out["cut"] = out.get("cut", []) + list(value)
            else:
                out.setdefault(key, {}).update(value)
    return out
