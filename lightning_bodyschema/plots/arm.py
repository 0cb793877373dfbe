"""Draw a tendon-driven arm and its muscle paths in its plane of motion, straight from MuJoCo's geometry.

Everything drawn is what MuJoCo computes at each posture (``mj_forward``): link capsules from
``geom_xpos``/``geom_xmat``, joint anchors from ``xanchor``, wrapping cylinders and spheres as circles,
and each muscle from its wrap points (``wrap_xpos``, ``wrap_obj``, ``ten_wrapadr``, ``ten_wrapnum``),
with the arc on a wrapping surface drawn in the sense the tendon arrives in. So the figure shows
the routing the physics really uses, and a routing bug is visible.

The drawing plane is perpendicular to the first hinge axis (the x-y plane for the paper arm; the
world x-z plane for a z-up model converted from OpenSim), oriented with "up" against gravity and
+q turning counter-clockwise. Points off that plane (3-D via sites, sphere wraps) are projected.
"""
from __future__ import annotations

import io
import os
from dataclasses import dataclass
from typing import Sequence

import mujoco
import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.patches import Circle
from matplotlib.ticker import MaxNLocator

from ..errors import BodySchemaInputError
from ..npz import atomic_write_bytes
from ..sim.model import MusculoskeletalModel

_CYL, _SPHERE = int(mujoco.mjtGeom.mjGEOM_CYLINDER), int(mujoco.mjtGeom.mjGEOM_SPHERE)
_CAPSULE = int(mujoco.mjtGeom.mjGEOM_CAPSULE)
_PULLEY = -2
_TAB10 = ["#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f", "#bcbd22", "#17becf"]


@dataclass(frozen=True)
class ViewPlane:
    """An orthonormal drawing basis: ``right``, ``up`` in the plane, ``normal`` = right x up (world)."""

    right: np.ndarray
    up: np.ndarray

    @property
    def normal(self) -> np.ndarray:
        return np.cross(self.right, self.up)

    def xy(self, points) -> np.ndarray:
        """(..., 3) world points [m] -> (..., 2) drawing coordinates [m]."""
        points = np.asarray(points, dtype=float)
        return np.stack([points @ self.right, points @ self.up], axis=-1)

    def label(self, axis: np.ndarray) -> str:
        """'x [m]', '-y [m]', ... when the axis is a world axis, else 'in-plane [m]'."""
        k = int(np.argmax(np.abs(axis)))
        if abs(abs(axis[k]) - 1.0) > 1e-9:
            return "in-plane [m]"
        return f"{'-' if axis[k] < 0 else ''}{'xyz'[k]} [m]"


def view_plane(m: mujoco.MjModel, d: mujoco.MjData, joint: int | None = None) -> ViewPlane:
    """The plane perpendicular to the axis of hinge ``joint`` (default: the first hinge), "up" against gravity (or
    along world z / y).

    Needs ``mj_kinematics`` on ``d``. For a model without hinges (slide joints only) the x-y plane.
    """
    hinges = [j for j in range(m.njnt) if int(m.jnt_type[j]) == int(mujoco.mjtJoint.mjJNT_HINGE)]
    if joint is not None:
        hinges = [joint]
    normal = d.xaxis[hinges[0]].copy() if hinges else np.array([0.0, 0.0, 1.0])
    normal /= np.linalg.norm(normal)
    for candidate in (-np.asarray(m.opt.gravity, float), np.array([0.0, 1.0, 0.0]), np.array([0.0, 0.0, 1.0])):
        up = candidate - normal * (candidate @ normal)
        if np.linalg.norm(up) > 1e-6 * max(np.linalg.norm(candidate), 1e-300):
            up /= np.linalg.norm(up)
            return ViewPlane(right=np.cross(up, normal), up=up)
    raise AssertionError("unreachable: y and z cannot both be parallel to one normal")


def _wrap_geoms(m: mujoco.MjModel) -> set[int]:
    """Geoms that some tendon wraps around (drawn as circles, not as links)."""
    kinds = (int(mujoco.mjtWrap.mjWRAP_CYLINDER), int(mujoco.mjtWrap.mjWRAP_SPHERE))
    return {int(g) for g, t in zip(m.wrap_objid, m.wrap_type) if int(t) in kinds}


def _arc(center, axis, start, end, incoming, n: int = 24) -> np.ndarray:
    """(n, 3) points on the wrapping surface from ``start`` to ``end``, turning the way the tendon arrives."""
    r1, r2 = start - center, end - center
    if axis is None:  # sphere: the geodesic lies in the plane of r1 and the incoming direction
        axis = np.cross(r1, incoming)
    axis = axis / (np.linalg.norm(axis) + 1e-300)
    p1, p2 = r1 - axis * (r1 @ axis), r2 - axis * (r2 @ axis)
    e1 = p1 / (np.linalg.norm(p1) + 1e-300)
    e2 = np.cross(axis, e1)
    theta = np.arctan2(p2 @ e2, p2 @ e1)
    turn = axis @ np.cross(r1, incoming)
    if abs(turn) > 1e-12:  # follow the incoming sense; else take the shorter way round
        theta = theta % (2 * np.pi) if turn > 0 else theta % (2 * np.pi) - 2 * np.pi
    s = np.linspace(0.0, 1.0, n)[:, None]
    ring = np.linalg.norm(p1) * (np.cos(s * theta) * e1 + np.sin(s * theta) * e2)
    return center + ring + axis * ((1 - s) * (r1 @ axis) + s * (r2 @ axis))


def _wrap_axis(m, d, geom: int):
    """Cylinder axis in world frame; None for a sphere (its arc plane comes from the tendon)."""
    return None if int(m.geom_type[geom]) == _SPHERE else d.geom_xmat[geom].reshape(3, 3)[:, 2].copy()


def muscle_polylines(m: mujoco.MjModel, d: mujoco.MjData, tendon: int) -> list[np.ndarray]:
    """World points (K, 3) [m] of one spatial tendon's path, one array per pulley branch."""
    adr, num = int(d.ten_wrapadr[tendon]), int(d.ten_wrapnum[tendon])
    pts, objs = d.wrap_xpos.reshape(-1, 3)[adr:adr + num], d.wrap_obj.reshape(-1)[adr:adr + num]
    paths, path, k = [], [], 0
    while k < num:
        if objs[k] == _PULLEY:
            if path:
                paths.append(np.array(path))
            path, k = [], k + 1
            continue
        if objs[k] >= 0 and k + 1 < num and objs[k + 1] == objs[k] and path:
            g = int(objs[k])
            path.extend(_arc(d.geom_xpos[g], _wrap_axis(m, d, g), pts[k], pts[k + 1], pts[k] - path[-1]))
            k += 2
            continue
        path.append(pts[k])
        k += 1
    return paths + ([np.array(path)] if path else [])


def _link_geoms(m: mujoco.MjModel, skip: set[int]) -> list[int]:
    """Capsules and cylinders drawn as links: not wrapping surfaces, not cylinders wider than long (platforms)."""
    return [g for g in range(m.ngeom) if g not in skip and (int(m.geom_type[g]) == _CAPSULE or (
        int(m.geom_type[g]) == _CYL and m.geom_size[g, 0] <= m.geom_size[g, 1]))]


def _link_segments(m, d, skip: set[int]) -> list[np.ndarray]:
    """(2, 3) world ends [m] of each link geom's axis."""
    return [np.stack([d.geom_xpos[g] - h, d.geom_xpos[g] + h]) for g in _link_geoms(m, skip)
            for h in [d.geom_xmat[g].reshape(3, 3)[:, 2] * m.geom_size[g, 1]]]


def _draw_links(ax: Axes, m, d, skip: set[int], plane: ViewPlane):
    """Link geoms as thick grey lines over a thin skeleton joining each body's origin to its parent's (it shows where
    only meshes are, e.g. a prosthesis's knee); if a model has no link geom at all, a thick skeleton."""
    segments = _link_segments(m, d, skip)
    for b in range(1, m.nbody):
        if m.body_parentid[b] > 0 or not segments:
            xy = plane.xy(d.xpos[[m.body_parentid[b], b]])
            thin = bool(segments)
            ax.plot(xy[:, 0], xy[:, 1], color="0.45" if thin else "0.6", lw=2.5 if thin else 7, solid_capstyle="round",
                    zorder=0.9)
    for ends in segments:
        xy = plane.xy(ends)
        ax.plot(xy[:, 0], xy[:, 1], color="0.6", lw=7, solid_capstyle="round", zorder=1)


def _draw_wrap_surfaces(ax: Axes, m, d, wraps: set[int], plane: ViewPlane):
    """Cylinders (seen along their axis) and spheres as circles; spheres dashed to tell them apart."""
    for g in sorted(wraps):
        sphere = int(m.geom_type[g]) == _SPHERE
        ax.add_patch(Circle(plane.xy(d.geom_xpos[g]), m.geom_size[g, 0], facecolor=(0.3, 0.6, 0.9, 0.12),
                            edgecolor=(0.2, 0.45, 0.75, 0.8), lw=0.8, ls="--" if sphere else "-", zorder=2))


_MAX_LABELLED = 12  # more muscles than this (myoArm's 50) are drawn thinner and without a legend entry each


def _draw_muscles(ax: Axes, model: MusculoskeletalModel, d, label: bool, plane: ViewPlane):
    for k, (tendon, name) in enumerate(zip(model.muscle_ids, model.muscle_names)):
        color = _TAB10[k % len(_TAB10)]
        for j, path in enumerate(muscle_polylines(model.mj_model, d, int(tendon))):
            xy = plane.xy(path)
            ax.plot(xy[:, 0], xy[:, 1], color=color, lw=1.8 if model.n_muscles <= _MAX_LABELLED else 0.9, zorder=4,
                    label=name if label and j == 0 and model.n_muscles <= _MAX_LABELLED else None)
            ax.plot(xy[[0, -1], 0], xy[[0, -1], 1], "o", color=color, ms=3, zorder=5)


def _draw_joints_and_site(ax: Axes, m, d, site: str, plane: ViewPlane):
    anchors = plane.xy(d.xanchor)
    ax.plot(anchors[:, 0], anchors[:, 1], "o", mfc="white", mec="black", ms=6, zorder=6)
    sid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, site)
    if sid >= 0:
        xy = plane.xy(d.site_xpos[sid])
        ax.plot(*xy, "s", color="black", ms=6, zorder=6)
        ax.annotate(site, xy, xytext=(6, -10), textcoords="offset points", fontsize=8)


def _draw_posture(ax: Axes, model: MusculoskeletalModel, d, site: str, label: bool, plane: ViewPlane):
    """Everything at the posture currently in ``d`` (after mj_forward). Arrays are copied: d is reused."""
    m = model.mj_model
    wraps = _wrap_geoms(m)
    _draw_links(ax, m, d, wraps, plane)
    _draw_wrap_surfaces(ax, m, d, wraps, plane)
    _draw_muscles(ax, model, d, label, plane)
    _draw_joints_and_site(ax, m, d, site, plane)


def _draw_gravity(ax: Axes, gravity: np.ndarray, plane: ViewPlane):
    """Arrow in the upper right corner along gravity's in-plane direction."""
    g_xy = plane.xy(np.asarray(gravity, dtype=float))
    norm = np.linalg.norm(g_xy)
    if norm < 1e-9:
        ax.text(0.97, 0.95, "g ⟂ drawing plane", transform=ax.transAxes, ha="right", va="top", fontsize=8)
        return
    tail, head = np.array([0.9, 0.92]), np.array([0.9, 0.92]) + 0.12 * g_xy / norm
    ax.annotate("", xy=head, xytext=tail, xycoords="axes fraction",
                arrowprops=dict(arrowstyle="-|>", color="black", lw=1.5))
    ax.text(tail[0] - 0.03, (tail[1] + head[1]) / 2, f"g\n{np.linalg.norm(gravity):.2f} m/s²",
            transform=ax.transAxes, ha="right", va="center", fontsize=8)


def _check_postures(model: MusculoskeletalModel, qs) -> np.ndarray:
    q = model.check_q(qs)
    lo, hi = model.q_range.T
    bad = np.flatnonzero(((q < lo - 1e-9) | (q > hi + 1e-9)).any(axis=1))
    if bad.size:
        raise BodySchemaInputError(
            f"posture {q[bad[0]].tolist()} is outside the joint ranges {model.q_range.tolist()}")
    return q


def _new_grid(n_postures: int, n_zoom: int, n_joints: int) -> tuple[Figure, np.ndarray]:
    """Agg figure: row 0 the whole arm (shared limits), then one zoom row per joint; a column per posture. Titles
    beyond 4 lines (over 8 joints) get their own height."""
    title_in = 0.17 * max(0, -(-n_joints // 2) - 4)
    fig = Figure(figsize=(3.6 * n_postures, 4.2 + title_in + 2.6 * n_zoom), dpi=150, layout="constrained")
    grid = fig.subplots(1 + n_zoom, n_postures, squeeze=False, height_ratios=[1.5] + [1.0] * n_zoom)
    for a in grid[0, 1:]:
        a.sharex(grid[0, 0])
        a.sharey(grid[0, 0])
    return fig, grid.T  # (posture, row)


def _caller_grid(qs: np.ndarray, ax) -> np.ndarray:
    axes = [ax] * len(qs) if isinstance(ax, Axes) else list(ax)
    if len(axes) != len(qs):
        raise BodySchemaInputError(f"got {len(axes)} axes for {len(qs)} postures; give one axes or one per posture")
    return np.array(axes, dtype=object)[:, None]


def save_figure_atomic(fig: Figure, path: str | os.PathLike, **savefig_options):
    """Render into memory (``Figure.savefig`` with ``savefig_options``), then write via a temp file and rename:
    readers never see half a figure."""
    path = os.fspath(path)
    fmt = (os.path.splitext(path)[1] or ".png")[1:]
    buffer = io.BytesIO()
    fig.savefig(buffer, format=fmt, **savefig_options)
    atomic_write_bytes(path, buffer.getvalue())


def draw_arm(model: MusculoskeletalModel, qs, ax: Axes | Sequence[Axes] | None = None,
             path: str | os.PathLike | None = None, site: str = "hand", zoom: bool = True,
             view_joint: str | None = None, frame: str = "all") -> Figure:
    """Draw the arm with its muscles at postures ``qs (B, N)`` [rad] and return the figure.

    Default: a new figure with one column per posture, the whole arm on top and, if ``zoom``, one
    close-up per joint below it so the wrapping is visible. ``ax``: draw into one Axes (postures
    overlaid) or one Axes per posture instead. ``path``: also save the figure there (atomically).
    ``view_joint``: a hinge joint's name; the drawing plane is perpendicular to its axis (default: the
    first hinge's). ``frame``: ``"all"`` shows everything drawn, ``"moving"`` only the bodies the free
    joints move (with a margin), e.g. the hand of a whole-body model.
    """
    qs = _check_postures(model, qs)
    if frame not in FRAMES:
        raise BodySchemaInputError(f"frame {frame!r} is not one of {list(FRAMES)}")
    n_zoom = model.n_joints if zoom and ax is None else 0
    fig, grid = _new_grid(len(qs), n_zoom, model.n_joints) if ax is None else (None, _caller_grid(qs, ax))
    m, d = model.mj_model, mujoco.MjData(model.mj_model)  # own data: never disturbs the model's
    mujoco.mj_kinematics(m, d)
    plane = view_plane(m, d, _hinge_id(m, view_joint))  # hinge axes keep their world direction in a planar arm
    moving = _moving_bodies(m, model.joint_map.free)
    framed = []
    for i, (q, column) in enumerate(zip(qs, grid)):
        d.qpos[:] = model.joint_map.full_q(q[None])[0]  # locked and coupled joints too
        mujoco.mj_forward(m, d)
        framed.append(_moving_points(m, d, moving, model.joint_map.free, plane))
        _draw_column(column, model, d, q, site, i == 0, plane)
    for column in grid if frame == "moving" else ():
        _frame(column[0], np.concatenate(framed))
    _draw_gravity(grid[0][0], m.opt.gravity, plane)
    fig = fig or grid[0][0].figure
    _legend(fig, grid[0][0], own_figure=ax is None)
    if path is not None:
        save_figure_atomic(fig, path, bbox_inches="tight", pad_inches=0.05)
    return fig


def _draw_column(column, model: MusculoskeletalModel, d, q: np.ndarray, site: str, first: bool, plane: ViewPlane):
    """One posture (``d`` after mj_forward): the whole arm in ``column[0]``, a joint's close-up in each further Axes."""
    m = model.mj_model
    for row, a in enumerate(column):
        _draw_posture(a, model, d, site, label=first and row == 0, plane=plane)
    _style_whole(column[0], q, model.joint_names, plane)
    for j, a in enumerate(column[1:]):
        center = plane.xy(d.xanchor[model.joint_map.free[j]])
        _style_zoom(a, center, _zoom_half_width_m(m, d, plane, center), model.joint_names[j])


FRAMES = ("all", "moving")


def _hinge_id(m: mujoco.MjModel, name: str | None) -> int | None:
    """Id of the hinge joint ``name`` (None: None); one clear error for another name."""
    if name is None:
        return None
    j = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, name)
    hinges = [mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_JOINT, k) for k in range(m.njnt)
              if int(m.jnt_type[k]) == int(mujoco.mjtJoint.mjJNT_HINGE)]
    if j < 0 or name not in hinges:
        raise BodySchemaInputError(f"view joint {name!r} is not a hinge of the model; hinges: {hinges}")
    return j


def _moving_bodies(m: mujoco.MjModel, free_joints) -> list[int]:
    """Bodies at or below a free joint's body in the kinematic tree."""
    roots = {int(m.jnt_bodyid[j]) for j in free_joints}

    def moves(b: int) -> bool:
        return b in roots or (b > 0 and moves(int(m.body_parentid[b])))
    return [b for b in range(1, m.nbody) if moves(b)]


def _moving_points(m, d, moving: list[int], free_joints, plane: ViewPlane) -> np.ndarray:
    """(K, 2) drawing points [m] of the moving bodies: their origins, link ends and the free joints' anchors."""
    links = [e for e, g in zip(_link_segments(m, d, set(_wrap_geoms(m))), _link_geoms(m, _wrap_geoms(m)))
             if int(m.geom_bodyid[g]) in moving]
    points = [d.xpos[moving], d.xanchor[list(free_joints)]] + links
    return plane.xy(np.concatenate(points))


def _frame(a: Axes, xy: np.ndarray, margin: float = 0.12):
    """Limit ``a`` to the box around ``xy (K, 2)`` [m], widened by ``margin`` of its larger side."""
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    pad = margin * max(hi - lo)
    a.set_xlim(lo[0] - pad, hi[0] + pad)
    a.set_ylim(lo[1] - pad, hi[1] + pad)


def _zoom_half_width_m(m: mujoco.MjModel, d: mujoco.MjData, plane: ViewPlane, center: np.ndarray) -> float:
    """Half the side of a joint's close-up: 2.5 radii of the largest wrap centred on that joint
    (within 5 mm in the drawing), else of the largest wrap anywhere, or 0.1 m when nothing wraps."""
    wraps = sorted(_wrap_geoms(m))
    here = [m.geom_size[g, 0] for g in wraps if np.linalg.norm(plane.xy(d.geom_xpos[g]) - center) < 5e-3]
    radii = here or [m.geom_size[g, 0] for g in wraps]
    return 2.5 * max(radii) if radii else 0.1


def _style_whole(a: Axes, q: np.ndarray, joint_names: list[str], plane: ViewPlane):
    a.set_aspect("equal", adjustable="box")
    a.grid(True, lw=0.3, alpha=0.5)
    a.set_xlabel(plane.label(plane.right))
    a.set_ylabel(plane.label(plane.up))
    parts = [f"{n}={v:+.2f}" for n, v in zip(joint_names, q)]
    title = "\n".join(", ".join(parts[i:i + 2]) for i in range(0, len(parts), 2)) + " rad"  # 2 joints a line
    a.set_title(title if a.get_title() == "" else a.get_title() + "\n" + title, fontsize=9)


def _style_zoom(a: Axes, center: np.ndarray, half_m: float, joint: str):
    a.set_xlim(center[0] - half_m, center[0] + half_m)
    a.set_ylim(center[1] - half_m, center[1] + half_m)
    a.set_aspect("equal", adjustable="box")
    a.grid(True, lw=0.3, alpha=0.5)
    a.tick_params(labelsize=7)
    a.xaxis.set_major_locator(MaxNLocator(5))
    a.yaxis.set_major_locator(MaxNLocator(5))
    a.set_title(f"close-up: {joint}", fontsize=8)


def _legend(fig: Figure, first: Axes, own_figure: bool):
    handles, labels = first.get_legend_handles_labels()
    if not labels:
        return  # too many muscles to label one by one
    if own_figure:
        fig.legend(handles, labels, loc="outside lower center", ncol=min(len(labels), 3), fontsize=8, frameon=False)
    else:
        first.legend(handles, labels, fontsize=7, loc="lower left")
