"""The fit of a per-muscle path's cells (``networks.cells``: the layout and the evaluation): which muscles get cells
(a median residual above ``CELL_MEDIANS`` times the median muscle's and above ``CELL_FLOOR``), each cell's least
squares (thin cells fewer terms: ``thin_cell_terms``; with ``cell_trim`` refitted without the samples it misses by
far: ``_trimmed``), and which muscles keep them (``_kept``). Plain PyTorch, no Lightning."""
from __future__ import annotations

import torch

from .basis import product_basis
from .branches import SAMPLES_PER_TERM, refresh_branches
from .cells import cell_degree, cell_index, cell_inputs, set_cell_layout
from .polynomial import solve_systems
from .trim import trimmed_refits

CELL_MEDIANS = 4.0  # a candidate's median residual exceeds this many times the median muscle's
CELL_FLOOR = 1e-7  # and this (normalized length units: a fraction of the muscle's length spread)
CELL_GAIN = 2.0  # kept cells divide the muscle's median residual on the fitted samples at least by this
CELL_RIDGE = 1e-12  # each cell's ridge, times the mean of its normal equations' diagonal (the basis is local)
CELL_TRIM_ROUNDS = 20  # refits of a trimmed cell at most (it stops when its kept samples stop changing)


@torch.no_grad()
def fit_cells(path, x: torch.Tensor, y: torch.Tensor, chunk: int = 8192) -> None:
    """Cells for the muscles of a fitted ``PerMusclePath`` that a smooth polynomial fits worst (module docstring):
    sets the path's cell layout (``cells.set_cell_layout``) and coefficients, and clears ``branched`` where
    cells replace the branches (``branched.refresh_branches``). ``x (S, N)``, ``y (S, M)`` float64, normalized."""
    set_cell_layout(path, torch.zeros_like(path.cell_degrees))
    r = torch.cat([y[i:i + chunk] - path(x[i:i + chunk]) for i in range(0, len(x), chunk)]).abs()
    median = r.median(0).values
    candidates = (median > CELL_MEDIANS * median.median()) & (median > CELL_FLOOR)
    if not bool(candidates.any()):
        return
    total = path.exponents.sum(1)
    own_degree = (total[None, :] * path.term_mask).amax(1)
    cuts = path.cell_cut.sum(1).tolist()  # each muscle's cutting joints
    set_cell_layout(path, torch.tensor([cell_degree(a, int(d), path.pieces, len(x), n) if c else 0
                                        for a, d, c, n in zip(path.block_sizes, own_degree, candidates, cuts)],
                                       device=median.device))
    _fit_each_cell(path, x, y[:, path.cell_muscles], r[:, path.cell_muscles], chunk)
    muscles = path.cell_muscles
    miss = torch.cat([y[i:i + chunk, muscles] - path(x[i:i + chunk])[:, muscles] for i in range(0, len(x), chunk)])
    keep = _kept(miss.abs(), r[:, muscles], path.config.cell_keep)
    coef, fitted = path.cell_coef[keep], path.cell_fitted[keep]
    degrees = path.cell_degrees.clone()
    degrees[muscles[~keep]] = 0
    set_cell_layout(path, degrees)  # the kept muscles' own terms come first in either layout: same columns
    path.cell_coef.copy_(coef[:, :path.cell_coef.shape[1], :path.cell_coef.shape[2]])
    path.cell_fitted.copy_(fitted[:, :path.cell_fitted.shape[1]])
    if path.branches == 2:
        path.branched[path.cell_muscles] = False
        refresh_branches(path)


def _kept(miss: torch.Tensor, own: torch.Tensor, rule: str) -> torch.Tensor:
    """``(Mc,)`` which celled muscles keep their cells, from their cells' and their whole-box model's residuals on
    the fitted samples ``(S, Mc)``: the median divided by ``CELL_GAIN`` at least, and with ``"median_and_p99"`` no
    larger p99 (cells that ring). ``"median"``: the median alone (a trimmed cell's missed smaller side of a jump
    raises the p99 while the rest of the muscle's postures become far better)."""
    keep = miss.median(0).values * CELL_GAIN <= own.median(0).values
    if rule == "median_and_p99":
        keep &= torch.quantile(miss, 0.99, dim=0) <= torch.quantile(own, 0.99, dim=0)
    return keep


def _fit_each_cell(path, x, y_m, own, chunk):
    """Least squares of every celled muscle's cells into ``path.cell_coef (Mc, C, K)`` (0 on padded terms) and
    ``path.cell_fitted (Mc, C)``: a thin cell takes fewer terms (``thin_cell_terms``), kept only where it halves the
    median miss of the muscle's whole-box model ``own (S, Mc)`` on its samples. Muscles of one group share each
    cell's normal equations (one right-hand side each): a loop over groups and their cells."""
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
            if path.config.cell_trim is not None:
                solution = _trimmed(phi_c, y_c, gram, rhs, solution, path.config.cell_trim, SAMPLES_PER_TERM * terms)
            better = torch.ones(len(members), dtype=torch.bool, device=x.device)
            if terms < width:  # a thin cell replaces the whole-box polynomial only where it halves its miss there
                miss = (phi_c @ solution - y_c).abs().median(0).values
                better = miss * CELL_GAIN <= own[rows][:, members].median(0).values
            path.cell_coef[members[better], c, :terms] = solution.T[better]
            path.cell_fitted[members[better], c] = True


def thin_cell_terms(totals: list, samples: int) -> int:
    """How many of a cell's leading terms (``totals``: each term's total degree, nondecreasing) its ``samples`` fit:
    all of them with ``SAMPLES_PER_TERM`` samples each, else those of the highest total degree >= 1 that leaves as
    many (a cell thinner than the even spread the cell degree assumed), else 0."""
    for degree in sorted(set(totals), reverse=True):
        count = sum(1 for t in totals if t <= degree)
        if degree >= 1 and count * SAMPLES_PER_TERM <= samples:
            return count
    return 0


def _trimmed(phi, y, gram, rhs, solution, factor: float, least: int) -> torch.Tensor:
    """Each muscle's cell polynomial ``(K, Mg)`` refitted without the samples it misses by more than ``factor`` times
    the kept ones' median (``trim.trimmed_refits`` per muscle, up to ``CELL_TRIM_ROUNDS`` refits), from
    ``phi (S, K)``, ``y (S, Mg)``, the whole cell's normal equations ``gram``, ``rhs`` and their ``solution``; each
    refit updates every muscle's normal equations by the rows whose side changed only. A muscle keeps every sample
    where fewer than ``least`` would stay. Where a wrap switches sides inside the cell, the trimmed polynomial fits
    the larger side and misses the smaller by about the jump (one over both rings over the whole cell)."""
    system, b = gram.expand(y.shape[1], -1, -1).clone(), rhs.T.clone()  # (Mg, K, K), (Mg, K)
    every, fitted = torch.ones_like(b, dtype=torch.bool), [solution]

    def refit(keep, new):
        rows = torch.nonzero((new != keep).any(1)).flatten()
        phi_r, sign = phi[rows], new[rows].to(phi.dtype) - keep[rows].to(phi.dtype)  # +1 back in, -1 dropped
        system.add_((phi_r.T[None] * sign.T[:, None, :]) @ phi_r)
        b.add_((sign * y[rows]).T @ phi_r)
        fitted[0] = solve_systems(system, b, every, CELL_RIDGE).T
    trimmed_refits(lambda p: p @ fitted[0], phi, y, refit, factor, CELL_TRIM_ROUNDS, len(phi), True, least)
    return fitted[0]
