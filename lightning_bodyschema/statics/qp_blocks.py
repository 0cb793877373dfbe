"""The muscles' box QPs cut into the pieces the solver runs fastest: independent blocks, and chunks of rows.

* Blocks: where the muscles and joints fall into groups that share no moment arm (myoLegs with its pelvis welded:
  each leg's 40 muscles span only that leg's 7 joints), the QP of a row is one QP per group: the objective is a sum
  over muscles and each joint's balance involves only its group's muscles, so the minimizer is the groups'
  minimizers side by side (it is unique: the Hessian is the identity). Two QPs of 40 x 7 cost about a quarter of one
  of 80 x 14 in the Newton systems (``G^T D G``) and half in every product with G.
* Chunks: on the CPU, rows are solved about ``CHUNK_BYTES`` of moment arms at a time, so that the solver's passes
  over G and its line search's trials stay in cache (a 10,000-frame myoLegs motion has 90 MB of G). The answer of a
  row does not depend on the others.

Fewer than ``MIN_BLOCK_ROWS`` rows are solved whole (a solver call costs more than a block saves them). A row's
status is its blocks' worst (``BAD_INPUT``, then ``INFEASIBLE``, ``NOT_CONVERGED``, ``OK``). numpy; the solver
runs in torch. Never imports Lightning.
"""
from __future__ import annotations

import numpy as np

from ..status import Status
from .warm_start import SEED_EVERY, solve_warm

CHUNK_BYTES = 2 ** 23  # of G per chunk: a quarter of this machine's L3 (32 MiB); 1 to 8 MiB ran alike, 90 MB
# in one batch 1.4-1.8x slower (the myoLegs squat's QP, BENCHMARKS)
MIN_CHUNK_ROWS = 1024  # never fewer rows per chunk: a solver call costs ~1 ms more (~1 us a row at this size)
MIN_BLOCK_ROWS = 64  # fewer rows are solved whole: each block is a solver call (~1 ms), more than a block saves them
# each code's rank, worst lowest: a row is as bad as its worst block (a code not named here ranks worst)
_RANK = np.zeros(max(s.code for s in Status) + 1, dtype=int)
_RANK[[Status.INFEASIBLE.code, Status.NOT_CONVERGED.code, Status.OK.code]] = [1, 2, 3]  # BAD_INPUT: 0


def blocks(G: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """``[(muscles, joints)]`` index arrays of the independent blocks of the moment arms ``G`` (B, M, N): the
    connected groups of muscles and joints, linked where some row has a nonzero moment arm. Muscles that span no
    joint and joints that no muscle spans join the first block (their part of the QP is the same there). One block:
    ``[(slice(None), slice(None))]`` (no copy)."""
    spans = (G != 0).any(0) if len(G) else np.zeros(G.shape[1:], dtype=bool)  # (M, N)
    label = np.full(G.shape[2], -1)
    for start in range(G.shape[2]):
        if label[start] >= 0 or not spans[:, start].any():
            continue
        joints = np.zeros(G.shape[2], dtype=bool)
        joints[start] = True
        while True:  # the joints reached through the muscles reached, to a fixed point
            reached = spans[spans[:, joints].any(1)].any(0)
            if (reached <= joints).all():
                break
            joints |= reached
        label[joints] = label.max() + 1
    if label.max() < 1:
        return [(slice(None), slice(None))]
    muscle_block = np.where(spans.any(1), label[np.argmax(spans, 1)], 0)  # a muscle's joints share one block
    label[label < 0] = 0
    return [(np.flatnonzero(muscle_block == k), np.flatnonzero(label == k)) for k in range(label.max() + 1)]


def chunks(rows: int, values_per_row: int, device=None) -> list[slice]:
    """Slices of ``rows`` rows of ``CHUNK_BYTES`` to twice that of float64 each (``values_per_row`` of G), at least
    ``MIN_CHUNK_ROWS`` rows, evenly sized; one slice on another device than the CPU (a GPU wants the whole batch)."""
    if device is not None and getattr(device, "type", device) != "cpu":
        return [slice(0, rows)]
    per_chunk = max(MIN_CHUNK_ROWS, CHUNK_BYTES // (8 * max(1, values_per_row)))
    edges = np.linspace(0, rows, max(1, rows // per_chunk) + 1).round().astype(int)  # each chunk >= per_chunk rows
    return [slice(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:])]


def solve_in_pieces(solve, G, column_scale, tau_nm, x_ref, lo, hi, device=None, warm_tol_nm=None):
    """``solve(G_piece, tau_nm, x_ref, lo, hi) -> (x (b, m), codes (b,))`` on every block and chunk (module docstring)
    of the QP whose moment arms are ``G`` (B, M, N) with each muscle's row scaled by ``column_scale`` (B, M) (each
    piece scaled on its own: no scaled copy of the whole), put together: ``(x (B, M), codes (B,))``. ``warm_tol_nm``:
    the rows are a motion's consecutive frames; on the CPU each chunk is warm-started (``statics.warm_start``),
    frames taken where they balance to it [N m]."""
    x, code = np.full(lo.shape, np.nan), np.full(len(G), Status.OK.code)
    cpu = device is None or getattr(device, "type", device) == "cpu"
    for muscles, joints in blocks(G) if len(G) >= MIN_BLOCK_ROWS else [(slice(None), slice(None))]:
        whole = isinstance(muscles, slice)
        pick = (lambda a: a) if whole else (lambda a: a[:, muscles])  # noqa: E731
        for rows in chunks(len(G), (G.shape[1] * G.shape[2]) if whole else len(muscles) * len(joints), device):
            arms = G[rows] if whole else G[rows, muscles[:, None], joints]
            piece = (arms * pick(column_scale[rows])[..., None], tau_nm[rows] if whole else tau_nm[rows][:, joints],
                     *(pick(a[rows]) for a in (x_ref, lo, hi)))
            warm = warm_tol_nm is not None and cpu and len(arms) >= 2 * SEED_EVERY
            x_rows, code_rows = solve_warm(solve, *piece, warm_tol_nm) if warm else solve(*piece)
            x[rows, muscles] = x_rows
            code[rows] = np.where(_RANK[code_rows] < _RANK[code[rows]], code_rows, code[rows])
    return x, code
