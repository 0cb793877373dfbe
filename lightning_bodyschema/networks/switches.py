"""Where a learned path switches branch: each posture's distance to the nearest learned switch, for the adapter's flag.

MuJoCo's wrapping picks a side of each wrap object and the length jumps where the side switches (myoArm: 1-20 mm).
A two-branch muscle (``networks.branches``) places its switch from samples: its length is the second polynomial
where its gate is positive. Near the gate's zero set the learned length may sit on the wrong side of the true jump
(myoArm: the zero set lies a median 8 mrad from MuJoCo's jump where one is found nearby), so a command there is not
exact: the adapter reports such postures (``near_path_switch``) instead of commanding them as if exact.

``switch_distance`` estimates each posture's distance [rad, Euclidean over the joints] to every learned switch to
first order, ``|g(q)| / |grad_q g(q)|`` (exact for a plane; near a curved zero set, where the flag matters, close),
and, within reach, keeps the switches whose two branches differ there by at least ``JUMP_FLOOR_M`` (a degree-8 gate also changes
sign where both branches agree: no jump, nothing to flag). Muscles whose cells replaced their branches
(``networks.cells``) do not switch by a gate and are not counted: a trimmed cell fits the larger side of a jump
inside it and says nothing of where the smaller side begins (RESULTS.md "Hold every posture").

In numpy (a few terms per gate: at one posture numpy's calls cost less than torch's); no Lightning.
"""
from __future__ import annotations

import numpy as np
import torch

from .basis import product_basis

SWITCH_REACH_RAD = 0.005  # a posture this close to a learned switch is flagged [rad] (RESULTS.md "Hold every posture":
# 0.65 % of uniform myoArm postures; 10 mrad: 1.2 %)
JUMP_FLOOR_M = 1e-4  # a gate's zero counts as a switch where its branches differ by this much [m] (evaluation.
# body_errors.BAD_LENGTH_MM: a posture whose worst muscle misses by more is a bad one)


def gated_muscles(path) -> torch.Tensor:
    """The muscles of a ``PerMusclePath`` whose length a gate switches (``branched``), ``(G,)`` long."""
    if getattr(path, "branches", 1) != 2:
        return torch.zeros(0, dtype=torch.long, device=path.coef.device)
    return torch.nonzero(path.branched).flatten()


def _legendre(x: np.ndarray, degree: int) -> tuple[np.ndarray, np.ndarray]:
    """``P_0..P_degree`` of ``x (B, N)`` and their slopes, ``(B, N, degree + 1)`` each (``basis.legendre``)."""
    values, slopes = [np.ones_like(x), x], [np.zeros_like(x), np.ones_like(x)]
    for n in range(1, degree):  # (n+1) P_{n+1} = (2n+1) x P_n - n P_{n-1};  P'_{n+1} = P'_{n-1} + (2n+1) P_n
        values.append(((2 * n + 1) * x * values[n] - n * values[n - 1]) / (n + 1))
        slopes.append(slopes[n - 1] + (2 * n + 1) * values[n])
    return np.stack(values[:degree + 1], -1), np.stack(slopes[:degree + 1], -1)


class _Terms:
    """Product-Legendre terms ``exponents (P, N)`` evaluated in numpy at ``x (B, N)``: ``phi (B, P)`` and, with
    ``slopes``, ``dphi/dx (B, N, P)`` (``basis.product_basis``'s arithmetic on the few terms a gate uses)."""

    def __init__(self, exponents: torch.Tensor):
        self.exponents = exponents.cpu().numpy()
        self.degree = max(int(self.exponents.max(initial=0)), 1)

    def __call__(self, x: np.ndarray, slopes: bool = False):
        values, derivs = _legendre(x, self.degree)
        joints = np.arange(x.shape[1])
        factors = values[:, joints, self.exponents]  # (B, P, N)
        phi = factors.prod(-1)
        if not slopes:
            return phi, None
        ones = np.ones_like(factors[..., :1])
        before = np.concatenate([ones, np.cumprod(factors[..., :-1], -1)], -1)  # prod_{i<j} factor_i
        after = np.concatenate([np.cumprod(factors[..., :0:-1], -1)[..., ::-1], ones], -1)  # prod_{i>j}
        slope = derivs[:, joints, self.exponents] * before * after  # (B, P, N)
        return phi, slope.transpose(0, 2, 1)


class SwitchSnapshot:
    """A fitted ``PerMusclePath``'s learned switches frozen in numpy (the gates in use and their branches'
    difference, each on its own terms only), for ``switch_distance``; rebuilt when the path changes (a schema keeps
    it in its inference cache)."""

    def __init__(self, path):
        self.muscles = gated_muscles(path).cpu().numpy()
        if not len(self.muscles):
            return
        index = torch.as_tensor(self.muscles, device=path.coef.device)
        gate = path.gate[index]
        diff = (path.coef_alt[index] - path.coef[index]) * path.term_mask[index]
        self.gate_terms, self.gate = self._columns(path, gate)
        self.gap_terms, self.gap = self._columns(path, diff)

    @staticmethod
    def _columns(path, coef: torch.Tensor):
        cols = torch.nonzero(coef.abs().sum(0) > 0).flatten()
        return _Terms(path.exponents[cols]), coef[:, cols].T.cpu().numpy()  # (P', G)

    def __call__(self, x: np.ndarray, half_range: np.ndarray, length_scale_m: np.ndarray):
        """``(distance (B,), muscle (B,))``: ``switch_distance``'s answer at normalized postures ``x (B, N)``."""
        if not len(self.muscles):
            return np.full(len(x), np.inf), np.full(len(x), -1, dtype=np.int64)
        phi, dphi = self.gate_terms(x, slopes=True)
        grad = (dphi @ self.gate) / half_range[None, :, None]  # (B, N, G): d g / d q [1/rad]
        distance = np.abs(phi @ self.gate) / np.maximum(np.linalg.norm(grad, axis=1), 1e-300)  # (B, G)
        rows, cols = np.nonzero(distance <= SWITCH_REACH_RAD)  # within reach: is there a jump? (few rows)
        if len(rows):
            jump_m = np.abs((self.gap_terms(x[rows])[0] @ self.gap)[np.arange(len(rows)), cols])
            jump_m *= length_scale_m[self.muscles[cols]]
            distance[rows[jump_m < JUMP_FLOOR_M], cols[jump_m < JUMP_FLOOR_M]] = np.inf
        which = np.argmin(distance, axis=1)
        nearest = distance[np.arange(len(x)), which]
        return nearest, np.where(np.isfinite(nearest), self.muscles[which], -1)


def switch_distance(path, x, half_range, length_scale_m, snapshot: SwitchSnapshot = None) -> tuple[np.ndarray,
                                                                                                  np.ndarray]:
    """Each posture's distance [rad] to the nearest learned switch of ``path`` (a ``PerMusclePath``) and its muscle,
    ``(B,)`` each (``inf``, -1: none), at normalized postures ``x (B, N)``; ``half_range (N,)``: rad per normalized
    unit, ``length_scale_m (M,)``: m per normalized length unit; ``snapshot``: ``SwitchSnapshot(path)`` when the
    caller keeps one. A gate's zero set within ``SWITCH_REACH_RAD`` where its branches differ by less than
    ``JUMP_FLOOR_M`` is no switch (inf)."""
    snapshot = SwitchSnapshot(path) if snapshot is None else snapshot
    host = lambda a: np.asarray(a.detach().cpu() if torch.is_tensor(a) else a, np.float64)  # noqa: E731
    return snapshot(host(x), host(half_range), host(length_scale_m))


def switch_diagnostics(distance_rad: np.ndarray, muscle: np.ndarray) -> dict:
    """``switch_distance``'s answer as the adapter's per-row diagnostics: ``near_path_switch`` (within
    ``SWITCH_REACH_RAD``), ``path_switch_distance_rad``, ``path_switch_muscle``."""
    return {"near_path_switch": distance_rad <= SWITCH_REACH_RAD, "path_switch_distance_rad": distance_rad,
            "path_switch_muscle": muscle}
