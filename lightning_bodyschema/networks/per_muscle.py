"""Per-muscle path models: each muscle's length over only the joints it crosses, with exact moment arms.

``PerMusclePath`` is a polynomial per muscle in a tensor-product Legendre basis of the normalized joint angles, terms
only over the joints the muscle crosses (``networks.polynomial``), fitted by least squares (``fit_polynomial``), plus
optionally a small MLP per muscle (``networks.muscle_mlp``), two branches and a gate (``networks.branches``) and cells
(``networks.cells``) where one polynomial rings. ``with_jacobian(x)`` gives the lengths and their exact derivative,
exactly 0 on a joint a muscle does not cross. Plain PyTorch, no Lightning.
"""
from __future__ import annotations

from dataclasses import replace
from typing import Optional

import numpy as np
import torch
from torch import nn

from .arrays import apply_keeping_dtype, pick
from .basis import ProductTerms, product_basis
from .branches import add_branches, fit_branches, one_thread, refresh_branches
from .cell_fit import fit_cells
from .cells import cell_cuts, evaluate_cells, set_cell_layout
from .muscle_mlp import muscle_mlp, muscle_mlp_parameters
from .path_config import PathConfig
from .polynomial import (block_sizes, check_blocks, check_crossing, check_degrees, muscle_degrees,
                         solve_normal_equations, term_exponents, term_mask)
from .snapshot import PathSnapshot
from .trim import trimmed_refits

BASIS_ELEMENTS = 2 ** 19  # rows x terms of one block of ``PerMusclePath.polynomial`` (BENCHMARKS.md)


@torch.no_grad()
def degrees_within_tolerance(crossing, x: torch.Tensor, y: torch.Tensor, scale: torch.Tensor, degree: int,
                             max_terms: int, budget: int, tolerance: float, blocks=None) -> np.ndarray:
    """Each muscle's degree when a term budget goes only where it is needed: a first one-polynomial fit with at most
    ``max_terms`` terms per muscle on ``x (S, N)``, ``y (S, M)``; the muscles whose p99 residual times ``scale (M,)``
    exceeds ``tolerance`` (same units) then share ``budget`` (``muscle_degrees`` with ``eligible``)."""
    first = PerMusclePath(crossing, degree=degree, n_hidden=0, max_terms=max_terms, blocks=blocks).to(x.device)
    first.fit_polynomial(x, y)
    p99 = torch.quantile((first(x.to(torch.float64)) - y.to(torch.float64)).abs() * scale.to(x.device), 0.99, dim=0)
    return muscle_degrees(crossing, degree, max_terms, budget, (p99 > tolerance).cpu().numpy(), blocks)


class PerMusclePath(nn.Module):
    """Lengths ``y (B, M)`` of M muscles at normalized postures ``x (B, N)`` (module docstring).

    Args:
        crossing: ``(M, N)`` bool array (numpy or nested lists), which joints each muscle crosses.
        config: the options (``networks.path_config.PathConfig``: degrees and term budgets, the per-muscle MLP,
            branches, cells, blocks); ``options``: the same by name, instead of or over ``config``.
    """

    def __init__(self, crossing, config: Optional[PathConfig] = None, **options):
        super().__init__()
        config = replace(config or PathConfig(), **options).checked()
        crossing = check_crossing(crossing)
        blocks = check_blocks(crossing, config.blocks)
        n_muscles, n_joints = crossing.shape
        self.config = config  # the fit's options (gate degree, cell trim and keep rule), not the state's
        self.n_hidden, self.branches, self.pieces = config.n_hidden, config.branches, config.cells
        self.block_sizes = block_sizes(blocks)  # per muscle, the joints in each group (term counts)
        degrees = muscle_degrees(crossing, config.degree, config.max_terms, config.term_budget, blocks=blocks) \
            if config.degrees is None else check_degrees(config.degrees, len(crossing))
        self.degree = int(degrees.max())
        exponents = term_exponents(blocks, degrees)
        self.register_buffer("crossing", torch.tensor(crossing))
        self.register_buffer("exponents", torch.tensor(exponents))
        self.terms = ProductTerms(exponents)  # the evaluation's basis, a support at a time (no state-dict entry)
        mask = term_mask(blocks, exponents, degrees)
        self.register_buffer("term_mask", torch.tensor(mask))  # (M, P)
        self.register_buffer("coef", torch.zeros(n_muscles, len(exponents), dtype=torch.float64))
        if self.branches == 2:  # a second polynomial per muscle and a gate whose sign picks it (networks.branches)
            add_branches(self)
        if self.pieces > 1:  # cells per muscle (networks.cells); which muscles, and their layout, follow the fit
            self._cell_sources = (crossing, exponents, mask)  # numpy: a skeleton's buffers hold no values
            self.cell_cut = cell_cuts(crossing, blocks, config.cell_joints)  # (M, N) numpy: the joints that cut boxes
            set_cell_layout(self, np.zeros(n_muscles, np.int64) if config.cell_degrees is None else config.cell_degrees)
        # the box of the fitted samples (normalized units); outside it the polynomial is extended to first order
        self.register_buffer("x_lo", -torch.ones(n_joints, dtype=torch.float64))
        self.register_buffer("x_hi", torch.ones(n_joints, dtype=torch.float64))
        self.weights, self.biases = muscle_mlp_parameters(n_muscles, n_joints, config.hidden, self.n_hidden)

    # ------------------------------------------------------------------ the polynomial
    def basis(self, x: torch.Tensor, slopes: bool = False):
        """``phi (B, P)`` and, with ``slopes``, ``dphi/dx (B, N, P)`` of every term (``product_basis``)."""
        return product_basis(x, self.exponents, self.degree, slopes)

    def polynomial(self, x: torch.Tensor, slopes: bool = False, snapshot: Optional[PathSnapshot] = None):
        """The polynomial part, evaluated in float64: ``(B, M)`` and, with ``slopes``, ``(B, M, N)``, in x's dtype;
        ``snapshot``: ``snapshot()`` when the caller keeps it. Inside the box of the fitted samples (``x_lo``,
        ``x_hi``) the polynomial itself; outside, its first-order extension from the nearest point ``c`` of the box,
        ``p(c) + p'(c) (x - c)``, with moment arms ``p'(c)``. At few postures (``PathSnapshot.max_postures``) and
        exported (any batch) the snapshot; above, the snapshot's candidate rows in blocks of rows (a grouped basis),
        each muscle's row chosen as the snapshot chooses, the cells a cell at a time."""
        x64 = x.to(torch.float64)
        snapshot = self.snapshot() if snapshot is None else snapshot
        if torch.compiler.is_exporting() or len(x) <= snapshot.max_postures:
            y, dy, _ = snapshot(x64)
            return y.to(x.dtype), dy.to(x.dtype) if slopes else None
        inside = torch.clamp(x64, self.x_lo, self.x_hi)
        derive = slopes or not torch.equal(inside, x64)
        rows = self.terms.layout(snapshot.box)  # its candidate rows (whole-box, branches, gates), once per call
        blocks = inside.split(max(1, BASIS_ELEMENTS // self.coef.shape[1]))
        parts = [self.terms.contract(self.terms(block, derive, dense=False), rows) for block in blocks]
        y, dy = parts[0] if len(parts) == 1 else (torch.cat([y for y, _ in parts]),
                                                  torch.cat([dy for _, dy in parts]) if derive else None)
        choice = snapshot.branch_choice(y)
        y, dy = y.gather(1, choice), None if dy is None else pick(dy, choice)
        if snapshot.cells:
            y, dy = evaluate_cells(self, inside, y, dy)
        if dy is not None:  # (None: no slopes asked, every posture inside the box)
            y = y + (dy @ (x64 - inside)[:, :, None])[..., 0]  # a product: fewer operations than einsum's reshapes
        return y.to(x.dtype), dy.to(x.dtype) if slopes else None

    def snapshot(self) -> PathSnapshot:
        """The fitted polynomials frozen (``networks.snapshot.PathSnapshot``): valid while they do not change."""
        return PathSnapshot(self)

    def _apply(self, fn, *args, **kwargs):
        return apply_keeping_dtype(self, ("coef", "coef_alt", "gate", "cell_coef"), super()._apply, fn, *args, **kwargs)

    @torch.no_grad()
    @one_thread()
    def fit_polynomial(self, x: torch.Tensor, y: torch.Tensor, ridge: float = 1e-12, chunk: int = 8192) -> None:
        """Least squares of every muscle's polynomial (then branches and cells, as configured) on ``x (S, N)``,
        ``y (S, M)`` in float64 (``polynomial.solve_normal_equations``), on one CPU thread (``branches.one_thread``)."""
        x, y, gram, rhs, order = self._fit_whole_box(x, y, ridge, chunk)
        if self.branches == 2:
            self.branched.zero_()
            fit_branches(self, x, y, gram, rhs, order, self.config.gate_degree, chunk)
            refresh_branches(self)  # before the cells: their candidates are the muscles the branches leave worst
        if self.pieces > 1:
            fit_cells(self, x, y, chunk)

    def _fit_whole_box(self, x: torch.Tensor, y: torch.Tensor, ridge: float, chunk: int) -> tuple:
        """The box and ``coef`` of every sample: ``(x, y)`` in float64, the normal equations and ``order (M, P)``
        (each muscle's terms first)."""
        x, y = x.to(torch.float64), y.to(torch.float64)
        self.x_lo.copy_(x.amin(0))
        self.x_hi.copy_(x.amax(0))
        gram, rhs = self._normal_equations(x, y, chunk)
        coef, order = solve_normal_equations(self.term_mask, gram, rhs, ridge)
        self.coef.copy_(coef)
        return x, y, gram, rhs, order

    @torch.no_grad()
    @one_thread()
    def fit_trimmed(self, x: torch.Tensor, y: torch.Tensor, factor: float = 10.0, rounds: int = 3,
                    ridge: float = 1e-12, chunk: int = 8192) -> torch.Tensor:
        """The polynomial alone (no branches or cells) by least squares on ``x (S, N)``, ``y (S, M)``, then up to
        ``rounds`` refits without the samples whose residual norm over the muscles exceeds ``factor`` times the
        median (``trim.trimmed_refits``; the box is every sample's); the kept samples' mask ``(S,)``. One thread."""
        x, y, gram, rhs, _ = self._fit_whole_box(x, y, ridge, chunk)

        def refit(keep, new):
            for rows, sign in ((new & ~keep, 1.0), (keep & ~new, -1.0)):  # back in: added; dropped: taken out
                gram_rows, rhs_rows = self._normal_equations(x[rows], y[rows], chunk)
                gram.add_(sign * gram_rows)
                rhs.add_(sign * rhs_rows)
            self.coef.copy_(solve_normal_equations(self.term_mask, gram, rhs, ridge)[0])
        return trimmed_refits(self, x, y, refit, factor, rounds, chunk)

    def _normal_equations(self, x: torch.Tensor, y: torch.Tensor, chunk: int) -> tuple[torch.Tensor, torch.Tensor]:
        """``phi^T phi (P, P)`` and ``phi^T y (P, M)`` of this path's terms at ``x (S, N)``, ``y (S, M)`` float64,
        summed over chunks of samples (the chunks bound the memory; no sample: zeros)."""
        gram = x.new_zeros(len(self.exponents), len(self.exponents))
        rhs = x.new_zeros(len(self.exponents), y.shape[1])
        for start in range(0, len(x), chunk):
            phi = self.basis(x[start:start + chunk])[0]
            gram += phi.T @ phi
            rhs += phi.T @ y[start:start + chunk]
        return gram, rhs

    # ------------------------------------------------------------------ the network
    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = self.polynomial(x)[0]
        return y + muscle_mlp(self, x, False)[0] if self.n_hidden else y

    def with_jacobian(self, x: torch.Tensor, snapshot: Optional[PathSnapshot] = None) -> tuple[torch.Tensor,
                                                                                                torch.Tensor]:
        """``(y (B, M), dy/dx (B, M, N))``, exact; zero on every joint a muscle does not cross (``snapshot``:
        ``polynomial``'s)."""
        y, dy = self.polynomial(x, slopes=True, snapshot=snapshot)
        if self.n_hidden:
            y_net, dy_net = muscle_mlp(self, x, True)
            y, dy = y + y_net, dy + dy_net
        return y, dy

