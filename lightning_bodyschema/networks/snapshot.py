"""The fitted per-muscle body frozen once, and its one evaluation at few postures, written once for numpy and torch.

At one posture every tensor operation costs its dispatch, not its arithmetic (a float64 product of ten numbers: about
2 us in torch, 0.5 us in numpy), so a controller on a CPU asks numpy for the body, while a schema on a GPU, or one
asked for a few dozen postures, stays in torch. Both run the code below: ``PathSnapshot`` (every part of a fitted
``PerMusclePath``, its whole-box polynomials, branches and cells, from one stacked basis: one product with the
whole-box rows, one with the posture's cells' rows, one pick of each muscle's candidate), ``GravitySnapshot`` (a
``GravityTorque``'s torque by one 4x4 motion per joint and the frames' world poses) and ``BodySnapshot`` (the schema's
normalizer and unit scales around both: ``StructuredSchema.body_si``'s whole arithmetic). Each is built from the
modules' tensors (torch) and ``on_host()`` gives the same object in numpy over host copies of them; the few
operations whose spelling differs between the two libraries are ``networks.arrays``' (``xp``: the object's array
library). The numpy evaluation multiplies the two large matrices by torch (numpy's OpenBLAS threads on its own).

Lifetime: a snapshot holds what it read when built and never follows the module afterwards; a schema keeps its
snapshots in its inference cache (``schemas/cache.py``: cleared on every weight, dtype or device change). No
Lightning.
"""
from __future__ import annotations

import numpy as np
import torch

from .arrays import (Frozen, as_dtype, as_index, decode_q, encode_q, horner, offsets, pick, product, rows_product,
                     scatter_sum, take)
from .basis import _slot_products
from .cells import cell_spread

JUMP_ROWS = 4  # up to this many postures the kinematics jump pointers (fewest operations); above, a product per node

# the largest stacked basis of this evaluation: postures x terms (whole-box and cell) x (1 + joints), about 11 MB of
# float64. Above it, ``PerMusclePath``'s blocks of rows and a cell at a time are faster (their slopes touch only the
# joints each term uses): myoArm's per-muscle path 102 postures, myoLegs + OSL 43, myoLegs 22, myoHand 241
FEW_ELEMENTS = 1_400_000


class TermsSnapshot(Frozen):
    """A ``basis.ProductTerms``' terms and their slopes at few postures in one array ``(B, P, 1 + columns)``:
    column 0 the term, then each variable's slope added into its output column (``ProductTerms.columns``; with
    ``scale (V,)`` times ``d variable / d output``). The Legendre values from the powers of x times a fixed matrix;
    each slot's factors a contiguous row; one weighted bincount adds each term's slots in their order."""

    def __init__(self, terms):
        self.degree, self.n_slots, self.n_columns = terms.degree, terms.n_slots, terms.n_columns
        self.to_values, self.to_slopes = terms.to_values, terms.to_slopes
        self.n_terms, width = len(terms.stacked_index), 1 + terms.n_columns
        self.slot_index = terms.slot_index.view(self.n_terms, -1).T.flatten()  # slot-major
        rows = torch.arange(self.n_terms, device=terms.stacked_index.device)[:, None]
        self.flat_index = (rows * width + terms.stacked_index).T.contiguous()  # (1 + slots, P) into (P, width)

    def __call__(self, x, scale=None):
        xp, n = self.xp, x.shape[0]
        rising = xp.cumprod(xp.broadcast_to(x[..., None], (*x.shape, self.degree)), -1)
        powers = xp.concatenate([xp.ones_like(rising[..., :1]), rising], -1)
        values, derivs = powers @ self.to_values, powers @ self.to_slopes
        derivs = derivs if scale is None else derivs * scale[:, None]
        shape = (n, self.n_slots, self.n_terms)
        factors = take(values.reshape(n, -1), self.slot_index, 1).reshape(shape)
        slopes = take(derivs.reshape(n, -1), self.slot_index, 1).reshape(shape)
        phi, slopes = _slot_products(tuple(factors[:, s] for s in range(self.n_slots)),
                                     tuple(slopes[:, s] for s in range(self.n_slots)))
        width = self.n_terms * (1 + self.n_columns)
        index = self.flat_index + offsets(x, width)
        parts = xp.stack([phi] + slopes, 1)  # (B, 1 + slots, P)
        return scatter_sum(index.ravel(), parts.ravel(), n * width).reshape(n, self.n_terms, -1)


def has_cells(path) -> bool:
    """Whether ``path`` (a ``PerMusclePath``) has celled muscles (their layout set)."""
    return path.pieces > 1 and len(path.cell_muscles) > 0


def few_rows(path) -> int:
    """The most postures ``path`` evaluates by its snapshot: their stacked basis within ``FEW_ELEMENTS``."""
    terms = len(path.few_terms.exponents) if has_cells(path) else path.coef.shape[1]
    return FEW_ELEMENTS // (terms * (1 + path.crossing.shape[1]))


def few_for(path, x) -> bool:
    """Whether ``path`` evaluates postures ``x (B, N)`` by its snapshot (``few_rows``), never in an exported program
    (one path for any batch there: ``PerMusclePath.polynomial``'s blocks)."""
    return not torch.compiler.is_exporting() and len(x) <= few_rows(path)


class PathSnapshot(Frozen):
    """A fitted ``PerMusclePath``'s polynomials: ``(y (B, M), dy (B, M, N))`` at float64 postures ``x64 (B, N)``,
    clamped to the fitted box and extended to first order outside it (``PerMusclePath.polynomial``).

    ``box (R, P)`` holds the whole-box rows a posture may use (the muscles without cells fitted everywhere, then the
    branched muscles' second polynomials, then their gates), ``spread (Mc, C, T)`` the cells' coefficients on every
    cell term (``cells.cell_spread``), and per muscle ``(M,)`` the candidate of each choice: ``box_col`` (whole box),
    ``alt_col`` and ``gate_col`` (its branch and gate where ``gated``), ``cell_col`` and ``cell_of`` (its cell
    polynomial and row among the celled muscles where ``celled``). A muscle takes its cell's polynomial where that
    cell was fitted, else its gate's branch, else its whole-box polynomial; the slopes of a cell coordinate are
    scaled by ``pieces`` (its chain rule, exact for a power of two). ``max_postures``: the most postures it is built
    for (``few_rows``, with the budget of its build)."""

    def __init__(self, path):
        self.x_lo, self.x_hi, self.cells, self.max_postures = path.x_lo, path.x_hi, has_cells(path), few_rows(path)
        self.terms = TermsSnapshot(path.few_terms if self.cells else path.terms)
        self.n_terms = path.coef.shape[1]
        self._choices(path)
        if self.cells:
            self.pieces, self.extra, self.scale = path.pieces, path.cell_extra, path.few_scale
            self.stride, self.rows, self.fitted = path.cell_stride, path.cell_rows, path.cell_fitted
            self.spread = cell_spread(path)
            self.first_piece, self.last_piece = (path.x_lo.new_tensor(float(v)) for v in (0, path.pieces - 1))

    def _choices(self, path) -> None:
        """The rows of ``box`` and each muscle's candidates (class docstring), from the coefficients masked to each
        muscle's terms."""
        n, long = len(path.coef), dict(dtype=torch.long, device=path.coef.device)
        self.celled, everywhere = (torch.zeros(n, dtype=torch.bool, device=path.coef.device) for _ in range(2))
        self.cell_of = torch.zeros(n, **long)
        if self.cells:
            self.celled[path.cell_muscles] = True
            everywhere[path.cell_muscles] = path.cell_fitted.all(1)  # never a whole-box row
            self.cell_of[path.cell_muscles] = torch.arange(len(path.cell_muscles), **long)
        box_muscles = torch.nonzero(~everywhere).flatten()
        self.box_col = torch.zeros(n, **long)
        self.box_col[box_muscles] = torch.arange(len(box_muscles), **long)
        rows, self.alt_col, self.gate_col = [(path.coef * path.term_mask)[box_muscles]], self.box_col.clone(), \
            torch.zeros(n, **long)
        if path.branches == 2 and len(path.branched_index):
            branched, count = path.branched_index, len(path.branched_index)
            rows += [path.coef_alt[branched] * path.term_mask[branched], path.gate[branched]]
            self.alt_col[branched] = len(box_muscles) + torch.arange(count, **long)
            self.gate_col[branched] = len(box_muscles) + count + torch.arange(count, **long)
        self.box = torch.cat(rows)
        self.cell_col = torch.where(self.celled, len(self.box) + self.cell_of, self.box_col)
        self.gated = self.alt_col != self.box_col

    def __call__(self, x64):
        xp = self.xp
        inside = xp.minimum(xp.maximum(x64, self.x_lo), self.x_hi)
        if self.cells:  # the variables: every joint, then the cells' coordinates (its local one, the joints kept whole)
            piece, z = self._cell_inputs(inside)
            basis = self.terms(xp.concatenate([inside, z], 1), self.scale)
        else:
            basis = self.terms(inside)  # (B, P, 1 + N)
        candidates = _box_product(self.box, basis[:, :self.n_terms])  # (B, R, 1 + N)
        gate = candidates[:, :, 0][:, self.gate_col]
        choice = xp.where((gate > 0) & self.gated, self.alt_col, self.box_col)
        if self.cells:
            cell = (piece[:, None, :] * self.stride).sum(-1)  # (B, Mc): each celled muscle's cell
            at_cell = self.spread[self.rows[None, :], cell]  # (B, Mc, T)
            candidates = xp.concatenate([candidates, product(at_cell, basis[:, self.n_terms:])], 1)
            fitted = self.fitted[self.rows[None, :], cell][:, self.cell_of]
            choice = xp.where(fitted & self.celled, self.cell_col, choice)
        picked = pick(candidates, choice)  # (B, M, 1 + N)
        y, dy = picked[..., 0], picked[..., 1:]
        return y + (dy @ (x64 - inside)[:, :, None])[..., 0], dy

    def _cell_inputs(self, x):
        """Each joint's piece ``(B, N)`` and the cells' coordinates (``cells.cell_inputs``); a NaN posture gets piece
        0 (a NaN answer at a valid index)."""
        scaled = self.pieces * (x + 1)
        k = self.xp.fmin(self.xp.fmax(self.xp.floor(scaled / 2), self.first_piece), self.last_piece)
        return as_index(k), self.xp.concatenate([scaled - 2 * k - 1, take(x, self.extra, 1)], 1)


def _box_product(box, basis):
    """``(B, R, K)``: rows ``box (R, P)`` times ``basis (B, P, K)``, as one ``(R, P) x (P, B K)`` product."""
    xp = np if isinstance(box, np.ndarray) else torch
    flat = xp.swapaxes(basis, 0, 1).reshape(basis.shape[1], -1)
    return xp.swapaxes(product(box, flat).reshape(len(box), basis.shape[0], -1), 0, 1)


class GravitySnapshot(Frozen):
    """A fitted ``GravityTorque``'s torque ``tau (B, N)`` [N m] at float64 postures ``q (B, N)`` [rad or m]: the
    tree's tables (every buffer of the module) and, from its coefficients, per frame ``(s, m)`` ``(F, 4, 1)`` (in the
    order of a pose's columns), each moving joint's mass below it ``(J,)``, the offsets and spring rates ``(N,)``.
    Each joint's motion is one 4x4 sum ``I + sin M_sin + versine M_versine + angle M_angle``; a frame's ``R s + p m``
    and a joint's anchor and axis each one product of a pose's top rows; the world poses by pointer jumping up to
    ``JUMP_ROWS`` postures and in numpy, else one product per node (``GravityTorque.kinematics``' two ways)."""

    def __init__(self, gravity):
        self.__dict__.update(gravity.named_buffers(recurse=False))
        self.pointers = [getattr(gravity, f"node_pointer{k}_index") for k in range(gravity.n_rounds)]
        self.node_parent, self.node_chain = gravity.node_parent, gravity.node_chain
        self.coupled, self.all_hinges = bool(gravity.dep_joint), gravity.all_hinges
        f64, hinge = dict(dtype=torch.float64, device=gravity.coef.device), gravity.chain_hinge[:, None]
        terms = torch.zeros(3, len(gravity.chain_cross), 4, 4, **f64)
        terms[0, :, :3, :3], terms[0, :, :3, 3] = gravity.chain_cross, -hinge * gravity.chain_cross_pos
        terms[1, :, :3, :3], terms[1, :, :3, 3] = gravity.chain_cross2, -hinge * gravity.chain_cross2_pos
        terms[2, :, :3, 3] = (1.0 - hinge) * gravity.chain_axis
        self.motion_eye, self.motion_terms = torch.eye(4, **f64), terms
        self.anchor_axis = torch.zeros(len(gravity.moving_joint), 4, 2, **f64)
        self.anchor_axis[:, :3, 0], self.anchor_axis[:, 3, 0] = gravity.moving_pos, 1.0
        self.anchor_axis[:, :3, 1] = gravity.moving_axis
        self.chain_joint_index = torch.as_tensor(gravity.chain_joint, dtype=torch.long, device=f64["device"])
        self.chain_qpos0, self.gravity_cross_T = gravity.qpos0[gravity.chain_joint], gravity.gravity_cross.T.clone()
        n_frames, n_free, coef = gravity.n_frames, gravity.n_free, gravity.coef
        order = torch.arange(4 * n_frames, device=coef.device).view(-1, 4)[:, [1, 2, 3, 0]].flatten()
        self.moment_mass = coef.index_select(0, order).view(-1, 4, 1)
        self.mass_joint = gravity.moves_frame @ coef[:4 * n_frames].view(n_frames, 4)[:, 0]
        self.offset, self.rate = coef[4 * n_frames:4 * n_frames + n_free], coef[4 * n_frames + n_free:]

    def __call__(self, q):
        xp, full = self.xp, self._full_q(q)
        angle = (take(full, self.chain_joint_index, 1) - self.chain_qpos0)[:, :, None, None]
        by_sin, by_versine, by_angle = self.motion_terms
        motion = self.motion_eye + xp.sin(angle) * by_sin + (1.0 - xp.cos(angle)) * by_versine + angle * by_angle
        frames, before = self._world(motion)
        w = (frames[..., :3, :] @ self.moment_mass)[..., 0]
        anchor_axis = before[..., :3, :] @ self.anchor_axis  # (B, J, 3, 2)
        o, a = anchor_axis[..., 0], anchor_axis[..., 1]
        w_joint = rows_product(self.moves_frame, w)
        tau = -((a @ self.gravity_cross_T) * (w_joint - self.mass_joint[:, None] * o)).sum(-1)
        if not self.all_hinges:
            tau = self.hinge * tau + (1.0 - self.hinge) * (-(a @ self.gravity) * self.mass_joint)
        slopes = horner(self.slope_horner, take(full, self.slope_index, 1) - self.slope_qpos0)
        return (tau * slopes) @ self.free_scatter + self.offset + self.rate * q

    def _full_q(self, q):
        """Every joint from the free ones (locks, then couplings: ``GravityTorque.full_q``)."""
        full = q @ self.free_select + self.full_base
        if not self.coupled:
            return full
        value = horner(self.dep_horner, take(full, self.dep_follows_index, 1) - self.dep_follows_qpos0)
        return full + (value + self.dep_qpos0 - take(full, self.dep_index, 1)) @ self.dep_scatter

    def _world(self, motion):
        """The world poses ``(B, F, 4, 4)`` of the frames and ``(B, J, 4, 4)`` of the nodes before the moving joints
        from the chain joints' motions ``(B, C, 4, 4)``."""
        xp, n = self.xp, motion.shape[0]
        if xp is np or torch.compiler.is_exporting() or n <= JUMP_ROWS:  # exported: one path for any batch
            world = self.node_const + (self.node_motion @ motion.reshape(n, -1, 16)).reshape(n, -1, 4, 4)
            for pointer in self.pointers:
                world = take(world, pointer, 1) @ world
        else:
            nodes = []
            for i, (parent, chain) in enumerate(zip(self.node_parent, self.node_chain)):
                T = self.node_const[i] if chain < 0 else motion[:, chain]
                nodes.append(xp.broadcast_to(T, (n, 4, 4)) if parent < 0 else nodes[parent] @ T)
            world = xp.stack(nodes, 1)
        return take(world, self.frame_node_index, 1), take(world, self.before_node_index, 1)


class BodySnapshot(Frozen):
    """``StructuredSchema.body_si``'s arithmetic on a per-muscle path and a gravity torque: ``(l_geo [m] (B, M),
    G [m/rad] (B, M, N), tau [N m] (B, N))`` float64 at postures ``q_rad (B, N)`` [rad], each step and cast of
    ``StructuredSchema.body``: the normalized posture in the schema's ``dtype``, the path in float64 then cast to it,
    the lengths and moment arms scaled in it (``scales``: ``l_mean``, ``l_std`` (M,) and ``arm`` (M, N)), the
    torque at that posture decoded to radians in float64, then cast."""

    def __init__(self, q_lo, q_hi, dtype, path: PathSnapshot, gravity: GravitySnapshot, scales):
        self.q_lo, self.q_hi, self.dtype, self.float64 = q_lo.to(torch.float64), q_hi.to(torch.float64), dtype, \
            torch.float64
        self.path, self.gravity = path, gravity
        self.l_mean, self.l_std, self.arm = scales

    def __call__(self, q_rad):
        f64 = self.float64
        q_n = as_dtype(encode_q(q_rad, self.q_lo, self.q_hi), self.dtype)
        y, dy = self.path(as_dtype(q_n, f64))
        l_geo = self.l_mean + self.l_std * as_dtype(y, self.dtype)
        tau = as_dtype(self.gravity(decode_q(as_dtype(q_n, f64), self.q_lo, self.q_hi)), self.dtype)
        return as_dtype(l_geo, f64), as_dtype(as_dtype(dy, self.dtype) * self.arm, f64), as_dtype(tau, f64)
