"""Piecewise muscle paths: a muscle's box of joints cut into cells, one polynomial per cell (its layout and evaluation;
the fit: ``networks.cell_fit``).

A wrapping path's length is smooth in pieces; over a smaller box the same degree fits far better (RESULTS.md
"Per-muscle paths on myoArm"). A celled muscle has ``pieces ** n`` cells over the ``n`` joints that cut its box
(``cell_cuts``), each a polynomial in the cell's coordinates (``cell_inputs``). The length at a posture is its cell's
polynomial where that cell was fitted and the moment arm that polynomial's exact derivative (the length steps by about
the fit's error at a cell's edge); joints a muscle does not cross cut nothing (exactly zero moment arm). Plain
PyTorch, no Lightning.
"""
from __future__ import annotations

from typing import Optional

import numpy as np
import torch
from torch import nn

from .arrays import as_dtype, clip, namespace, take
from .basis import ProductTerms
from .branches import SAMPLES_PER_TERM
from .polynomial import check_degrees, term_count


def cell_coordinates(x, pieces: int):
    """Each joint's piece ``k (B, N)`` (int64, 0..pieces-1, of [-1, 1] cut evenly) and the local coordinate
    ``x_local (B, N)`` in [-1, 1] within it, ``d x_local / d x = pieces``, at ``x`` (numpy or torch); a NaN
    coordinate gets piece 0 (a NaN answer at a valid index)."""
    xp = namespace(x)
    scaled = pieces * (x + 1)
    k = clip(xp.floor(scaled / 2), 0, pieces - 1)
    return as_dtype(k, xp.int64), scaled - 2 * k - 1


def cell_index(piece: torch.Tensor, stride: torch.Tensor) -> torch.Tensor:
    """Each posture's cell ``(B,)`` or ``(B, Mc)`` from its joints' pieces ``piece (B, N)`` (long) and a muscle's
    ``stride (N,)`` or every celled muscle's ``(Mc, N)`` (a product and a sum: CUDA has no integer matmul)."""
    return (piece[:, None, :] * stride).sum(-1) if stride.ndim == 2 else (piece * stride).sum(-1)


def cell_degree(joints, degree: int, pieces: int, samples: int, cut: Optional[int] = None) -> int:
    """The highest total degree ``<= degree`` whose polynomial over ``joints`` (a number, or the sizes of the groups
    whose effects add up: ``polynomial.term_count``) has ``SAMPLES_PER_TERM`` samples per term in each of the
    ``pieces ** cut`` cells of its ``cut`` cutting joints (None: all its joints) when ``samples`` spread evenly (at
    least 1)."""
    sizes = (joints,) if isinstance(joints, (int, np.integer)) else tuple(joints)
    room = samples / (SAMPLES_PER_TERM * pieces ** (sum(sizes) if cut is None else int(cut)))
    return max([1] + [d for d in range(1, degree + 1) if term_count(sizes, d) <= room])


def cell_cuts(crossing: np.ndarray, blocks: np.ndarray, rule: str) -> np.ndarray:
    """``(M, N)`` bool: the joints that cut each muscle's box (``crossing (M, N)`` bool) into cells by ``rule``
    (``PathConfig.cell_joints``, checked). ``"crossed"``: every joint it crosses; ``"largest_group"``: only the
    joints of its largest groups of ``blocks`` (``polynomial.check_blocks``), the others left whole (BIClong: 8 cells
    over its shoulder, its elbow whole, instead of 32 over both)."""
    if rule == "crossed":
        return crossing.copy()
    size = ((blocks[:, :, None] == blocks[:, None, :]) & crossing[:, None, :]).sum(-1)  # each joint's group's size
    size = np.where(crossing, size, 0)
    return crossing & (size == size.max(1, keepdims=True))


def cell_layout(crossing: np.ndarray, exponents: np.ndarray, term_mask: np.ndarray, degrees: np.ndarray,
                pieces: int, cut: np.ndarray) -> tuple:
    """The cell layout, in numpy (a skeleton is built on the meta device), from each muscle's cell degree ``degrees
    (M,)`` (0: no cells) and its cutting joints ``cut (M, N)`` (``cell_cuts``):
    ``muscles (Mc,)``, ``strides (Mc, N)`` (``pieces ** rank`` on the joints each cuts, 0 elsewhere), the cell terms'
    ``exponents (C, N + E)`` (each celled muscle's own terms up to its cell degree, in ``cell_inputs``' coordinates),
    each muscle's term columns ``order (Mc, K)`` (padding on column 0) and ``valid (Mc, K)``, the most cells of a
    muscle, and ``extra (E,)``: the joints some celled muscle crosses uncut."""
    muscles = np.flatnonzero(degrees > 0)
    mask = term_mask[muscles] & (exponents.sum(1)[None, :] <= degrees[muscles, None])
    uncut = crossing[muscles] & ~cut[muscles]
    extra = np.flatnonzero(uncut.any(0))
    own, term = np.nonzero(mask)  # each muscle's terms in order
    rows = np.concatenate([term[:, None], exponents[term] * cut[muscles][own],
                           (exponents[term] * uncut[own])[:, extra]], 1)
    keys, column = np.unique(rows, axis=0, return_inverse=True)  # by whole-box term, then its cut pattern
    counts = mask.sum(1)
    width, most = (int(counts.max()), int(cut[muscles].sum(1).max())) if len(muscles) else (1, 0)
    valid = np.arange(width)[None, :] < counts[:, None]
    order = np.zeros((len(muscles), width), np.int64)
    order[valid] = column.reshape(-1)
    rank = np.cumsum(cut[muscles], 1) - 1
    strides = np.where(cut[muscles], pieces ** np.maximum(rank, 0), 0)
    cell_exponents = keys[:, 1:] if len(keys) else np.zeros((1, exponents.shape[1] + len(extra)), np.int64)
    return muscles, strides, cell_exponents, order, valid, pieces ** most, extra


def cell_inputs(path, x):
    """Each joint's piece ``k (B, N)`` and the cells' coordinates ``z (B, N + E)`` at ``x (B, N)`` (numpy or torch)
    of a ``PerMusclePath`` or its snapshot: every joint's local coordinate (``cell_coordinates``), then the joints
    ``cell_extra`` as they are."""
    k, x_local = cell_coordinates(x, path.pieces)
    if not len(path.cell_extra):
        return k, x_local
    return k, namespace(x).concatenate([x_local, take(x, path.cell_extra, 1)], 1)


def evaluate_cells(path, x: torch.Tensor, y: torch.Tensor, dy):
    """``y (B, M)`` and ``dy (B, M, N)`` (or None; both written in place) with every celled muscle's cell polynomial
    where its cell was fitted, at ``x`` inside the box (float64): per group of muscles sharing joints and cell terms,
    the postures sorted by cell, one basis and product per cell (exported: ``snapshot.PathSnapshot``)."""
    k, z = cell_inputs(path, x)
    for (start, end, width), terms in zip(path.cell_group_bounds, path.cell_terms):
        members = path.cell_perm[start:end]
        cell = cell_index(k, path.cell_stride[members[0]])  # (B,): shared by the group
        order = torch.argsort(cell)  # the postures sorted by cell
        coef = path.cell_coef[members, :, :width]  # (Mg, C, K)
        parts = [terms.contract(terms(rows, dy is not None), coef[:, c])
                 for c, rows in enumerate(z[order].split(torch.bincount(cell).tolist())) if len(rows)]
        inverse = torch.argsort(order)
        muscles = path.cell_muscles[members]
        fitted = path.cell_fitted[members][:, cell].T  # (B, Mg)
        y[:, muscles] = torch.where(fitted, torch.cat([part[0] for part in parts])[inverse], y[:, muscles])
        if dy is not None:  # d/dz (B, Mg, N + E) as d/dx: d x_local / d x = pieces; a joint kept whole its own column
            n = path.cell_stride.shape[1]
            dz = torch.cat([part[1] for part in parts])[inverse]
            dx = dz[..., :n] * path.pieces
            dx = dx + dz[..., n:] @ path.cell_unfold if len(path.cell_extra) else dx
            dy[:, muscles] = torch.where(fitted[:, :, None], dx, dy[:, muscles])
    return y, dy


def set_cell_layout(path, degrees) -> None:
    """A ``PerMusclePath``'s cells for each muscle's cell degree ``(M,)`` (0: no cells): the layout, each group's
    and every cell term (``basis.ProductTerms``), the snapshot's terms and zero cell coefficients, none fitted."""
    values = check_degrees(degrees, len(path.coef), 0, "cell_degrees")
    *layout, valid, n_cells, extra = cell_layout(*path._cell_sources, values, path.pieces, path.cell_cut)
    # the celled muscles grouped by equal joints and cell terms: ``perm`` (group by group, each in muscle order) and
    # each group's (start, end, number of terms) in it
    inverse = np.unique(np.concatenate([layout[1], layout[3]], 1), axis=0, return_inverse=True)[1].reshape(-1)
    perm, ends = np.argsort(inverse, kind="stable"), np.cumsum(np.bincount(inverse)).tolist()
    path.cell_group_bounds = [(end - count, end, int(valid[perm[end - count]].sum()))
                              for end, count in zip(ends, np.bincount(inverse).tolist())]
    device = path.coef.device  # (a fit sets the cells on its own device, a GPU's too)
    path.cell_terms = nn.ModuleList(ProductTerms(layout[2][layout[3][perm[start], :width]])
                                    for start, _, width in path.cell_group_bounds).to(device)  # each group's
    _set_few_terms(path, layout[2], extra)
    derived = zip(("cell_degrees", "cell_muscles", "cell_stride", "cell_exponents", "cell_order", "cell_valid",
                   "cell_perm", "cell_rows", "cell_extra", "cell_unfold"),  # unfold (E, N): the joints kept whole
                  (values, *layout, valid, perm, np.arange(len(layout[0])), extra,
                   np.eye(path.crossing.shape[1])[extra]))
    for name, value in derived:
        path.register_buffer(name, torch.as_tensor(value, device=device), persistent=False)
    shape = (len(layout[0]), n_cells)
    path.register_buffer("cell_coef", torch.zeros(*shape, valid.shape[1], dtype=torch.float64, device=device))
    path.register_buffer("cell_fitted", torch.zeros(*shape, dtype=torch.bool, device=device))


def _set_few_terms(path, cell_exponents: np.ndarray, extra: np.ndarray) -> None:
    """``few_terms``: the whole-box and the cell terms over ``snapshot.PathSnapshot``'s variables (the joints, then
    ``cell_inputs``' coordinates), each slope into its joint's column times ``few_scale`` (on a local one: pieces)."""
    exponents, n_joints = path._cell_sources[1], path.crossing.shape[1]
    merged = np.zeros((len(exponents) + len(cell_exponents), 2 * n_joints + len(extra)), np.int64)
    merged[:len(exponents), :n_joints], merged[len(exponents):, n_joints:] = exponents, cell_exponents
    columns = np.concatenate([np.arange(n_joints), np.arange(n_joints), extra])
    path.few_terms = ProductTerms(merged, columns).to(path.coef.device)
    scale = np.ones(len(columns))
    scale[n_joints:2 * n_joints] = path.pieces
    path.register_buffer("few_scale", torch.tensor(scale, device=path.coef.device), persistent=False)
