"""The fitted per-muscle body frozen once, written once for numpy and torch: ``PathSnapshot`` (a ``PerMusclePath``'s
polynomials, branches and cells from one stacked basis), ``GravitySnapshot`` (a ``GravityTorque``'s torque) and
``BodySnapshot`` (the schema's normalizer and unit scales around both: ``StructuredSchema.body_si``'s arithmetic).
Each is built from the modules' tensors; ``on_host()`` gives the same object in numpy over host copies (``xp``: its
array library; the spellings that differ: ``networks.arrays``). A snapshot never follows the module after it is
built (a schema keeps its snapshots in its inference cache, cleared on every weight, dtype or device change). No
Lightning.
"""
from __future__ import annotations

import numpy as np
import torch

from .arrays import Frozen, as_dtype, decode_q, encode_q, horner, pick, product, rows_product, take
from .basis import TermsSnapshot
from .cells import cell_index, cell_inputs

JUMP_ROWS = 4  # up to this many postures the kinematics jump pointers (fewest operations); above, a product per node

# the largest stacked basis (postures x terms x (1 + joints)) evaluated here; above, ``PerMusclePath``'s blocks of rows
# (slopes only on the joints each term uses; BENCHMARKS.md "Figures behind code choices")
FEW_ELEMENTS = 1_400_000


class PathSnapshot(Frozen):
    """A fitted ``PerMusclePath``'s polynomials ``(y (B, M), dy (B, M, N))`` at float64 postures ``x64 (B, N)``,
    clamped to the fitted box and extended to first order outside it (``PerMusclePath.polynomial``): a muscle takes
    its cell's polynomial where that cell was fitted, else its gate's branch, else its whole-box polynomial (the
    candidate rows: ``_choices``). ``max_postures``: the most postures it evaluates (its stacked basis within
    ``FEW_ELEMENTS``; exported, any batch: ``PerMusclePath.polynomial``); ``cells``: whether the path has celled
    muscles."""

    def __init__(self, path):
        self.x_lo, self.x_hi, self.cells = path.x_lo, path.x_hi, path.pieces > 1 and len(path.cell_muscles) > 0
        self.terms = TermsSnapshot(path.few_terms if self.cells else path.terms)
        self.max_postures = FEW_ELEMENTS // (self.terms.n_terms * (1 + path.crossing.shape[1]))
        self.n_terms = path.coef.shape[1]
        self._choices(path)
        if self.cells:
            self.pieces, self.cell_extra, self.scale = path.pieces, path.cell_extra, path.few_scale
            self.stride, self.rows, self.fitted = path.cell_stride, path.cell_rows, path.cell_fitted
            coef = path.cell_coef  # spread (Mc, C, T): each celled muscle's coefficients in each of its cells on every
            # cell term, zero off its own terms (the padding's zeros added onto column 0)
            order = path.cell_order[:, None, :].expand(-1, coef.shape[1], -1)
            self.spread = coef.new_zeros(*coef.shape[:2], len(path.cell_exponents)).scatter_add_(2, order, coef)

    def _choices(self, path) -> None:
        """``box (R, P)``: the whole-box rows a posture may use (the muscles without cells fitted everywhere; every
        muscle in an exported program, a size from the data there, or when every muscle's are; the branched muscles'
        second polynomials, their gates; masked to each muscle's terms), and per muscle ``(M,)`` its candidates:
        ``box_col``, ``alt_col`` and ``gate_col`` (where ``gated``), ``cell_col``, ``cell_of`` (where ``celled``)."""
        n, long = len(path.coef), dict(dtype=torch.long, device=path.coef.device)
        self.celled, everywhere = (torch.zeros(n, dtype=torch.bool, device=path.coef.device) for _ in range(2))
        self.cell_of = torch.zeros(n, **long)
        if self.cells:
            self.celled[path.cell_muscles] = True
            everywhere[path.cell_muscles] = path.cell_fitted.all(1)  # never a whole-box row
            self.cell_of[path.cell_muscles] = torch.arange(len(path.cell_muscles), **long)
        every = torch.compiler.is_exporting() or bool(everywhere.all())  # (blocks of rows gather a row)
        box_muscles = torch.arange(n, **long) if every else torch.nonzero(~everywhere).flatten()
        self.box_col = torch.zeros(n, **long)
        self.box_col[box_muscles] = torch.arange(len(box_muscles), **long)
        rows, self.alt_col, self.gate_col = [(path.coef * path.term_mask)[box_muscles]], self.box_col.clone(), \
            torch.zeros(n, **long)
        if path.branches == 2 and len(path.branched_index):  # second polynomials zero off each muscle's terms
            branched, count = path.branched_index, len(path.branched_index)
            rows += [path.coef_alt[branched] * path.term_mask[branched], path.gate[branched]]
            self.alt_col[branched] = len(box_muscles) + torch.arange(count, **long)
            self.gate_col[branched] = len(box_muscles) + count + torch.arange(count, **long)
        self.box = torch.cat(rows)
        self.cell_col = torch.where(self.celled, len(self.box) + self.cell_of, self.box_col)
        self.gated = self.alt_col != self.box_col

    def branch_choice(self, values):
        """Each posture's whole-box or branch row ``(B, M)`` per muscle from the candidate rows' values ``(B, R)``: a
        gated muscle's second polynomial where its gate is positive."""
        return self.xp.where((values[:, self.gate_col] > 0) & self.gated, self.alt_col, self.box_col)

    def __call__(self, x64):
        xp = self.xp
        inside = xp.minimum(xp.maximum(x64, self.x_lo), self.x_hi)
        if self.cells:  # the variables: every joint, then the cells' coordinates (its local one, the joints kept whole)
            piece, z = cell_inputs(self, inside)
            basis = self.terms(xp.concatenate([inside, z], 1), self.scale)
        else:
            basis = self.terms(inside)  # (B, P, 1 + N)
        flat = xp.swapaxes(basis[:, :self.n_terms], 0, 1).reshape(self.n_terms, -1)  # one (R, P) x (P, B (1 + N))
        candidates = xp.swapaxes(product(self.box, flat).reshape(len(self.box), basis.shape[0], -1), 0, 1)
        choice = self.branch_choice(candidates[:, :, 0])  # candidates (B, R, 1 + N): each row's value and slopes
        if self.cells:
            cell = cell_index(piece, self.stride)  # (B, Mc): each celled muscle's cell
            at_cell = self.spread[self.rows[None, :], cell]  # (B, Mc, T)
            candidates = xp.concatenate([candidates, product(at_cell, basis[:, self.n_terms:])], 1)
            fitted = self.fitted[self.rows[None, :], cell][:, self.cell_of]
            choice = xp.where(fitted & self.celled, self.cell_col, choice)
        picked = pick(candidates, choice)  # (B, M, 1 + N)
        y, dy = picked[..., 0], picked[..., 1:]
        return y + (dy @ (x64 - inside)[:, :, None])[..., 0], dy, candidates[:, :len(self.box)]


class GravitySnapshot(Frozen):
    """A fitted ``GravityTorque``'s torque ``tau (B, N)`` [N m] at float64 postures ``q (B, N)`` [rad or m], from
    the tree's buffers and, from its coefficients, per frame ``(s, m)`` ``(F, 4, 1)``, each moving joint's mass below
    it ``(J,)``, the offsets and spring rates ``(N,)``; and the tree's kinematics (``full``, ``kinematics``,
    ``slopes``)."""

    def __init__(self, gravity):
        self.__dict__.update(gravity.named_buffers(recurse=False))
        self.node_parent, self.node_chain = gravity.node_parent, gravity.node_chain
        self.coupled, self.all_hinges = gravity.coupled, gravity.all_hinges
        # the rows each pick takes (``GravityTorque._register_nodes``)
        *self.pointers, self.frame_rows, self.before_rows = (getattr(gravity, name) for name in gravity.pick_names)
        n_frames, n_free, coef = gravity.n_frames, gravity.n_free, gravity.coef
        order = torch.arange(4 * n_frames, device=coef.device).view(-1, 4)[:, [1, 2, 3, 0]].flatten()
        self.moment_mass = coef.index_select(0, order).view(-1, 4, 1)
        self.mass_joint = gravity.moves_frame @ coef[:4 * n_frames].view(n_frames, 4)[:, 0]
        self.offset, self.rate = coef[4 * n_frames:4 * n_frames + n_free], coef[4 * n_frames + n_free:]

    def __call__(self, q):
        full = self.full(q)
        frames, o, a = self.kinematics(full)
        w = (frames[..., :3, :] @ self.moment_mass)[..., 0]
        w_joint = rows_product(self.moves_frame, w)
        tau = -((a @ self.gravity_cross_T) * (w_joint - self.mass_joint[:, None] * o)).sum(-1)
        if not self.all_hinges:
            tau = self.hinge * tau + (1.0 - self.hinge) * (-(a @ self.gravity) * self.mass_joint)
        return (tau * self.slopes(full)) @ self.free_scatter + self.offset + self.rate * q

    def full(self, q):
        """Every joint ``(B, nq)`` from the free joints ``q (B, N)`` (``sim.joints.JointMap.full_q``)."""
        full = q @ self.free_select + self.full_base
        if not self.coupled:
            return full
        value = horner(self.dep_horner, take(full, self.dep_follows_index, 1) - self.dep_follows_qpos0)
        return full + (value + self.dep_qpos0 - take(full, self.dep_index, 1)) @ self.dep_scatter

    def slopes(self, full):
        """``(B, J)`` ``d q_full[j] / d q[free_column[j]]`` of each moving joint at every joint's ``full (B, nq)``: 1,
        or its coupling's slope."""
        return horner(self.slope_horner, take(full, self.slope_index, 1) - self.slope_qpos0)

    def kinematics(self, full):
        """The frames' world poses ``(B, F, 4, 4)`` and the moving joints' anchors ``o (B, J, 3)`` and axes
        ``a (B, J, 3)`` at every joint's ``full (B, nq)`` (MuJoCo's mj_kinematics): each body at its parent's pose
        times its offset, then each joint's motion ``I + sin M_sin + versine M_versine + angle M_angle`` (a hinge
        rotates by ``q - qpos0`` about its axis through its anchor, a slide translates; ``_node_poses``)."""
        angle = (take(full, self.chain_joint_index, 1) - self.chain_qpos0)[:, :, None, None]
        by_sin, by_versine, by_angle = self.motion_terms
        xp = self.xp
        motion = self.motion_eye + xp.sin(angle) * by_sin + (1.0 - xp.cos(angle)) * by_versine + angle * by_angle
        world = self._node_poses(motion)
        anchor_axis = take(world, self.before_rows, 1)[..., :3, :] @ self.anchor_axis  # (B, J, 3, 2)
        return take(world, self.frame_rows, 1), anchor_axis[..., 0], anchor_axis[..., 1]

    def _node_poses(self, motion):
        """Every node's world pose ``(B, nodes + 1, 4, 4)`` from the chain joints' motions ``(B, C, 4, 4)``: pointer
        jumping (up to ``JUMP_ROWS`` postures, numpy, exported), else one product per node, parents first."""
        xp = self.xp
        if xp is np or torch.compiler.is_exporting() or motion.shape[0] <= JUMP_ROWS:
            moved = self.node_motion @ motion.reshape(*motion.shape[:2], 16)
            world = self.node_const + moved.reshape(*moved.shape[:2], 4, 4)
            for rows in self.pointers:
                world = take(world, rows, 1) @ world
            return world
        nodes = []
        for i, (parent, chain) in enumerate(zip(self.node_parent, self.node_chain)):
            T = self.node_const[i] if chain < 0 else motion[:, chain]
            nodes.append(xp.broadcast_to(T, (motion.shape[0], 4, 4)) if parent < 0 else nodes[parent] @ T)
        return xp.stack(nodes, 1)


class BodySnapshot(Frozen):
    """``StructuredSchema.body_si``'s arithmetic on a per-muscle path and a gravity torque: ``(l_geo [m] (B, M),
    G [m/rad] (B, M, N), tau [N m] (B, N))`` float64 at postures ``q_rad (B, N)`` [rad], with every cast of
    ``StructuredSchema.body`` (``scales``: ``l_mean``, ``l_std`` (M,), ``arm`` (M, N) in the schema's ``dtype``)."""

    def __init__(self, q_lo, q_hi, dtype, path: PathSnapshot, gravity: GravitySnapshot, scales):
        self.q_lo, self.q_hi, self.dtype, self.float64 = q_lo.to(torch.float64), q_hi.to(torch.float64), dtype, \
            torch.float64
        self.path, self.gravity = path, gravity
        self.l_mean, self.l_std, self.arm = scales

    def __call__(self, q_rad):
        f64 = self.float64
        q_n = as_dtype(encode_q(q_rad, self.q_lo, self.q_hi), self.dtype)
        y, dy, box_rows = self.path(as_dtype(q_n, f64))
        if self.xp is np:  # the path-switch flag reads the rows at the same postures (one assignment: a whole pair)
            self.recent = (q_rad.copy(), box_rows)
        l_geo = self.l_mean + self.l_std * as_dtype(y, self.dtype)
        tau = as_dtype(self.gravity(decode_q(as_dtype(q_n, f64), self.q_lo, self.q_hi)), self.dtype)
        return as_dtype(l_geo, f64), as_dtype(as_dtype(dy, self.dtype) * self.arm, f64), as_dtype(tau, f64)
