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


def _no_wrap(p0, p1, centre, rot, radius, sphere, side, has_side) -> _Wrap:
    """Nothing wraps (``paths.wrap.wrap``'s interface, until it lands): straight paths only."""
    inf = torch.full_like(radius, float("inf"))
    return _Wrap(torch.zeros_like(sphere), p0, p1, torch.zeros_like(radius), inf, inf)


try:
    from .wrap import wrap as _wrap
except ImportError:  # paths/wrap.py not merged yet
    _wrap = _no_wrap


def _unit(v: torch.Tensor) -> torch.Tensor:
    """``v / |v|``, 0 for a zero vector (a padded segment, an unwrapped segment's second piece)."""
    norm = torch.linalg.vector_norm(v, dim=-1, keepdim=True)
    return v / torch.where(norm > 0, norm, torch.ones_like(norm))


class GeometricPath(nn.Module):
    """Lengths ``l_m (B, M)`` [m] and moment arms ``G (B, M, N)`` [m per rad or m] of a ``PathLayout``'s muscles at
    free-joint postures ``q (B, N)`` [rad or m] (module docstring), float64 whatever the input's dtype.

    ``numbers`` (Q,) float64 is the only state-dict entry: every muscle's path numbers in ``paths.parts.numbers``
    order (sites', geom centres' and side sites' positions in their bodies [m], radii [m]), starting at the MJCF's.
    The layout's arrays are non-persistent buffers (a schema rebuilds them from its robot's XML); device moves apply
    to every buffer, dtype casts to none."""

    def __init__(self, layout: PathLayout):
        super().__init__()
        self.muscle_names, self.muscle_start = list(layout.muscle_names), layout.muscle_start.tolist()
        self.number_kind = layout.number_kind.copy()
        self.kinematics = GravityTorque(layout.tree)
        self.kinematics.register_buffer("coef", self.kinematics.coef, persistent=False)  # masses: not a path's
        self.register_buffer("numbers", torch.tensor(layout.numbers, **_F64))
        n_muscles, n_frames = len(layout.muscle_names), layout.n_frames + 1  # the world last
        long = lambda a: torch.as_tensor(np.ascontiguousarray(a), dtype=torch.long)  # noqa: E731
        point_frame = np.append(layout.point_frame, layout.n_frames)  # the pad point rides the world
        seg_frames = np.stack([point_frame[layout.seg_start], point_frame[layout.seg_end]], -1)
        geom_frame = np.append(layout.point_frame[layout.geom_centre], layout.n_frames)[layout.seg_wrap]
        endpoint_frame = np.concatenate([seg_frames, geom_frame[..., None]], -1)  # (M, S, 3): start, end, geom
        buffers = dict(
            point_frame=long(layout.point_frame), point_rot=torch.tensor(layout.point_rot, **_F64),
            point_shift=torch.tensor(layout.point_shift, **_F64), point_number=long(layout.point_number),
            seg_start=long(layout.seg_start.ravel()), seg_end=long(layout.seg_end.ravel()),
            seg_wrap=long(layout.seg_wrap.ravel()), wrap_slot=long(layout.wrap_slot.ravel()),
            geom_centre=long(layout.geom_centre), geom_side=long(layout.geom_side),
            geom_radius=long(layout.geom_radius), geom_sphere=torch.as_tensor(layout.geom_sphere),
            geom_has_side=torch.as_tensor(layout.geom_side < layout.n_points),
            geom_rot=torch.tensor(layout.geom_rot, **_F64), geom_frame=long(layout.point_frame[layout.geom_centre]),
            geom_start=long(layout.geom_start), geom_end=long(layout.geom_end),
            endpoint_bin=long((np.arange(n_muscles)[:, None, None] * n_frames + endpoint_frame).ravel()),
            moves=torch.cat([torch.tensor(layout.tree.moves_frame, **_F64),
                             torch.zeros(len(layout.tree.moving_joint), 1, **_F64)], 1),
            world=torch.eye(4, **_F64)[None, None, :3])
        for name, value in buffers.items():
            self.register_buffer(name, value, persistent=False)
        self.n_muscles, self.n_frames, self.n_slots = n_muscles, n_frames, layout.seg_start.shape[1]
        self.n_wrap_slots = layout.wrap_slot.shape[1]

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

    def margins(self, q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(side_margin (B, M, K), inside_margin (B, M, K))`` [m] of each muscle's wrapping geoms in path order
        (``paths.wrap.wrap``'s margins; +inf in slots without a geom)."""
        return self._evaluate(q)[2]

    def _evaluate(self, q: torch.Tensor):
        """Lengths, moment arms and the wrap margins at postures ``q (B, N)``."""
        q = q.to(torch.float64)
        tree = GravitySnapshot(self.kinematics)
        full = tree.full(q)
        frames, o, a = tree.kinematics(full)
        frames = torch.cat([frames[..., :3, :], self.world.expand(q.shape[0], 1, 3, 4)], 1)  # (B, F + 1, 3, 4)
        points = self._points(frames)
        wraps = self._wraps(points, frames)
        p0, p1 = points.index_select(1, self.seg_start), points.index_select(1, self.seg_end)  # (B, M S, 3)
        wrapped, t0, t1, arc = (w.index_select(1, self.seg_wrap) for w in wraps[:4])
        norm = lambda v: torch.linalg.vector_norm(v, dim=-1)  # noqa: E731
        segment = torch.where(wrapped, norm(t0 - p0) + arc + norm(p1 - t1), norm(p1 - p0))
        length = segment.view(q.shape[0], self.n_muscles, self.n_slots).sum(-1)
        joint_arm = self._joint_arms(self._piece_vectors(p0, p1, wrapped, t0, t1), o, a)  # (B, M, J)
        arm = (joint_arm * tree.slopes(full)[:, None]) @ tree.free_scatter
        margins = tuple(w.index_select(1, self.wrap_slot).view(q.shape[0], self.n_muscles, self.n_wrap_slots)
                        for w in wraps[4:])
        return length, arm, margins

    def _points(self, frames: torch.Tensor) -> torch.Tensor:
        """Every point's world position ``(B, P + 1, 3)`` [m], the pad point (0) last."""
        local = torch.einsum("pij,pj->pi", self.point_rot, self.numbers[self.point_number]) + self.point_shift
        pose = frames.index_select(1, self.point_frame)  # (B, P, 3, 4)
        world = torch.einsum("bpij,pj->bpi", pose[..., :3], local) + pose[..., 3]
        return torch.cat([world, world.new_zeros(world.shape[0], 1, 3)], 1)

    def _wraps(self, points: torch.Tensor, frames: torch.Tensor) -> tuple:
        """Every wrapping geom's ``paths.wrap.Wrap`` fields ``(B, W + 1, ...)``, a geom-less slot's (nothing wrapped,
        margins +inf) last."""
        batch, take = points.shape[0], lambda rows: points.index_select(1, rows)  # noqa: E731
        none = (torch.zeros(batch, 1, dtype=torch.bool, device=points.device), points.new_zeros(batch, 1, 3),
                points.new_zeros(batch, 1, 3), points.new_zeros(batch, 1),
                points.new_full((batch, 1), float("inf")), points.new_full((batch, 1), float("inf")))
        if not len(self.geom_centre):
            return none
        rot = frames.index_select(1, self.geom_frame)[..., :3] @ self.geom_rot
        out = _wrap(take(self.geom_start), take(self.geom_end), take(self.geom_centre), rot,
                    self.numbers[self.geom_radius].expand(batch, -1), self.geom_sphere.expand(batch, -1),
                    take(self.geom_side), self.geom_has_side.expand(batch, -1))
        return tuple(torch.cat([field, pad], 1) for field, pad in zip(out, none))

    def _piece_vectors(self, p0, p1, wrapped, t0, t1) -> torch.Tensor:
        """``(B, M S, 3, 6)``: per segment the signed ``(p x d, d)`` of its start (on the first site's frame), its end
        (the last site's) and its tangent points (the geom's; zero unwrapped): ``p0 -> t0``, ``t1 -> p1`` wrapped, else
        ``p0 -> p1``."""
        around = wrapped[..., None]
        d0, d1 = _unit(torch.where(around, t0, p1) - p0), _unit(p1 - torch.where(around, t1, p0))
        g0, g1 = torch.where(around, t0, 0.0), torch.where(around, t1, 0.0)
        cross = torch.linalg.cross
        return torch.stack([torch.cat([-cross(p0, d0), -d0], -1), torch.cat([cross(p1, d1), d1], -1),
                            torch.cat([cross(g0, d0) - cross(g1, d1), d0 - d1], -1)], 2)

    def _joint_arms(self, vectors: torch.Tensor, o: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
        """``(B, M, J)`` each muscle's moment arm on each moving joint: the piece vectors summed per muscle and frame,
        carried to the joints moving each frame, dotted with the joint's ``(a, -(a x o))`` (hinge) or ``(0, a)``
        (slide)."""
        batch = vectors.shape[0]
        per_frame = vectors.new_zeros(batch, self.n_muscles * self.n_frames, 6).index_add(
            1, self.endpoint_bin, vectors.flatten(1, 2))
        per_joint = self.moves @ per_frame.view(batch, self.n_muscles, self.n_frames, 6)  # (B, M, J, 6)
        hinge = self.kinematics.hinge[:, None]
        weights = torch.cat([hinge * a, (1.0 - hinge) * a - hinge * torch.linalg.cross(a, o)], -1)  # (B, J, 6)
        return (per_joint * weights[:, None]).sum(-1)
