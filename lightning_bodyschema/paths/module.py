"""``GeometricPath``: every muscle's MuJoCo tendon length and moment arms from its path numbers, in torch.

At postures ``q (B, N)`` the moving frames' poses come from the gravity tree's kinematics
(``networks.snapshot.GravitySnapshot``), every point of every path (``paths.layout``) is placed in the world, each
wrapping geom is wrapped (``paths.wrap.wrap``) and each segment's length is ``|p1 - p0|`` or, wrapped,
``|t0 - p0| + arc + |p1 - t1|`` (MuJoCo's ``mj_tendon``).

Moment arms follow MuJoCo's tendon Jacobian: each straight piece ``u -> v`` (unit direction ``d``) adds
``d . (J_v - J_u)``, a tangent point riding its geom's frame and the arc adding nothing (by the envelope theorem the
length's exact derivative wherever the wrap state is constant). A point ``p`` on frame f moves with joint j that moves
f as ``a_j x (p - o_j)`` (hinge) or ``a_j`` (slide), so ``d . J_p`` on joint j is ``a_j . (p x d) - (a_j x o_j) .
d`` or ``a_j . d``: the pieces' vectors ``(p x d, d)`` (signed: + at a piece's end, - at its start) are summed per
muscle and frame, carried to the joints that move each frame, dotted with each joint's ``(a, a x o)`` and scattered to
the free joints through the couplings' slopes. Float64 throughout; plain PyTorch, no Lightning.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch
from torch import nn

from ..errors import BodySchemaInputError
from ..networks.arrays import apply_keeping_dtype
from ..networks.gravity import GravityTorque
from ..networks.snapshot import GravitySnapshot
from .layout import PathLayout

_F64 = dict(dtype=torch.float64)


class _Wrap(NamedTuple):
    wrapped: torch.Tensor
    t0: torch.Tensor
    t1: torch.Tensor
    arc_m: torch.Tensor
    side_margin_m: torch.Tensor
    inside_margin_m: torch.Tensor
    end_margin_m: torch.Tensor


def _no_wrap(p0, p1, centre, rot, radius, sphere, side, has_side) -> _Wrap:
    """Nothing wraps (``paths.wrap.wrap``'s interface, until it lands): straight paths only."""
    inf = torch.full_like(radius, float("inf"))
    return _Wrap(torch.zeros_like(sphere), p0, p1, torch.zeros_like(radius), inf, inf, inf)


try:
    from .wrap import wrap as _wrap
except ModuleNotFoundError as missing:  # paths/wrap.py not merged yet; any other failure of it is raised
    if missing.name != f"{__package__}.wrap":
        raise
    _wrap = _no_wrap


class GeometricPath(nn.Module):
    """Lengths ``l_m (B, M)`` [m] and moment arms ``G (B, M, N)`` [m per rad or m] of a ``PathLayout``'s muscles at
    free-joint postures ``q (B, N)`` [rad or m] (module docstring), float64 whatever the input's dtype.

    ``numbers`` (Q,) float64 is the only state-dict entry: every muscle's path numbers in ``paths.parts.numbers``
    order (sites', geom centres' and side sites' positions in their bodies [m], radii [m]), starting at the MJCF's.
    The layout's arrays are non-persistent buffers (a schema rebuilds them from its robot's XML); device moves apply
    to every buffer, dtype casts to none. Vectors are held as ``(B, 3, K)`` (coordinates first: each coordinate's
    row contiguous over the K points)."""

    def __init__(self, layout: PathLayout):
        super().__init__()
        self.muscle_names, self.muscle_start = list(layout.muscle_names), layout.muscle_start.tolist()
        self.number_kind = layout.number_kind.copy()
        self.kinematics = GravityTorque(layout.tree)
        self.kinematics.register_buffer("coef", self.kinematics.coef, persistent=False)  # masses: not a path's
        self.register_buffer("numbers", torch.tensor(layout.numbers, **_F64))
        tables = _tables(layout)
        for name, value in tables.items():
            kind = torch.long if value.dtype == np.int64 else torch.bool if value.dtype == bool else torch.float64
            self.register_buffer(name, torch.as_tensor(value, dtype=kind), persistent=False)
        self.register_buffer("world", torch.eye(4, **_F64)[None, None, :3], persistent=False)
        self.n_muscles, self.n_wrap_slots = len(self.muscle_names), layout.wrap_slot.shape[1]
        frame_of_live = np.append(layout.point_frame, layout.n_frames)[tables["live"]]  # (numpy: a meta skeleton)
        self.live_frames = sorted(set(frame_of_live.tolist()))  # the frames the live points ride, in order
        self.live_counts = [int((frame_of_live == f).sum()) for f in self.live_frames]

    def _apply(self, fn, *args, **kwargs):
        """Device moves apply to every buffer; dtype casts do not (the geometry stays float64)."""
        return apply_keeping_dtype(self, list(self._buffers), super()._apply, fn, *args, **kwargs)

    # ------------------------------------------------------------------ numbers
    def set_numbers(self, per_muscle: list) -> None:
        """Every muscle's numbers (M arrays in ``paths.parts.numbers`` order [m]): finite, radii > 0."""
        sizes = np.diff(self.muscle_start)
        if len(per_muscle) != len(sizes):
            raise BodySchemaInputError(f"set_numbers got {len(per_muscle)} muscles' numbers; the path has "
                                       f"{len(sizes)} muscles {self.muscle_names}")
        for a, (values, size) in enumerate(zip(per_muscle, sizes)):
            values = np.asarray(values, float)
            radii = values[self.number_kind[self.muscle_start[a]:self.muscle_start[a + 1]] == 2] \
                if values.shape == (size,) else values
            if values.shape != (size,) or not np.isfinite(values).all() or (radii <= 0).any():
                raise BodySchemaInputError(f"numbers of muscle {self.muscle_names[a]!r} are {values!r}; give {size} "
                                           "finite values [m] in paths.parts.numbers order, radii > 0")
        flat = np.concatenate([np.asarray(v, float) for v in per_muscle])
        with torch.no_grad():
            self.numbers.copy_(torch.as_tensor(flat, **_F64))

    def muscle_numbers(self, a: int) -> np.ndarray:
        """Muscle ``a``'s numbers (a host copy, ``paths.parts.numbers`` order) [m]."""
        return self.numbers[self.muscle_start[a]:self.muscle_start[a + 1]].detach().cpu().numpy().copy()

    # ------------------------------------------------------------------ evaluation
    def forward(self, q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(l_m (B, M) [m], G (B, M, N) = d l_m / d q)`` at postures ``q (B, N)``, float64."""
        length, arm, _ = self._evaluate(q)
        return length, arm

    def margins(self, q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``(side_margin, inside_margin, end_margin)``, each ``(B, M, K)`` [m], of each muscle's wrapping geoms in path
        order (``paths.wrap.wrap``'s margins: every jump of a path is where one of them changes sign; +inf where a
        margin does not apply and in slots without a geom)."""
        return self._evaluate(q)[2]

    def _evaluate(self, q: torch.Tensor):
        """Lengths, moment arms and the wrap margins at postures ``q (B, N)``."""
        q = q.to(torch.float64)
        tree = GravitySnapshot(self.kinematics)
        full = tree.full(q)
        frames, o, a = tree.kinematics(full)
        frames = torch.cat([frames[..., :3, :], self.world.expand(q.shape[0], 1, 3, 4)], 1)  # (B, F + 1, 3, 4)
        local = torch.einsum("pij,pj->ip", self.point_rot, self.numbers[self.point_number]) + self.point_shift.T
        points = self._points(frames, local.index_select(1, self.live))
        take = lambda rows: points.index_select(2, rows)  # noqa: E731
        p0, p1 = take(self.straight_start), take(self.straight_end)
        straight = _norm(p1 - p0)
        wraps = self._wraps(points, frames)
        q0, q1, (wrapped, t0, t1, arc) = take(self.geom_start), take(self.geom_end), wraps[:4]
        wrapped_m = torch.where(wrapped, _norm(t0 - q0) + arc + _norm(q1 - t1), _norm(q1 - q0))
        length = self._lengths(local, torch.cat([straight, wrapped_m], 1))
        entries = torch.cat([_straight_vectors(p0, p1, straight), _wrap_vectors(q0, q1, wrapped, t0, t1)], 2)
        arm = self._arms(entries, o, a, tree.slopes(full))
        margins = tuple(torch.cat([w, torch.full_like(w[:, :1], float("inf"))], 1).index_select(1, self.wrap_slot)
                        .view(q.shape[0], self.n_muscles, self.n_wrap_slots) for w in wraps[4:])
        return length, arm, margins

    def _lengths(self, local: torch.Tensor, moving: torch.Tensor) -> torch.Tensor:
        """``(B, M)`` [m]: each muscle's segments between frames ``moving (B, S)`` plus those within one frame (a
        constant, from the points' frame coordinates ``local (3, P)``)."""
        within = local.index_select(1, self.fixed_end) - local.index_select(1, self.fixed_start)
        fixed = local.new_zeros(self.n_muscles).index_add(0, self.fixed_muscle, torch.linalg.vector_norm(within, dim=0))
        return moving.new_zeros(moving.shape[0], self.n_muscles).index_add(1, self.segment_muscle, moving) + fixed

    def _points(self, frames: torch.Tensor, local: torch.Tensor) -> torch.Tensor:
        """The world positions ``(B, 3, L)`` [m] of the points ``live`` (sorted by frame: one product per frame) at
        their frame coordinates ``local (3, L)``."""
        pieces = local.split(self.live_counts, 1)
        return torch.cat([frames[:, f, :, :3] @ part + frames[:, f, :, 3:] for f, part in
                          zip(self.live_frames, pieces) if part.shape[1]], 2)

    def _wraps(self, points: torch.Tensor, frames: torch.Tensor) -> tuple:
        """Every wrapping geom's ``paths.wrap.Wrap``: ``wrapped (B, W)``, ``t0``, ``t1`` ``(B, 3, W)``, the arc and
        the three margins ``(B, W)`` [m]."""
        batch, take = points.shape[0], lambda rows: points.index_select(2, rows).transpose(1, 2)  # noqa: E731
        if not len(self.geom_start):
            empty = points.new_zeros(batch, 0)
            return empty.bool(), points[..., :0], points[..., :0], empty, empty, empty, empty
        rot = frames.index_select(1, self.geom_frame)[..., :3] @ self.geom_rot
        out = _wrap(take(self.geom_start), take(self.geom_end), take(self.geom_centre), rot,
                    self.numbers[self.geom_radius].expand(batch, -1), self.geom_sphere.expand(batch, -1),
                    take(self.geom_side), self.geom_has_side.expand(batch, -1))
        return out[0], out[1].transpose(1, 2), out[2].transpose(1, 2), *out[3:]

    def _arms(self, entries: torch.Tensor, o: torch.Tensor, a: torch.Tensor, slopes: torch.Tensor) -> torch.Tensor:
        """``G (B, M, N)`` from the pieces' signed vectors ``(p x d, d)`` ``entries (B, 6, E)``: summed per muscle and
        frame, dotted with each joint's ``(a, -(a x o))`` (hinge) or ``(0, a)`` (slide) where the joint moves the
        frame, summed per muscle, times the couplings' slopes ``(B, J)`` onto the free joints."""
        batch = entries.shape[0]
        per_bin = entries.new_zeros(batch, 6, len(self.bin_muscle)).index_add(2, self.entry_bin, entries)
        hinge = self.kinematics.hinge[:, None]
        weights = torch.cat([hinge * a, (1.0 - hinge) * a - hinge * torch.linalg.cross(a, o)], -1)  # (B, J, 6)
        per_joint = (weights @ per_bin) * self.bin_moves  # (B, J, bins)
        joint_arm = per_joint.new_zeros(batch, per_joint.shape[1], self.n_muscles).index_add(
            2, self.bin_muscle, per_joint) * slopes[:, :, None]
        return (self.kinematics.free_scatter.T @ joint_arm).transpose(1, 2)


def _norm(v: torch.Tensor) -> torch.Tensor:
    """``|v|`` ``(B, K)`` of ``(B, 3, K)`` vectors (by rows: a norm over the strided axis is several times slower)."""
    x, y, z = v.unbind(1)
    return torch.sqrt(x * x + y * y + z * z)


def _cross(u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """``u x v`` of ``(B, 3, K)`` vectors."""
    ux, uy, uz = u.unbind(1)
    vx, vy, vz = v.unbind(1)
    return torch.stack([uy * vz - uz * vy, uz * vx - ux * vz, ux * vy - uy * vx], 1)


def _unit(v: torch.Tensor, norm: torch.Tensor | None = None) -> torch.Tensor:
    """``v / |v|`` of ``(B, 3, K)`` vectors, 0 for a zero vector (an unwrapped segment's second piece)."""
    norm = _norm(v) if norm is None else norm
    return v / torch.where(norm > 0, norm, torch.ones_like(norm))[:, None]


def _piece(start: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
    """``(start x d, d)`` ``(B, 6, K)``: a straight piece from ``start`` along ``d`` (any point of it gives the same
    ``p x d``)."""
    return torch.cat([_cross(start, d), d], 1)


def _straight_vectors(p0, p1, length) -> torch.Tensor:
    """The entries of the straight segments between two frames ``(B, 6, 2 S)``: - at the start, + at the end."""
    v = _piece(p0, _unit(p1 - p0, length))
    return torch.cat([-v, v], 2)


def _wrap_vectors(p0, p1, wrapped, t0, t1) -> torch.Tensor:
    """The entries of the segments through a geom ``(B, 6, 3 W)``: at the first site's frame, the last site's and the
    geom's. Wrapped: pieces ``p0 -> t0`` (A) and ``t1 -> p1`` (B), so - A, + B and A - B; else one piece
    ``p0 -> p1``: - A, + A and 0."""
    around = wrapped[:, None]
    a = _piece(p0, _unit(torch.where(around, t0, p1) - p0))
    b = _piece(p1, _unit(p1 - torch.where(around, t1, p1)))
    return torch.cat([-a, torch.where(around, b, a), torch.where(around, a - b, 0.0)], 2)


def _tables(layout: PathLayout) -> dict:
    """The module's index tables (numpy) from the layout's padded segments: segments within one frame (a constant
    length: ``fixed_*``, in point ids), straight segments between frames (``straight_*``) and through a geom
    (``geom_*``), both in ``live`` positions (the points placed at every posture); the pieces' entries' bins, one per
    muscle and frame that a piece ends on (bin 0: the world's, moved by no joint), each bin's muscle and moving
    joints."""
    n_points, n_geoms, n_frames = layout.n_points, layout.n_wraps, layout.n_frames
    frame = np.append(layout.point_frame, n_frames)  # the pad point rides the world
    muscle = np.broadcast_to(np.arange(len(layout.muscle_names))[:, None], layout.seg_start.shape)
    start, end, through = layout.seg_start, layout.seg_end, layout.seg_wrap
    geomless = (start < n_points) & (through == n_geoms)
    same = geomless & (frame[start] == frame[end])
    between = geomless & ~same
    side = np.where(layout.geom_side < n_points, layout.geom_side, layout.geom_centre)  # no side site: ignored
    live = np.unique(np.concatenate([start[between], end[between], layout.geom_start, layout.geom_end,
                                     layout.geom_centre, side]))
    live = live[np.argsort(frame[live], kind="stable")]  # by frame: ``GeometricPath._points``
    at = np.zeros(n_points + 1, np.int64)
    at[live] = np.arange(len(live))  # a live point's position in ``live``
    geom_muscle = np.repeat(np.arange(len(layout.muscle_names)), (layout.wrap_slot < n_geoms).sum(1))
    geom_frame = frame[layout.geom_centre]
    ends = [(muscle[between], frame[start[between]]), (muscle[between], frame[end[between]])] + \
        [(geom_muscle, frame[layout.geom_start]), (geom_muscle, frame[layout.geom_end]), (geom_muscle, geom_frame)]
    pairs = sorted({(m, f) for ms, fs in ends for m, f in zip(ms.tolist(), fs.tolist()) if f < n_frames})
    bin_of = {pair: b + 1 for b, pair in enumerate(pairs)}
    moves = np.hstack([np.zeros((len(layout.tree.moving_joint), 1)), layout.tree.moves_frame[:, [f for _, f in pairs]]])
    return dict(
        point_rot=layout.point_rot, point_shift=layout.point_shift, point_number=layout.point_number,
        live=live,
        fixed_start=start[same], fixed_end=end[same], fixed_muscle=muscle[same],
        straight_start=at[start[between]], straight_end=at[end[between]],
        segment_muscle=np.concatenate([muscle[between], geom_muscle]),
        geom_start=at[layout.geom_start], geom_end=at[layout.geom_end], geom_centre=at[layout.geom_centre],
        geom_side=at[side], geom_has_side=layout.geom_side < n_points, geom_frame=geom_frame,
        geom_rot=layout.geom_rot, geom_radius=layout.geom_radius, geom_sphere=layout.geom_sphere,
        wrap_slot=layout.wrap_slot.ravel(),
        entry_bin=np.array([bin_of.get((m, f), 0) for ms, fs in ends for m, f in zip(ms.tolist(), fs.tolist())],
                           np.int64),
        bin_muscle=np.array([0] + [m for m, _ in pairs], np.int64), bin_moves=moves)
