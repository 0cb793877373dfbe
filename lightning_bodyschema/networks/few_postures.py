"""A ``PerMusclePath`` at few postures: every part from one basis, in few operations.

A controller asks for the body at one posture, where each tensor operation costs its dispatch (a few microseconds)
rather than its arithmetic. Here the whole-box polynomials, the branches' second polynomials and gates, and the
cells' polynomials share one ``basis.ProductTerms`` over the joint angles, the cells' local coordinates and the
joints the cells keep whole (``PerMusclePath.few_terms``); its ``stacked`` evaluation puts each term and its slopes
d/dx in one tensor (a cell coordinate's slope times ``pieces``, its chain rule: exact for a power of two), so one
product with the whole-box rows and one with the posture's cells' rows give every candidate's length and moment
arms; one gather then picks each muscle's: its cell's polynomial where that cell was fitted, else its gate's branch,
else its whole-box polynomial. myoArm's per-muscle path at one posture: 0.52 -> 0.29 ms (BENCHMARKS.md). The same
values as the blockwise evaluation up to the order of the sums (~1e-13 of a normalized length). Plain PyTorch, no
Lightning.
"""
from __future__ import annotations

from typing import NamedTuple, Optional

import torch

from .cells import cell_index, cell_inputs, cell_spread

# the largest stacked basis of this evaluation: postures x terms (whole-box and cell) x (1 + joints), about 11 MB of
# float64. Above it, blocks of rows and a cell at a time are faster (their slopes touch only the joints each term
# uses). Measured crossovers (`tools/bench_body_eval.py --paths`): myoArm's per-muscle path ~280 postures (13 600
# elements per posture), myoLegs + OSL's ~45 (32 300), myoLegs' ~32 (60 900); this budget keeps each below its own:
# myoArm 102 postures, myoLegs + OSL 43, myoLegs 22, myoHand 241 (BENCHMARKS.md)
FEW_ELEMENTS = 1_400_000


class FewCoefficients(NamedTuple):
    """What ``evaluate_few`` reads from a path's coefficients (``few_coefficients``; a caller may keep it while they
    do not change): ``box (R, P)`` the whole-box rows a posture may use (the muscles without cells fitted everywhere,
    then the branched muscles' second polynomials, then their gates), ``spread (Mc, C, T)`` the cells'
    coefficients on every cell term (``cells.cell_spread``; None without cells), and per muscle ``(M,)`` the
    candidate column of each choice: ``box_col`` (whole box), ``alt_col`` and ``gate_col`` (its branch and gate
    where ``gated``; else ``box_col`` and 0), ``cell_col`` and ``cell_of`` (its cell polynomial and row among the
    celled muscles where ``celled``; else ``box_col`` and 0)."""
    box: torch.Tensor
    spread: Optional[torch.Tensor]
    box_col: torch.Tensor
    alt_col: torch.Tensor
    gate_col: torch.Tensor
    gated: torch.Tensor
    cell_col: torch.Tensor
    cell_of: torch.Tensor
    celled: torch.Tensor


def few_coefficients(path) -> FewCoefficients:
    """``FewCoefficients`` of a fitted ``PerMusclePath`` (its coefficients masked to each muscle's terms)."""
    n_muscles, device = path.coef.shape[0], path.coef.device
    long = dict(dtype=torch.long, device=device)
    celled, everywhere = (torch.zeros(n_muscles, dtype=torch.bool, device=device) for _ in range(2))
    spread, cell_of = None, torch.zeros(n_muscles, **long)
    if _has_cells(path):
        celled[path.cell_muscles] = True
        everywhere[path.cell_muscles] = path.cell_fitted.all(1)  # never a whole-box row
        cell_of[path.cell_muscles] = torch.arange(len(path.cell_muscles), **long)
        spread = cell_spread(path)
    box_muscles = torch.nonzero(~everywhere).flatten()
    box_col = torch.zeros(n_muscles, **long)
    box_col[box_muscles] = torch.arange(len(box_muscles), **long)
    rows, alt_col, gate_col = [(path.coef * path.term_mask)[box_muscles]], box_col.clone(), torch.zeros_like(cell_of)
    if path.branches == 2 and len(path.branched_index):
        branched, count = path.branched_index, len(path.branched_index)
        rows += [path.coef_alt[branched] * path.term_mask[branched], path.gate[branched]]
        alt_col[branched] = len(box_muscles) + torch.arange(count, **long)
        gate_col[branched] = len(box_muscles) + count + torch.arange(count, **long)
    box = torch.cat(rows)
    cell_col = torch.where(celled, len(box) + cell_of, box_col)
    return FewCoefficients(box, spread, box_col, alt_col, gate_col, alt_col != box_col, cell_col, cell_of, celled)


def evaluate_few(path, x64: torch.Tensor, inside: torch.Tensor, coefs: FewCoefficients):
    """Lengths ``y (B, M)`` and slopes ``dy (B, M, N)`` of ``path`` at float64 postures ``x64 (B, N)``, ``inside``
    them clamped to the box (outside, the first-order extension of ``PerMusclePath.polynomial``), from ``coefs``
    (module docstring)."""
    n_box, n_terms = len(coefs.box), path.coef.shape[1]
    cells = _has_cells(path)
    if cells:  # the variables: every joint, then the cells' coordinates (its local one, the joints kept whole)
        piece, z = cell_inputs(path, inside)
        v = torch.cat([inside, z], 1)
    basis = (path.few_terms.stacked(v, path.few_scale) if cells else path.terms.stacked(inside))  # (B, Pt, 1 + N)
    k = basis.shape[-1]
    candidates = (coefs.box @ basis[:, :n_terms].transpose(0, 1).flatten(1)).view(n_box, len(x64), k).transpose(0, 1)
    gate = candidates[:, :, 0].index_select(1, coefs.gate_col)
    choice = torch.where((gate > 0) & coefs.gated, coefs.alt_col, coefs.box_col)
    if cells:
        cell = cell_index(piece, path.cell_stride)  # (B, Mc): each celled muscle's cell
        at_cell = coefs.spread[path.cell_rows[None, :], cell]  # (B, Mc, T)
        candidates = torch.cat([candidates, at_cell @ basis[:, n_terms:]], 1)
        fitted = path.cell_fitted[path.cell_rows[None, :], cell].index_select(1, coefs.cell_of)
        choice = torch.where(fitted & coefs.celled, coefs.cell_col, choice)
    picked = candidates.gather(1, choice[..., None].expand(-1, -1, k))
    y, dy = picked[..., 0], picked[..., 1:]
    return y + (dy @ (x64 - inside)[:, :, None])[..., 0], dy


def few_for(path, x: torch.Tensor) -> bool:
    """Whether ``path`` evaluates postures ``x (B, N)`` here: their stacked basis within ``FEW_ELEMENTS``, never in an
    exported program (one path for any batch there: ``PerMusclePath.polynomial``'s blocks)."""
    terms = len(path.few_terms.exponents) if _has_cells(path) else path.coef.shape[1]
    return not torch.compiler.is_exporting() and len(x) * terms * (1 + x.shape[1]) <= FEW_ELEMENTS


def _has_cells(path) -> bool:
    """Whether ``path`` has celled muscles (their layout set)."""
    return path.pieces > 1 and len(path.cell_muscles) > 0
