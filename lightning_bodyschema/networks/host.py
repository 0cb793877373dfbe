"""A fitted per-muscle path and gravity torque at a few postures in numpy: what a controller asks for on a CPU.

At one posture every tensor operation costs its dispatch, not its arithmetic: on our 2-core CPU a float64 product
of ten numbers takes 1.9 us in torch (inference mode; an index or a matrix product 3.5-7 us) and 0.5 us in numpy.
myoArm's per-muscle body is ~170 of them (``few_postures.evaluate_few``, ``GravityTorque._eager_torque``), most of
a prepared adapter's time at batch 1. ``HostPath`` and ``HostGravity`` are numpy snapshots of the fitted
coefficients and constant tables that repeat those two evaluations operation by operation, in the same order (the
two large matrix products by torch, as there): the same values up to the order of a product's sums (~1e-12
relative). ``StructuredSchema.body_si``, already a numpy boundary, takes them on the CPU at a few postures
(``schemas.host_body.HOST_ROWS``).

Lifetime: a snapshot copies what it reads when built and never follows the module afterwards; the schema's
inference cache holds it (``schemas/cache.py``: cleared on every weight, dtype or device change). numpy, and torch
for two matrix products; no Lightning.
"""
from __future__ import annotations

import numpy as np
import torch

from .basis import _slot_products
from .few_postures import _has_cells
from .gravity import horner


def host_copy(tensor) -> np.ndarray:
    """A host copy of ``tensor`` (never a view of the module's memory)."""
    return tensor.detach().cpu().numpy().copy()


class _HostTerms:
    """``basis.ProductTerms.stacked`` in numpy: every term and its slopes ``(B, P, 1 + n_columns)``, each slot's
    factors a contiguous row (numpy's products along a short last axis are several times slower)."""

    def __init__(self, terms):
        self.degree, self.n_slots, self.n_columns = terms.degree, terms.n_slots, terms.n_columns
        self.to_values, self.to_slopes = host_copy(terms.to_values), host_copy(terms.to_slopes)
        self.n_terms = len(terms.stacked_index)
        self.slot_index = host_copy(terms.slot_index).reshape(self.n_terms, -1).T.reshape(-1)  # slot-major
        # scatter_add's target of each (slot, term) as a flat index: a weighted bincount adds each term's slots in
        # their order, as scatter_add does (the same bits)
        width = 1 + self.n_columns
        self.flat_index = (np.arange(self.n_terms)[:, None] * width + host_copy(terms.stacked_index)).T.copy()

    def __call__(self, x: np.ndarray, scale=None) -> np.ndarray:
        rising = np.cumprod(np.broadcast_to(x[..., None], (*x.shape, self.degree)), -1)
        powers = np.concatenate([np.ones_like(rising[..., :1]), rising], -1)
        values, derivs = powers @ self.to_values, powers @ self.to_slopes
        derivs = derivs if scale is None else derivs * scale[:, None]
        shape = (len(x), self.n_slots, self.n_terms)
        factors = values.reshape(len(x), -1).take(self.slot_index, 1).reshape(shape)
        slopes = derivs.reshape(len(x), -1).take(self.slot_index, 1).reshape(shape)
        phi, slopes = _slot_products(tuple(factors.transpose(1, 0, 2)), tuple(slopes.transpose(1, 0, 2)))
        parts = np.stack([phi] + slopes, 1)  # (B, 1 + slots, P)
        width = self.n_terms * (1 + self.n_columns)
        index = self.flat_index + (width * np.arange(len(x)))[:, None, None]
        return np.bincount(index.ravel(), parts.ravel(), len(x) * width).reshape(len(x), self.n_terms, -1)


class HostPath:
    """``few_postures.evaluate_few`` of a fitted ``PerMusclePath`` without hidden layers, from its
    ``FewCoefficients``: ``(y (B, M), dy (B, M, N))`` float64 at float64 postures ``x (B, N)``."""

    def __init__(self, path, coefs):
        self.x_lo, self.x_hi, self.cells = host_copy(path.x_lo), host_copy(path.x_hi), _has_cells(path)
        self.terms = _HostTerms(path.few_terms if self.cells else path.terms)
        self.n_terms = path.coef.shape[1]
        self.box = host_copy(coefs.box)
        self.box_col, self.alt_col, self.gate_col, self.gated, self.cell_col, self.cell_of, self.celled = (
            host_copy(t) for t in coefs[2:])
        if self.cells:
            self.pieces, self.extra, self.scale = path.pieces, host_copy(path.cell_extra), host_copy(path.few_scale)
            self.stride, self.spread = host_copy(path.cell_stride), host_copy(coefs.spread)
            self.rows, self.fitted = host_copy(path.cell_rows), host_copy(path.cell_fitted)

    def __call__(self, x64: np.ndarray):
        inside = np.minimum(np.maximum(x64, self.x_lo), self.x_hi)
        if self.cells:
            piece, z = self._cell_inputs(inside)
            basis = self.terms(np.concatenate([inside, z], 1), self.scale)
        else:
            basis = self.terms(inside)
        candidates = _box_product(self.box, basis[:, :self.n_terms])  # (B, R, 1 + N)
        gate = candidates[:, :, 0][:, self.gate_col]
        choice = np.where((gate > 0) & self.gated, self.alt_col, self.box_col)
        if self.cells:
            cell = (piece[:, None, :] * self.stride).sum(-1)  # (B, Mc)
            at_cell = self.spread[self.rows[None, :], cell]  # (B, Mc, T)
            candidates = np.concatenate([candidates, _product(at_cell, basis[:, self.n_terms:])], 1)
            fitted = self.fitted[self.rows[None, :], cell][:, self.cell_of]
            choice = np.where(fitted & self.celled, self.cell_col, choice)
        picked = candidates[np.arange(len(x64))[:, None], choice]  # (B, M, 1 + N)
        y, dy = picked[..., 0], picked[..., 1:]
        return y + (dy @ (x64 - inside)[:, :, None])[..., 0], dy

    def _cell_inputs(self, x: np.ndarray):
        """``cells.cell_inputs``: each joint's piece and the cells' coordinates."""
        scaled = self.pieces * (x + 1)
        k = np.fmin(np.fmax(np.floor(scaled / 2), 0), self.pieces - 1)  # NaN: piece 0 (a NaN answer, a valid index)
        return k.astype(np.int64), np.concatenate([scaled - 2 * k - 1, x[:, self.extra]], 1)


class HostGravity:
    """``GravityTorque._eager_torque`` with its ``coef_terms``: ``tau (B, N)`` [N m] at float64 postures
    ``q (B, N)``, the kinematics by pointer jumping (``GravityTorque._world``, any number of postures)."""

    NAMES = ("free_select", "full_base", "dep_follows_index", "dep_follows_qpos0", "dep_horner", "dep_qpos0",
             "dep_index", "dep_scatter", "chain_joint_index", "chain_qpos0", "motion_eye", "motion_terms",
             "node_const", "node_motion", "frame_node_index", "before_node_index", "anchor_axis", "moves_frame",
             "gravity_cross_T", "free_scatter", "slope_index", "slope_qpos0", "slope_horner", "hinge")

    def __init__(self, gravity, terms):
        for name in self.NAMES:
            setattr(self, name, host_copy(getattr(gravity, name)))
        self.pointers = [host_copy(getattr(gravity, f"node_pointer{k}_index")) for k in range(gravity.n_rounds)]
        self.coupled, self.all_hinges = bool(gravity.dep_joint), gravity.all_hinges
        self.gravity = host_copy(gravity.gravity)
        self.moment_mass, self.mass_joint, self.offset, self.rate = (host_copy(t) for t in terms)

    def __call__(self, q: np.ndarray) -> np.ndarray:
        full = self._full_q(q)
        angle = (full[:, self.chain_joint_index] - self.chain_qpos0)[:, :, None, None]
        by_sin, by_versine, by_angle = self.motion_terms
        motion = self.motion_eye + np.sin(angle) * by_sin + (1.0 - np.cos(angle)) * by_versine + angle * by_angle
        world = self.node_const + (self.node_motion @ motion.reshape(len(q), -1, 16)).reshape(len(q), -1, 4, 4)
        for pointer in self.pointers:
            world = world[:, pointer] @ world
        frames, before = world[:, self.frame_node_index], world[:, self.before_node_index]
        w = (frames[..., :3, :] @ self.moment_mass)[..., 0]
        anchor_axis = before[..., :3, :] @ self.anchor_axis  # (B, J, 3, 2)
        o, a = anchor_axis[..., 0], anchor_axis[..., 1]
        w_joint = self.moves_frame @ w
        tau = -((a @ self.gravity_cross_T) * (w_joint - self.mass_joint[:, None] * o)).sum(-1)
        if not self.all_hinges:
            tau = self.hinge * tau + (1.0 - self.hinge) * (-(a @ self.gravity) * self.mass_joint)
        slopes = horner(self.slope_horner, full[:, self.slope_index] - self.slope_qpos0)
        return (tau * slopes) @ self.free_scatter + self.offset + self.rate * q

    def _full_q(self, q: np.ndarray) -> np.ndarray:
        """``GravityTorque.full_q``: every joint from the free ones (locks, then couplings)."""
        full = q @ self.free_select + self.full_base
        if not self.coupled:
            return full
        value = horner(self.dep_horner, full[:, self.dep_follows_index] - self.dep_follows_qpos0)
        return full + (value + self.dep_qpos0 - full[:, self.dep_index]) @ self.dep_scatter


def _product(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a @ b`` by torch: the two products large enough for BLAS to start threads (numpy's OpenBLAS threads by default
    and does not follow ``torch.set_num_threads``: on myoLegs with the other core busy the body took 3.5 ms instead of
    1.4), as the torch evaluation multiplies them."""
    return torch.matmul(torch.from_numpy(a), torch.from_numpy(b)).cpu().numpy()


def _box_product(box: np.ndarray, basis: np.ndarray) -> np.ndarray:
    """``(B, R, K)`` rows ``box (R, P)`` times ``basis (B, P, K)``, as one ``(R, P) x (P, B K)`` product (as
    ``few_postures.evaluate_few``)."""
    flat = np.ascontiguousarray(basis.transpose(1, 0, 2)).reshape(basis.shape[1], -1)
    return _product(box, flat).reshape(len(box), len(basis), -1).transpose(1, 0, 2)
