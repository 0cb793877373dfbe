"""``PathLayout``: every muscle's path topology as the flat numpy arrays ``paths.module.GeometricPath`` evaluates.

A muscle's path (``paths.parts.path_parts``) is cut into *segments*, site -> site, each optionally through one
wrapping geom (sphere or cylinder, with or without a side site); every muscle's segments are padded to the most any
muscle has (a padded segment runs from the zero *pad point* to itself: no length, no moment arm).

Every *point* (site, geom centre, side site) is a private copy per muscle (two muscles' numbers are independent) and
rides a *frame*: one of the moving frames of ``sim.gravity_tree.gravity_tree`` (the bodies that a free joint moves,
whose world poses ``networks.snapshot.GravitySnapshot.kinematics`` computes) or the world (index ``n_frames``) for a
body nothing moves. A body rigid on its frame (on locked joints) keeps a constant transform to it, ``X_f^-1 X_b``
read from MuJoCo at one posture; a body welded to the world keeps its world pose. A point's position in its frame is
``point_rot @ numbers[point_number] + point_shift``. numpy and MuJoCo only.
"""
from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from ..errors import BodySchemaInputError
from ..sim.gravity_tree import GravityTree, gravity_tree
from .parts import KINDS, numbers, path_parts, true_values

_SPHERE = int(mujoco.mjtGeom.mjGEOM_SPHERE)


@dataclass
class PathLayout:
    """The arrays of every muscle's path (module docstring). ``P`` points (index ``P``: the pad point), ``W`` wrapping
    geoms over all muscles (index ``W``: none), ``M`` muscles of ``S`` segment slots and ``K`` wrap slots, ``F``
    moving frames (index ``F``: the world)."""

    tree: GravityTree  # the moving frames' kinematics
    muscle_names: list  # (M,) tendon names
    tables: list  # M lists of ``(kind, part, component)``: each muscle's numbers (``paths.parts.numbers``)
    numbers: np.ndarray  # (Q,) every muscle's numbers concatenated, the MJCF's values [m]
    number_kind: np.ndarray  # (Q,) index into ``paths.parts.KINDS``
    muscle_start: np.ndarray  # (M + 1,) where each muscle's numbers start in ``numbers``
    point_frame: np.ndarray  # (P,) the frame each point rides (F: the world)
    point_rot: np.ndarray  # (P, 3, 3) its body's orientation in that frame
    point_shift: np.ndarray  # (P, 3) its body's origin in that frame [m]
    point_number: np.ndarray  # (P, 3) the indices of its position in its body within ``numbers``
    seg_start: np.ndarray  # (M, S) each segment's first site (P: padding)
    seg_end: np.ndarray  # (M, S) its last site (P: padding)
    seg_wrap: np.ndarray  # (M, S) its wrapping geom (W: none)
    wrap_slot: np.ndarray  # (M, K) each muscle's wrapping geoms in path order (W: none)
    geom_centre: np.ndarray  # (W,) the geom's centre point
    geom_side: np.ndarray  # (W,) its side site's point (P: none)
    geom_radius: np.ndarray  # (W,) the index of its radius in ``numbers``
    geom_sphere: np.ndarray  # (W,) bool: a sphere (else a cylinder)
    geom_rot: np.ndarray  # (W, 3, 3) its axes in its frame (``geom_quat`` in its body, then the body's rotation)
    geom_start: np.ndarray  # (W,) the site before it
    geom_end: np.ndarray  # (W,) the site after it

    @property
    def n_frames(self) -> int:
        return self.tree.n_frames

    @property
    def n_points(self) -> int:
        return len(self.point_frame)

    @property
    def n_wraps(self) -> int:
        return len(self.geom_centre)

    def muscle_numbers(self, a: int) -> np.ndarray:
        """Muscle ``a``'s MJCF numbers (a copy), in ``paths.parts.numbers`` order."""
        return self.numbers[self.muscle_start[a]:self.muscle_start[a + 1]].copy()


def segments(parts: list[tuple], name: str) -> list[tuple[int, int, int]]:
    """``(first site, geom or -1, last site)`` as indices into ``parts``: the path cut site to site. Refuses what
    MuJoCo allows and the model does not hold (a geom not between two sites, two geoms in a row)."""
    kinds = [p[0] for p in parts]
    bad = [i for i, k in enumerate(kinds) if k == "geom" and not (0 < i < len(kinds) - 1
                                                                  and kinds[i - 1] == kinds[i + 1] == "site")]
    if bad or len(kinds) < 2:
        raise BodySchemaInputError(f"tendon {name!r} has path {kinds}: the geometric path model needs sites at both "
                                   f"ends and every wrapping geom between two sites (one geom per segment)")
    sites = [i for i, k in enumerate(kinds) if k == "site"]
    return [(i, i + 1 if j == i + 2 else -1, j) for i, j in zip(sites[:-1], sites[1:])]


def path_layout(model) -> PathLayout:
    """The ``PathLayout`` of a ``sim.MusculoskeletalModel``'s muscles (``model.muscle_ids``, in order)."""
    m, tree = model.mj_model, gravity_tree(model)
    body_frame, frame_bodies = _body_frames(model, tree)
    build = _Builder(m, body_frame, *_body_in_frames(model, body_frame, frame_bodies))
    names = [mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_TENDON, int(t)) or f"#{int(t)}" for t in model.muscle_ids]
    for tendon, name in zip(model.muscle_ids, names):
        build.muscle(int(tendon), name)
    return build.layout(tree, names)


class _Builder:
    """Accumulates the points, wrapping geoms and segments of one muscle after another (``path_layout``)."""

    def __init__(self, m: mujoco.MjModel, body_frame, body_rot, body_pos):
        self.m, self.body_frame, self.body_rot, self.body_pos = m, body_frame, body_rot, body_pos
        self.tables, self.values, self.points, self.geoms, self.segs, self.slots = [], [], [], [], [], []
        self.n_numbers = 0

    def point(self, body: int, first: int) -> int:
        """A new point on ``body`` whose position is numbers ``first .. first + 2``; its index."""
        self.points.append((int(self.body_frame[body]), self.body_rot[body], self.body_pos[body], first))
        return len(self.points) - 1

    def muscle(self, tendon: int, name: str) -> None:
        m = self.m
        parts = path_parts(m, tendon)
        table = numbers(m, parts)
        first = {}
        for n, (kind, i, _) in enumerate(table):
            first.setdefault((kind, i), self.n_numbers + n)
        at = {i: self.point(int(m.site_bodyid[p[1]]), first["site", i]) for i, p in enumerate(parts) if p[0] == "site"}
        segs, slots = [], []
        for i, g, j in segments(parts, name):
            if g >= 0:
                slots.append(self.geom(parts[g], first, g, at[i], at[j]))
            segs.append((at[i], at[j], slots[-1] if g >= 0 else -1))
        self.tables.append(table)
        self.values.append(true_values(m, parts, table))
        self.segs.append(segs)
        self.slots.append(slots)
        self.n_numbers += len(table)

    def geom(self, part: tuple, first: dict, i: int, start: int, end: int) -> int:
        """A new wrapping geom (part ``i``, between points ``start`` and ``end``); its index."""
        m, g, side = self.m, part[1], part[2]
        body = int(m.geom_bodyid[g])
        axes = np.zeros(9)
        mujoco.mju_quat2Mat(axes, m.geom_quat[g])
        centre = self.point(body, first["geom", i])
        side_point = self.point(int(m.site_bodyid[side]), first["side", i]) if side >= 0 else -1
        self.geoms.append((centre, side_point, first["radius", i], int(m.geom_type[g]) == _SPHERE,
                           self.body_rot[body] @ axes.reshape(3, 3), start, end))
        return len(self.geoms) - 1

    def layout(self, tree: GravityTree, names: list) -> PathLayout:
        n_points, n_geoms = len(self.points), len(self.geoms)
        frame, rot, shift, first = zip(*self.points)
        centre, side, radius, sphere, axes, start, end = zip(*self.geoms) if self.geoms else ([],) * 7
        n_segs, n_slots = max(len(s) for s in self.segs), max((len(s) for s in self.slots), default=0)
        pad = lambda rows, width, fill: np.array([r + [fill] * (width - len(r)) for r in rows], np.int64) \
            .reshape(len(rows), width)  # noqa: E731
        seg = [pad([[s[k] for s in muscle] for muscle in self.segs], n_segs, n_points) for k in (0, 1)]
        wraps = pad([[s[2] if s[2] >= 0 else n_geoms for s in muscle] for muscle in self.segs], n_segs, n_geoms)
        value = np.concatenate(self.values)
        return PathLayout(
            tree=tree, muscle_names=names, tables=self.tables, numbers=value,
            number_kind=np.array([KINDS.index(row[0]) for t in self.tables for row in t], np.int64),
            muscle_start=np.cumsum([0] + [len(t) for t in self.tables]).astype(np.int64),
            point_frame=np.array(frame, np.int64), point_rot=np.stack(rot), point_shift=np.stack(shift),
            point_number=np.array(first, np.int64)[:, None] + np.arange(3),
            seg_start=seg[0], seg_end=seg[1], seg_wrap=wraps, wrap_slot=pad(self.slots, n_slots, n_geoms),
            geom_centre=np.array(centre, np.int64), geom_side=np.array([s if s >= 0 else n_points for s in side],
                                                                        np.int64),
            geom_radius=np.array(radius, np.int64), geom_sphere=np.array(sphere, bool),
            geom_rot=np.array(axes, float).reshape(n_geoms, 3, 3), geom_start=np.array(start, np.int64),
            geom_end=np.array(end, np.int64))


def _body_frames(model, tree: GravityTree) -> tuple[np.ndarray, list]:
    """``(nbody,)`` the frame each body rides: its nearest ancestor (or itself) with a moving joint, F: the world;
    and each frame's body."""
    m = model.mj_model
    frame_bodies = sorted({int(b) for b in m.jnt_bodyid[tree.moving_joint]})  # gravity_tree's frames, in order
    names = [mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, b) or f"#{b}" for b in frame_bodies]
    if names != list(tree.frame_names):  # never: both read the same rule off the same model
        raise RuntimeError(f"the moving frames {names} differ from the gravity tree's {tree.frame_names}")
    index, out = {b: f for f, b in enumerate(frame_bodies)}, np.full(m.nbody, len(frame_bodies), np.int64)
    for b in range(1, m.nbody):  # parents precede children in MuJoCo's body order
        out[b] = index.get(b, out[int(m.body_parentid[b])])
    return out, frame_bodies


def _body_in_frames(model, body_frame: np.ndarray, frame_bodies: list) -> tuple[np.ndarray, np.ndarray]:
    """Every body's rotation ``(nbody, 3, 3)`` and origin ``(nbody, 3)`` in its frame, ``X_f^-1 X_b`` at the range's
    midpoint (constant: only locked joints lie between a body and its frame; the world's bodies: their world pose)."""
    m, data = model.mj_model, mujoco.MjData(model.mj_model)
    data.qpos[:] = model.joint_map.full_q(model.q_range.mean(axis=1)[None])[0]
    mujoco.mj_kinematics(m, data)
    rot, pos = data.xmat.reshape(-1, 3, 3), data.xpos
    owner = np.array(list(frame_bodies) + [0])[body_frame]  # the world body's pose is the identity
    frame_rot_T = np.swapaxes(rot[owner], 1, 2)
    return frame_rot_T @ rot, (frame_rot_T @ (pos - pos[owner])[..., None])[..., 0]
