"""Where a learned path switches branch: each posture's distance to the nearest learned switch, for the adapter's flag.

MuJoCo's wrapping picks a side of each wrap object and the length jumps where the side switches (myoArm: 1-20 mm).
A two-branch muscle (``networks.branches``) places its switch from samples: its length is the second polynomial
where its gate is positive. Near the gate's zero set the learned length may sit on the wrong side of the true jump
(myoArm: the zero set lies a median 8 mrad from MuJoCo's jump where one is found nearby), so a command there is not
exact: the adapter reports such postures (``near_path_switch``) instead of commanding them as if exact.

``PostureSwitches`` estimates each posture's distance [rad, Euclidean over the joints] to every learned switch to
first order, ``|g(q)| / |grad_q g(q)|`` (exact for a plane; near a curved zero set, where the flag matters, close),
and, within reach, keeps the switches whose two branches differ there by at least ``JUMP_FLOOR_M`` (a degree-8 gate
also changes sign where both branches agree: no jump, nothing to flag). Muscles whose cells replaced their branches
(``networks.cells``) do not switch by a gate and are not counted: a trimmed cell fits the larger side of a jump
inside it and says nothing of where the smaller side begins (RESULTS.md "Hold every posture"). In numpy; no Lightning.
"""
from __future__ import annotations

import numpy as np
import torch

from .arrays import Frozen, encode_q
from .basis import ProductTerms, TermsSnapshot

SWITCH_REACH_RAD = 0.005  # a posture this close to a learned switch is flagged [rad] (RESULTS.md "Hold every posture":
# 0.65 % of uniform myoArm postures; 10 mrad: 1.2 %)
JUMP_FLOOR_M = 1e-4  # a gate's zero counts as a switch where its branches differ by this much [m] (evaluation.
# body_errors.BAD_LENGTH_MM: a posture whose worst muscle misses by more is a bad one)


class PostureSwitches(Frozen):
    """A fitted ``PerMusclePath``'s learned switches, read from its ``snapshot.PathSnapshot`` (``muscles``: those a
    gate switches; the gates and their branches' difference, each on its own terms only: ``_on_terms``), with the
    schema's normalization (``q_lo``, ``q_hi`` (N,) [rad]: ``arrays.encode_q``) and the lengths' scale
    ``length_scale_m`` (M,) [m per normalized unit]; rebuilt when the path changes (a schema keeps it in its inference
    cache). A call in numpy (``on_host()``) ``(q_rad (B, N))`` gives each posture's distance [rad] to the nearest
    learned switch and its muscle, ``(B,)`` each (``inf``, -1: none)."""

    def __init__(self, path, snapshot, q_lo, q_hi, length_scale_m):
        self.q_lo, self.q_hi, self.length_scale_m = (a.to(torch.float64) for a in (q_lo, q_hi, length_scale_m))
        self.x_lo, self.x_hi, self.half_range = snapshot.x_lo, snapshot.x_hi, 0.5 * (self.q_hi - self.q_lo)
        self.muscles = torch.nonzero(snapshot.gated).flatten()
        self.gate_row, self.alt_row, self.box_row = (col[self.muscles] for col in (snapshot.gate_col, snapshot.alt_col,
                                                                                   snapshot.box_col))
        self.gate_terms, self.gate = _on_terms(path.exponents, snapshot.box[self.gate_row])
        self.gap_terms, self.gap = _on_terms(path.exponents, snapshot.box[self.alt_row] - snapshot.box[self.box_row])

    def __call__(self, q_rad, box_rows=None):
        """``box_rows``: the snapshot's whole-box rows at these postures (``PathSnapshot``'s third output), read
        instead of evaluating the gates on their own terms (the same polynomials: equal to rounding)."""
        if not len(self.muscles):
            return np.full(len(q_rad), np.inf), np.full(len(q_rad), -1, dtype=np.int64)
        if box_rows is None:  # (B, 1 + N, G): each gate's value, then its slopes
            x = np.minimum(np.maximum(encode_q(np.asarray(q_rad, np.float64), self.q_lo, self.q_hi), self.x_lo),
                           self.x_hi)
            gate = np.swapaxes(self.gate_terms(x), 1, 2) @ self.gate
        else:
            gate = np.swapaxes(box_rows[:, self.gate_row], 1, 2)
        grad = gate[:, 1:] / self.half_range[:, None]  # d g / d q [1/rad]
        norm = np.sqrt(np.add.reduce(grad * grad, axis=1))  # np.linalg.norm's arithmetic, without its checks
        distance = np.abs(gate[:, 0]) / np.maximum(norm, 1e-300)  # (B, G)
        within = distance <= SWITCH_REACH_RAD
        if within.any():  # within reach: is there a jump? (few rows)
            rows, cols = np.nonzero(within)
            jump_m = np.abs((self.gap_terms(x[rows])[:, :, 0] @ self.gap)[np.arange(len(rows)), cols] if box_rows is
                            None else box_rows[rows, self.alt_row[cols], 0] - box_rows[rows, self.box_row[cols], 0])
            jump_m *= self.length_scale_m[self.muscles[cols]]
            distance[rows[jump_m < JUMP_FLOOR_M], cols[jump_m < JUMP_FLOOR_M]] = np.inf
        nearest = distance.min(1)  # the entry argmin picks (a NaN row: NaN either way)
        return nearest, np.where(nearest < np.inf, self.muscles[distance.argmin(1)], -1)


def _on_terms(exponents: torch.Tensor, coef: torch.Tensor):
    """The terms ``coef (G, P)`` uses, as the path's own basis evaluation (``basis.TermsSnapshot``: each term and its
    slopes), and their coefficients ``(P', G)``."""
    cols = torch.nonzero(coef.abs().sum(0) > 0).flatten()
    return TermsSnapshot(ProductTerms(exponents[cols].cpu().numpy())), coef[:, cols].T


def switch_diagnostics(distance_rad: np.ndarray, muscle: np.ndarray) -> dict:
    """``PostureSwitches``' answer as the adapter's per-row diagnostics: ``near_path_switch`` (within
    ``SWITCH_REACH_RAD``), ``path_switch_distance_rad``, ``path_switch_muscle``."""
    return {"near_path_switch": distance_rad <= SWITCH_REACH_RAD, "path_switch_distance_rad": distance_rad,
            "path_switch_muscle": muscle}
