"""Piecewise muscle paths: a muscle's box of joints cut into cells, one polynomial per cell.

A MuJoCo path wraps on and off spheres and cylinders: its length is smooth in pieces, and a polynomial over the
whole box pays for every piece's seam everywhere (it rings). Over a smaller box the same degree fits far better:
on myoArm, least squares on 80 000 uniform postures, scored on 20 000 others, cutting each crossed joint's range in
two takes DELT1's and TMAJ's median length error from 0.10 to 0.0001 mm and TRIlong's from 0.39 to 0.019 mm
(RESULTS.md "Per-muscle paths on myoArm"). ``fit_cells`` gives the muscles a smooth polynomial fits worst
(candidates: a median residual above ``CELL_MEDIANS`` times the median muscle's) ``pieces ** n`` cells over the
``n`` joints they cross, each its own polynomial in the cell's local coordinates (the joint range of the cell
mapped to [-1, 1], where the Legendre basis is well conditioned), of the highest total degree (at most the muscle's
own) that leaves ``SAMPLES_PER_TERM`` samples per term at an even spread. A cell with fewer samples takes the
highest degree its own samples allow (``thin_cell_terms``) where that halves the whole-box model's median miss on
its samples, else (and when too thin for a first-degree polynomial) it keeps the muscle's whole-box model; a
muscle keeps its cells only where they at least halve its median residual on the fitted samples without a larger
p99. Muscles over the same joints share each cell's normal equations (one solve, a right-hand side per muscle): a
loop over such groups and their cells, none over muscles.

A wrap can switch sides inside a cell: the length jumps there (17 to 20 mm on myoArm's shoulder, BIClong, TMAJ,
DELT1), and one polynomial over both sides rings over the whole cell. With ``PerMusclePath(cell_trim=factor)`` each
cell is refitted without the samples it misses by more than ``factor`` times the kept ones' median (``_trimmed``):
it then fits the larger side and misses the smaller one by about the jump.

Which joints cut a box: every joint the muscle crosses, or with ``PerMusclePath(cell_joints="largest_group")`` only
those of its largest group of joints whose effects on the length add up (``cell_cuts``). BIClong's length is a
shoulder part plus an elbow part and only the shoulder part jumps: 8 cells over the shoulder leave each four times
the samples of 32 over both, and each cell's polynomial takes the elbow's joints as they are (the cells'
coordinates ``cell_inputs``: every joint's local one, then those joints).

The length at a posture is its cell's polynomial and the moment arm that polynomial's exact derivative: the learned
length steps by about the fit's error where a posture crosses into the next cell, and a QP at one posture sees
that posture's cell only. Joints a muscle does not cross do not cut its box (exactly zero moment arm there).
Plain PyTorch, no Lightning.
"""
from __future__ import annotations

from typing import Optional

import numpy as np
import torch
from torch.nn import functional as F

from ..errors import BodySchemaInputError
from .basis import product_basis
from .branches import SAMPLES_PER_TERM
from .degrees import term_count
from .path_config import CELL_JOINTS
from .trim import trimmed_refits

CELL_MEDIANS = 4.0  # a candidate's median residual exceeds this many times the median muscle's
CELL_FLOOR = 1e-7  # and this (normalized length units: a fraction of the muscle's length spread)
CELL_GAIN = 2.0  # kept cells divide the muscle's median residual on the fitted samples at least by this
CELL_RIDGE = 1e-12  # each cell's ridge, times the mean of its normal equations' diagonal (the basis is local)
CELL_TRIM_ROUNDS = 20  # refits of a trimmed cell at most (it stops when its kept samples stop changing)


def cell_coordinates(x: torch.Tensor, pieces: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Each joint's piece ``k (B, N)`` (long, 0..pieces-1, of [-1, 1] cut evenly) and the local coordinate
    ``x_local (B, N)`` in [-1, 1] within it; ``d x_local / d x = pieces``."""
    scaled = pieces * (x + 1)
    k = torch.clamp(torch.floor(scaled / 2), 0, pieces - 1)
    return k.to(torch.long), scaled - 2 * k - 1


def cell_index(piece: torch.Tensor, stride: torch.Tensor) -> torch.Tensor:
    """Each posture's cell ``(B,)`` or ``(B, Mc)`` from its joints' pieces ``piece (B, N)`` (long) and a muscle's
    ``stride (N,)`` or every celled muscle's ``(Mc, N)``: a product and a sum, not a matrix product (CUDA has none for
    integers)."""
    return (piece[:, None, :] * stride).sum(-1) if stride.dim() == 2 else (piece * stride).sum(-1)


def cell_degree(joints, degree: int, pieces: int, samples: int, cut: Optional[int] = None) -> int:
    """The highest total degree ``<= degree`` whose polynomial over ``joints`` (a number, or the sizes of the groups
    whose effects add up: ``degrees.term_count``) has ``SAMPLES_PER_TERM`` samples per term in each of the
    ``pieces ** cut`` cells of its ``cut`` cutting joints (None: all its joints) when ``samples`` spread evenly (at
    least 1)."""
    sizes = (joints,) if isinstance(joints, (int, np.integer)) else tuple(joints)
    room = samples / (SAMPLES_PER_TERM * pieces ** (sum(sizes) if cut is None else int(cut)))
    return max([1] + [d for d in range(1, degree + 1) if term_count(sizes, d) <= room])


def cell_cuts(crossing: np.ndarray, blocks: np.ndarray, rule: str) -> np.ndarray:
    """``(M, N)`` bool: the joints that cut each muscle's box into cells. ``"crossed"``: every joint it crosses;
    ``"largest_group"``: only the joints of its largest group of ``blocks`` (``per_muscle.check_blocks``; each tied
    group), the others left whole: a group of one or two joints (BIClong's elbow next to its shoulder) a polynomial
    fits over its whole range, and cutting it too would split every cell of the group that needs the cells."""
    if rule not in CELL_JOINTS:
        raise BodySchemaInputError(f"cell_joints={rule!r}; allowed: {list(CELL_JOINTS)}")
    crossing = np.asarray(crossing, dtype=bool)
    if rule == "crossed":
        return crossing.copy()
    blocks = np.asarray(blocks)
    size = ((blocks[:, :, None] == blocks[:, None, :]) & crossing[:, None, :]).sum(-1)  # each joint's group's size
    size = np.where(crossing, size, 0)
    return crossing & (size == size.max(1, keepdims=True))


def cell_layout(crossing: np.ndarray, exponents: np.ndarray, term_mask: np.ndarray, degrees: np.ndarray,
                pieces: int, cut: Optional[np.ndarray] = None) -> tuple:
    """Which muscles have cells and how they are laid out, from each muscle's cell degree ``degrees (M,)`` (0: no
    cells) and the joints that cut its box ``cut (M, N)`` (``cell_cuts``; None: every crossed joint), in numpy (a
    checkpoint's skeleton is built on the meta device): ``muscles (Mc,)``, ``strides (Mc, N)`` (``pieces ** rank``
    on the joints each cuts, rank among them; 0 elsewhere), the cell terms' ``exponents (C, N + E)`` (each celled
    muscle's own terms of total degree at most its cell degree, in the cells' coordinates: every joint's local one,
    then the E joints ``extra (E,)`` that some celled muscle crosses uncut, as they are), each muscle's term columns
    ``order (Mc, K)`` (its own first, padding on column 0) and ``valid (Mc, K)``, the number of cells of the muscle
    with the most, and ``extra``."""
    cut = crossing if cut is None else cut
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


def cell_groups(strides: np.ndarray, order: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, list]:
    """The celled muscles grouped by equal joints and cell terms: ``perm (Mc,)`` (group by group, each in muscle
    order) and each group's ``(start, end, width)`` in that order (its rows of ``perm``, its number of terms)."""
    inverse = np.unique(np.concatenate([strides, order], 1), axis=0, return_inverse=True)[1].reshape(-1)
    perm = np.argsort(inverse, kind="stable")
    ends = np.cumsum(np.bincount(inverse)).astype(np.int64)
    starts = ends - np.bincount(inverse)
    return perm, [(int(a), int(b), int(valid[perm[a]].sum())) for a, b in zip(starts, ends)]


def cell_inputs(path, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Each joint's piece ``k (B, N)`` and the cells' coordinates ``z (B, N + E)`` at ``x (B, N)``: every joint's
    local coordinate (``cell_coordinates``), then the joints ``cell_extra`` some celled muscle crosses uncut, as they
    are (in an exported program by padding and a one-hot product: a concatenation specializes the batch in
    torch.export; the same values)."""
    k, x_local = cell_coordinates(x, path.pieces)
    extra = len(path.cell_extra)
    if not extra:
        return k, x_local
    if not torch.compiler.is_exporting():  # two operations, not five (at one posture each costs its dispatch)
        return k, torch.cat([x_local, x.index_select(1, path.cell_extra)], 1)
    return k, F.pad(x_local, (0, extra)) + F.pad(x @ path.cell_unfold.T, (x.shape[1], 0))


def _fold(path, dz: torch.Tensor) -> torch.Tensor:
    """Slopes ``d/dz (..., N + E)`` in the cells' coordinates as ``d/dx (..., N)``: ``d x_local / d x = pieces``."""
    n = path.cell_stride.shape[1]
    dx = dz[..., :n] * path.pieces
    return dx + dz[..., n:] @ path.cell_unfold if len(path.cell_extra) else dx


def evaluate_cells(path, x: torch.Tensor, y: torch.Tensor, dy):
    """``y (B, M)`` and ``dy (B, M, N)`` (or None) with every celled muscle's cell polynomial where its cell was
    fitted; ``x`` is inside the box, float64. A loop over the groups of muscles that share joints and cell terms (a
    posture's cell and basis are the group's), the postures sorted by cell and each cell's one matrix product (no
    ``(B, muscles, terms)`` gathers); an exported program gathers each muscle's cell coefficients for one basis of
    every cell term (one path for any batch). Few postures in eager: ``networks.snapshot``."""
    k, z = cell_inputs(path, x)
    if torch.compiler.is_exporting():
        cell = cell_index(k, path.cell_stride)  # (B, Mc): each celled muscle's cell
        basis = path.cell_terms_all(z, dy is not None, dense=True)
        y_cell, dy_cell = _contract(path, basis, cell)
        dy_cell = None if dy is None else _fold(path, dy_cell)
        return _replace(y, dy, path.cell_muscles, path.cell_fitted[path.cell_rows, cell], y_cell, dy_cell)
    y, dy = y.clone(), None if dy is None else dy.clone()  # written in place below, group by group
    for (start, end, width), terms in zip(path.cell_group_bounds, path.cell_terms):
        members = path.cell_perm[start:end]
        cell = cell_index(k, path.cell_stride[members[0]])  # (B,): shared by the group
        y_cell, dy_cell = _by_cell(terms, path.cell_coef[members, :, :width], z, cell, dy is not None)
        y, dy = _replace(y, dy, path.cell_muscles[members], path.cell_fitted[members][:, cell].T, y_cell,
                         None if dy_cell is None else _fold(path, dy_cell), copy=False)
    return y, dy


def cell_spread(path) -> torch.Tensor:
    """Every celled muscle's coefficients in each of its cells spread on every cell term, ``(Mc, C, T)``: zero off
    its own terms (a sum: the padding's zeros land on column 0 too). The evaluation at few postures takes a
    posture's cell's rows (``networks.snapshot.PathSnapshot``: one index, not a gather and a scatter per call)."""
    coef = path.cell_coef
    index = path.cell_order[:, None, :].expand(-1, coef.shape[1], -1)
    return coef.new_zeros(*coef.shape[:2], len(path.cell_exponents)).scatter_add_(2, index, coef)


def _contract(path, basis, cell: torch.Tensor):
    """Each celled muscle's cell polynomial ``(B, Mc)`` and its slopes ``(B, Mc, N + E)`` (or None) at its posture's
    ``cell (B, Mc)`` from a dense basis of every cell term, in an exported program: each muscle's own columns of the
    basis times its cell's coefficients (a gather; a scatter would specialize the batch under vmap)."""
    coef, order = path.cell_coef[path.cell_rows[None, :], cell], path.cell_order
    y = (basis.phi[:, order] * coef).sum(-1)
    return y, None if basis.dphi is None else torch.einsum("bmkn,bmk->bmn", basis.dphi[:, order], coef)


def _by_cell(terms, coef, z, cell, slopes):
    """A group's cell polynomials ``(B, Mg)``, ``(B, Mg, N + E)`` (d/dz, ``cell_inputs``; or None) at the cells'
    coordinates ``z (B, N + E)``, from its cells' coefficients
    ``coef (Mg, C, K)``: the postures sorted by ``cell (B,)``, then per cell its postures' basis and one
    ``terms.contract`` (a loop over the cells; each cell's basis is a block of rows, never the whole batch's)."""
    order = torch.argsort(cell)
    x_sorted = z[order]
    y = z.new_empty(len(z), len(coef))
    dy = z.new_empty(len(z), len(coef), z.shape[1]) if slopes else None
    start = 0
    for c, count in enumerate(torch.bincount(cell).tolist()):
        if count:
            rows = slice(start, start + count)
            y[rows], dy_c = terms.contract(terms(x_sorted[rows], slopes), coef[:, c])
            if slopes:
                dy[rows] = dy_c
            start += count
    inverse = torch.argsort(order)
    return y[inverse], None if dy is None else dy[inverse]


def _replace(y, dy, muscles, fitted, y_cell, dy_cell, copy: bool = True):
    """``y``, ``dy`` with the cells' ``y_cell (B, Mc)``, ``dy_cell (B, Mc, N)`` (d/dx, ``_fold``) of ``muscles`` where
    their cell was ``fitted (B, Mc)`` (copies, or with ``copy=False`` written in place)."""
    y = y.clone() if copy else y
    y[:, muscles] = torch.where(fitted, y_cell, y[:, muscles])
    if dy is not None:
        dy = dy.clone() if copy else dy
        dy[:, muscles] = torch.where(fitted[:, :, None], dy_cell, dy[:, muscles])
    return y, dy


@torch.no_grad()
def fit_cells(path, x: torch.Tensor, y: torch.Tensor, chunk: int = 8192) -> None:
    """Cells for the muscles of a fitted ``PerMusclePath`` that a smooth polynomial fits worst (module docstring):
    sets the path's cell layout (``PerMusclePath.set_cell_degrees``) and coefficients, and clears ``branched`` where
    cells replace the branches. ``x (S, N)``, ``y (S, M)`` float64, normalized."""
    path.set_cell_degrees(torch.zeros_like(path.cell_degrees))
    r = torch.cat([y[i:i + chunk] - path(x[i:i + chunk]) for i in range(0, len(x), chunk)]).abs()
    median = r.median(0).values
    candidates = (median > CELL_MEDIANS * median.median()) & (median > CELL_FLOOR)
    if not bool(candidates.any()):
        return
    total = path.exponents.sum(1)
    own_degree = (total[None, :] * path.term_mask).amax(1)
    cuts = path.cell_cut.sum(1).tolist()  # each muscle's cutting joints
    path.set_cell_degrees(torch.tensor([cell_degree(a, int(d), path.pieces, len(x), n) if c else 0
                                        for a, d, c, n in zip(path.block_sizes, own_degree, candidates, cuts)],
                                       device=median.device))
    _fit_each_cell(path, x, y[:, path.cell_muscles], r[:, path.cell_muscles], chunk)
    muscles = path.cell_muscles
    miss = torch.cat([y[i:i + chunk, muscles] - path(x[i:i + chunk])[:, muscles] for i in range(0, len(x), chunk)])
    miss, own = miss.abs(), r[:, muscles]
    keep = _kept(miss, own, path.cell_keep)
    coef, fitted = path.cell_coef[keep], path.cell_fitted[keep]
    degrees = path.cell_degrees.clone()
    degrees[muscles[~keep]] = 0
    path.set_cell_degrees(degrees)  # the kept muscles' own terms come first in either layout: same columns
    path.cell_coef.copy_(coef[:, :path.cell_coef.shape[1], :path.cell_coef.shape[2]])
    path.cell_fitted.copy_(fitted[:, :path.cell_fitted.shape[1]])
    if hasattr(path, "branched"):
        path.branched[path.cell_muscles] = False


def _kept(miss: torch.Tensor, own: torch.Tensor, rule: str) -> torch.Tensor:
    """``(Mc,)`` which celled muscles keep their cells, from their cells' and their whole-box model's residuals on
    the fitted samples ``(S, Mc)``: the median divided by ``CELL_GAIN`` at least, and with ``"median_and_p99"`` no
    larger p99 (cells that ring). ``"median"``: the median alone; where a trimmed cell misses the smaller side of a
    jump that its whole-box model (two branches) only rings over, the p99 rises while the rest of the muscle's
    postures, and their moment arms, become far better (myoArm's LAT1 and LAT2: median moment-arm error 0.07 ->
    0.001 mm/rad)."""
    keep = miss.median(0).values * CELL_GAIN <= own.median(0).values
    if rule == "median_and_p99":
        keep &= torch.quantile(miss, 0.99, dim=0) <= torch.quantile(own, 0.99, dim=0)
    return keep


def _fit_each_cell(path, x, y_m, own, chunk):
    """Least squares of every celled muscle's cells into ``path.cell_coef (Mc, C, K)`` (0 on padded terms) and
    ``path.cell_fitted (Mc, C)``: a cell of fewer samples than its terms need takes fewer terms
    (``thin_cell_terms``), and only where it halves the median miss of the muscle's whole-box model ``own (S, Mc)``
    on its samples (a plane can be worse than a good whole-box polynomial). Muscles over the same joints with the same
    cell terms share their cells' normal equations (the shoulder's muscles: one system per cell for all of them, one
    right-hand side each): a loop over such groups and their cells."""
    k, z = cell_inputs(path, x)
    for start, end, width in path.cell_group_bounds:  # a loop over groups of muscles that share joints and terms
        members = path.cell_perm[start:end]
        first = int(members[0])
        exponents = path.cell_exponents[path.cell_order[first, :width]]
        phi = torch.cat([product_basis(z[i:i + chunk], exponents, int(exponents.max()))[0]
                         for i in range(0, len(x), chunk)])
        cell = cell_index(k, path.cell_stride[first])
        totals = exponents.sum(1).tolist()  # each column's total degree, nondecreasing (the whole-box terms' order)
        for c in range(path.pieces ** int((path.cell_stride[first] > 0).sum())):  # a loop over the group's cells
            rows = torch.nonzero(cell == c).flatten()
            terms = thin_cell_terms(totals, len(rows))
            if not terms:  # too few samples for a first-degree polynomial: the whole-box polynomial stays
                continue
            phi_c, y_c = phi[rows, :terms], y_m[rows][:, members]
            gram, rhs = phi_c.T @ phi_c, phi_c.T @ y_c
            eye = torch.eye(terms, dtype=torch.float64, device=x.device)
            solution = torch.linalg.solve(gram + CELL_RIDGE * gram.diagonal().mean() * eye, rhs)
            if path.cell_trim is not None:
                solution = _trimmed(phi_c, y_c, gram, rhs, solution, path.cell_trim, SAMPLES_PER_TERM * terms)
            better = torch.ones(len(members), dtype=torch.bool, device=x.device)
            if terms < width:  # a thin cell replaces the whole-box polynomial only where it halves its miss there
                miss = (phi_c @ solution - y_c).abs().median(0).values
                better = miss * CELL_GAIN <= own[rows][:, members].median(0).values
            path.cell_coef[members[better], c, :terms] = solution.T[better]
            path.cell_fitted[members[better], c] = True


def thin_cell_terms(totals: list, samples: int) -> int:
    """How many of a cell's leading terms (``totals``: each term's total degree, nondecreasing) its ``samples`` fit:
    all of them with ``SAMPLES_PER_TERM`` samples each, else those of the highest total degree >= 1 that leaves as
    many (a cell thinner than the even spread the cell degree assumed: trimming, a joint sampled unevenly), else 0.
    Before, such a cell kept the whole-box polynomial, which for a muscle whose path jumps misses by tens of mm
    (myoArm's LAT1 at 200 000 samples: 11 of 64 cells); ``_fit_each_cell`` keeps such a cell only where it does
    better."""
    for degree in sorted(set(totals), reverse=True):
        count = sum(1 for t in totals if t <= degree)
        if degree >= 1 and count * SAMPLES_PER_TERM <= samples:
            return count
    return 0


def _trimmed(phi, y, gram, rhs, solution, factor: float, least: int) -> torch.Tensor:
    """Each muscle's cell polynomial ``(K, Mg)`` refitted without the samples it misses by more than ``factor`` times
    the kept ones' median (``trim.trimmed_refits`` per muscle, up to ``CELL_TRIM_ROUNDS`` refits), from
    ``phi (S, K)``, ``y (S, Mg)``, the whole cell's normal equations ``gram``, ``rhs`` and their ``solution``; each
    refit updates every muscle's normal equations by the rows whose side changed only (few after the first). A
    muscle keeps every sample where fewer than ``least`` would stay.

    Where a wrap switches sides inside the cell the length jumps (17 to 20 mm on myoArm's shoulder); one
    polynomial over both sides rings over the whole cell, millimetres far from the jump. Trimmed, it fits the
    larger side to the micrometre and misses the smaller by about the jump."""
    system, b = gram.expand(y.shape[1], -1, -1).clone(), rhs.T.clone()  # (Mg, K, K), (Mg, K)
    eye = torch.eye(len(gram), dtype=gram.dtype, device=gram.device)
    fitted = [solution]

    def refit(keep, new):
        rows = torch.nonzero((new != keep).any(1)).flatten()
        phi_r, sign = phi[rows], new[rows].to(phi.dtype) - keep[rows].to(phi.dtype)  # +1 back in, -1 dropped
        system.add_((phi_r.T[None] * sign.T[:, None, :]) @ phi_r)
        b.add_((sign * y[rows]).T @ phi_r)
        ridge = CELL_RIDGE * system.diagonal(dim1=1, dim2=2).mean(1)[:, None, None] * eye
        fitted[0] = torch.linalg.solve(system + ridge, b.unsqueeze(-1)).squeeze(-1).T
    trimmed_refits(lambda p: p @ fitted[0], phi, y, refit, factor, CELL_TRIM_ROUNDS, len(phi), True, least)
    return fitted[0]
