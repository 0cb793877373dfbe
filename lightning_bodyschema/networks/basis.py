"""The Legendre product basis of the per-muscle polynomials (paths, gates, cells, the polynomial torque)."""
from __future__ import annotations

from typing import NamedTuple, Optional, Union

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from .arrays import Frozen, apply_keeping_dtype, namespace, scatter_columns, take_columns, unbind

DENSE_ROWS = 48  # up to this many postures ``ProductTerms`` gathers every factor at once (BENCHMARKS.md)


def legendre(x: torch.Tensor, degree: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Legendre polynomials ``P_0..P_degree`` of ``x (B, N)`` and their derivatives: two ``(B, N, degree + 1)``."""
    values, slopes = [torch.ones_like(x)], [torch.zeros_like(x)]
    if degree >= 1:
        values.append(x)
        slopes.append(torch.ones_like(x))
    for n in range(1, degree):  # (n+1) P_{n+1} = (2n+1) x P_n - n P_{n-1};  P'_{n+1} = P'_{n-1} + (2n+1) P_n
        values.append(((2 * n + 1) * x * values[n] - n * values[n - 1]) / (n + 1))
        slopes.append(slopes[n - 1] + (2 * n + 1) * values[n])
    return torch.stack(values, -1), torch.stack(slopes, -1)


def product_basis(x: torch.Tensor, exponents: torch.Tensor, degree: int, slopes: bool = False):
    """``phi (B, P)`` and, with ``slopes``, ``dphi/dx (B, N, P)``: per term ``exponents (P, N)``, the product over the
    joints of each joint's Legendre polynomial of that exponent (a loop over the N joints, batched over samples and
    terms); ``degree``: the largest exponent."""
    values, derivs = legendre(x, degree)
    factors = [values[:, j][:, exponents[:, j]] for j in range(x.shape[1])]  # N x (B, P)
    joint_slopes = [derivs[:, j][:, exponents[:, j]] for j in range(x.shape[1])] if slopes else None
    phi, dphi = _slot_products(factors, joint_slopes)
    return phi, None if dphi is None else torch.stack(dphi, 1)


def power_matrices(degree: int) -> tuple[np.ndarray, np.ndarray]:
    """``(degree + 1, degree + 1)`` float64 ``A``, ``D`` with ``P_n(x) = sum_k A[k, n] x^k`` and
    ``P'_n(x) = sum_k D[k, n] x^k``."""
    values, slopes = np.zeros((degree + 1, degree + 1)), np.zeros((degree + 1, degree + 1))
    for n in range(degree + 1):
        coef = np.polynomial.legendre.leg2poly(np.eye(degree + 1)[n])
        values[:len(coef), n] = coef
        slope = np.polynomial.polynomial.polyder(coef)
        slopes[:len(slope), n] = slope
    return values, slopes


class ProductTerms(nn.Module):
    """The product terms of ``exponents (P, N)``: ``forward(x, slopes)`` gives a ``Basis``, ``contract`` applies
    coefficients in the terms' original order (``layout``: arranged for the basis's path, once per evaluation).

    The Legendre values come from the powers of x times a fixed matrix (within about 1e-11 of the recurrence at
    degree 16 on [-1, 1]). Up to ``DENSE_ROWS`` postures every term's ``n_slots`` factors on the joints it uses are
    gathered at once (``dense_terms``, padded with exact ones); above, the terms are grouped by the joints they use and
    only those factors multiplied and differentiated (``grouped``). ``columns``: each variable's slope's output
    column (None: its own; a joint and its cell coordinate may share one). Buffers only, none persistent (the state
    dict is unchanged).
    """

    def __init__(self, exponents, columns=None):
        super().__init__()
        exponents = np.asarray(exponents, dtype=np.int64)
        self.n_joints, self.degree = exponents.shape[1], max(int(exponents.max(initial=0)), 1)
        supports = [tuple(np.flatnonzero(row).tolist()) for row in exponents]
        self.supports = sorted(set(supports), key=lambda s: (len(s), s))
        members = [np.array([p for p, s in enumerate(supports) if s == key], dtype=np.int64)
                   for key in self.supports]
        perm = np.concatenate(members) if members else np.zeros(0, np.int64)
        values, slopes = power_matrices(self.degree)
        # each term's factors in ``n_slots`` slots: the joints it uses, ascending, then joints it does not use
        # (exponent 0: a factor of exactly 1, a slope of exactly 0); the dense basis gathers these, not all N
        self.n_slots = max(1, int((exponents > 0).sum(1).max(initial=0)))
        slot_joint = np.argsort(exponents == 0, axis=1, kind="stable")[:, :self.n_slots]
        flat = slot_joint * (self.degree + 1) + np.take_along_axis(exponents, slot_joint, 1)
        columns = np.arange(self.n_joints) if columns is None else np.asarray(columns, dtype=np.int64)
        self.n_columns, self.n_terms = int(columns.max(initial=-1)) + 1, len(exponents)
        slot_column = columns[slot_joint]  # (P, slots): each slot's slope's output column
        flat_index = np.arange(self.n_terms)[:, None] * self.n_columns + slot_column  # its place in (P, columns)
        tables = dict(perm=perm, slot_index=flat.T.reshape(-1), exponents=exponents, slot_column=slot_column,
                      flat_index=flat_index.T.copy(), to_values=values, to_slopes=slopes)  # int64 or float64
        for g, (key, cols) in enumerate(zip(self.supports, members)):
            tables[f"exp{g}"] = exponents[cols][:, list(key)].T.copy()  # (|support|, P_g)
        for j in range(self.n_joints):  # the terms that use joint j, in the grouped order
            tables[f"joint_terms{j}"] = np.concatenate([cols for key, cols in zip(self.supports, members) if j in key]
                                                       or [np.zeros(0, np.int64)])
        for name, value in tables.items():
            self.register_buffer(name, torch.tensor(value), persistent=False)
        # where each support's terms sit: its rows of phi, and per joint it uses its rows of that joint's derivatives
        ends = np.cumsum([len(cols) for cols in members]).tolist()
        self.group_rows = [(end - len(cols), end) for end, cols in zip(ends, members)]
        self.joint_counts, self.joint_rows = [0] * self.n_joints, []
        for key, cols in zip(self.supports, members):
            self.joint_rows.append([(self.joint_counts[j], self.joint_counts[j] + len(cols)) for j in key])
            for j in key:
                self.joint_counts[j] += len(cols)

    def _apply(self, fn, *args, **kwargs):
        return apply_keeping_dtype(self, ("to_values", "to_slopes"), super()._apply, fn, *args, **kwargs)

    def forward(self, x: torch.Tensor, slopes: bool = False, dense: Optional[bool] = None) -> "Basis":
        """Every term at ``x (B, N)`` (float64) and, with ``slopes``, its derivatives; ``dense`` None: up to
        ``DENSE_ROWS`` postures."""
        if len(x) <= DENSE_ROWS if dense is None else dense:
            phi, parts = dense_terms(self, x)
            dphi = scatter_columns(parts, self.slot_column, self.flat_index, self.n_columns) if slopes else None
            return Basis(phi, dphi, False)
        powers = F.pad(x.T[:, None, :].expand(-1, self.degree, -1).cumprod(1), (0, 0, 1, 0), value=1.0)
        # (N, degree + 1, B): each joint's rows contiguous
        return self._grouped(self.to_values.T @ powers, (self.to_slopes.T @ powers) if slopes else None)

    def _grouped(self, values, derivs) -> "Basis":
        """``phi (P, B)`` (transposed) in ``perm``'s order and per joint ``j`` the derivative rows ``(P_j, B)`` of the
        terms ``joint_terms{j}``, from ``values``, ``derivs`` ``(N, degree + 1, B)``: a loop over the supports, each
        product written into its rows of the result."""
        phi = values.new_empty(len(self.perm), values.shape[-1])
        dphi = None if derivs is None else [values.new_empty(n, values.shape[-1]) for n in self.joint_counts]
        for g, key in enumerate(self.supports):
            (start, end), exps = self.group_rows[g], getattr(self, f"exp{g}")
            if not key:  # the constant
                phi[start:end] = 1.0
                continue
            factors = [values[j].index_select(0, exps[k]) for k, j in enumerate(key)]
            before = [factors[0]]  # prod_{i<=k} factor_i
            for factor in factors[1:-1]:
                before.append(before[-1] * factor)
            before.append(_product_into(phi[start:end], before[-1:] + factors[-1:] if len(key) > 1 else factors))
            after = None  # prod_{i>k} factor_i
            for k in reversed(range(len(key)) if derivs is not None else ()):
                j, (row, row_end) = key[k], self.joint_rows[g][k]
                parts = [derivs[j].index_select(0, exps[k])] + ([before[k - 1]] if k else []) + \
                    ([after] if after is not None else [])
                _product_into(dphi[j][row:row_end], parts)
                after = factors[k] if after is None else after * factors[k]
        return Basis(phi, dphi, True)

    def layout(self, coef: torch.Tensor):
        """Coefficients ``coef (M, P)`` (terms in their original order) as ``contract`` takes them for a grouped
        basis: once per evaluation, for all its blocks of rows (a gather of every coefficient per joint)."""
        return coef.index_select(1, self.perm).T, [coef.index_select(1, getattr(self, f"joint_terms{j}")).T
                                                   for j in range(self.n_joints)]

    def contract(self, basis: "Basis", coef):
        """``y (B, M)`` of coefficients ``coef`` (``(M, P)`` in the terms' original order, or ``layout``'s for a
        grouped basis) and, when the basis has slopes, ``dy (B, M, N)`` (else None)."""
        slopes = basis.dphi is not None
        if not basis.grouped:
            return basis.phi @ coef.T, torch.einsum("bpn,mp->bmn", basis.dphi, coef) if slopes else None
        by_term, by_joint = self.layout(coef) if torch.is_tensor(coef) else coef
        y = basis.phi.T @ by_term
        return y, torch.stack([d.T @ w for d, w in zip(basis.dphi, by_joint)], -1) if slopes else None


def dense_terms(terms, x, scale=None):
    """``phi (B, P)`` and per slot ``(B, P)`` (a list) its variable's slope times the other slots' factors, at
    postures ``x (B, V)`` (numpy or torch), of ``terms`` (a ``ProductTerms`` or its ``TermsSnapshot``; with
    ``scale (V,)`` the slopes times ``d variable / d output``); the caller adds them into their columns
    (``arrays.scatter_columns``). The powers by repeated products (pow rounds differently)."""
    xp, n = namespace(x), x.shape[0]  # (a symbolic batch stays symbolic in an exported program)
    rising = xp.cumprod(xp.broadcast_to(x[..., None], (*x.shape, terms.degree)), -1)
    powers = xp.concatenate([xp.ones_like(rising[..., :1]), rising], -1)
    values, derivs = powers @ terms.to_values, powers @ terms.to_slopes
    derivs = derivs if scale is None else derivs * scale[:, None]
    shape = (n, terms.n_slots, terms.n_terms)
    factors = take_columns(values.reshape(n, -1), terms.slot_index).reshape(shape)
    slopes = take_columns(derivs.reshape(n, -1), terms.slot_index).reshape(shape)
    return _slot_products(unbind(factors, 1), unbind(slopes, 1))


class TermsSnapshot(Frozen):
    """A ``ProductTerms``' tables frozen for ``dense_terms`` (``on_host()``: in numpy); a call gives
    ``(B, P, 1 + columns)``: each term, then its slopes (one scatter of both)."""

    def __init__(self, terms: ProductTerms):
        for name in ("degree", "n_slots", "n_columns", "n_terms", "to_values", "to_slopes", "slot_index"):
            setattr(self, name, getattr(terms, name))
        self.column = torch.cat([torch.zeros_like(terms.slot_column[:, :1]), 1 + terms.slot_column], 1)
        rows = torch.arange(self.n_terms, device=self.column.device)[:, None]
        self.flat_index = (rows * (1 + self.n_columns) + self.column).T.contiguous()

    def __call__(self, x, scale=None):
        phi, slopes = dense_terms(self, x, scale)
        return scatter_columns([phi] + slopes, self.column, self.flat_index, 1 + self.n_columns)


def _slot_products(factors: tuple, derivs: Optional[tuple]) -> tuple:
    """``phi`` (the product of ``factors``, one ``(B, P)`` per slot) and, with ``derivs`` (the same), each slot's
    slope ``derivs_j`` times the product of the other slots' factors (else None), associated as padded cumulative
    products would be (the same bits), one elementwise product at a time."""
    before, after = [None, factors[0]], [None] * len(factors)  # prod_{i<j} factor_i, prod_{i>j} factor_i
    for j in range(2, len(factors)):
        before.append(before[-1] * factors[j - 1])
    for j in range(len(factors) - 2, -1, -1):
        after[j] = factors[j + 1] if after[j + 1] is None else after[j + 1] * factors[j + 1]
    phi = factors[0] if len(factors) == 1 else before[-1] * factors[-1]
    if derivs is None:
        return phi, None
    times = lambda a, b: a if b is None else a * b  # noqa: E731
    return phi, [times(times(d, b), a) for d, b, a in zip(derivs, before, after)]


def _product_into(out: torch.Tensor, factors: list) -> torch.Tensor:
    """``out`` (written in place) = the product of ``factors`` (one or more tensors of its shape); through autograd
    when a factor needs it (``out=`` products do not record it)."""
    if len(factors) == 1:
        return out.copy_(factors[0])
    if torch.is_grad_enabled() and any(factor.requires_grad for factor in factors):
        product = factors[0]
        for factor in factors[1:]:
            product = product * factor
        return out.copy_(product)
    torch.mul(factors[0], factors[1], out=out)
    for factor in factors[2:]:
        out.mul_(factor)
    return out


class Basis(NamedTuple):
    """A ``ProductTerms`` evaluation: dense, ``phi (B, P)`` and ``dphi`` None or ``(B, P, N)``; grouped (the terms
    in the grouped order, transposed), ``phi (P, B)`` and ``dphi`` None or N ``(P_j, B)``."""
    phi: torch.Tensor
    dphi: Optional[Union[torch.Tensor, list]]
    grouped: bool
