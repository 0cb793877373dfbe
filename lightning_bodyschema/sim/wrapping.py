"""Which wrapping state each muscle's path is in, posture by posture: the pieces inside which MuJoCo's length is smooth.

A spatial tendon's path runs from site to site and, at each wrapping geom (sphere or cylinder) between two sites,
either goes straight (the geom is not wrapped) or wraps around it on one of two sides (``mju_wrap``: the short way
round, or the long way where a side site lies behind the geom; ``wrap_margins`` below). Inside one combination of these
choices the length is a smooth function of the posture; between them it may jump (a side site forcing a wrap that the
straight segment did not need: myoArm's 17-28 mm jumps) or bend (a wrap taking over smoothly: the length and its
first derivative continue, its second does not).

``wrap_states(model, q)`` reads MuJoCo's own choice (``mjData.wrap_obj``, ``ten_wrapadr``, ``wrap_xpos`` after
``mj_tendon``) and codes it per muscle as ``sum_j s_j 3**j`` over the muscle's wrapping geoms ``j`` in path order
(``wrap_geoms``), ``s_j`` 0: not wrapped, 1: wrapped with the incoming tangent on the positive side, 2: on the
negative side. The side is the sign, in the 2D frame ``mju_wrap`` wraps in, of ``p0 x t1`` (``p0`` the site before
the geom, ``t1`` the first tangent point, both relative to the geom's centre): about the cylinder's axis, or about
``p0 x p1`` for a sphere (``p1`` the site after it). A sphere's frame turns with ``p0`` and ``p1``, so the side
there is relative to them: where ``p0``, the centre and ``p1`` line up the path swaps sides with a kink in its length
and no change of code (a set of postures of dimension two lower than a switch of the codes).

``wrap_margins(model, q)`` gives the smooth signed quantities MuJoCo's choice is made of, per muscle and wrapping
geom, in metres, in the geom's 2D wrapping frame (``d0``, ``d1`` the sites before and after, ``r`` the radius,
``turn`` = ``d0 x d1 / |d1 - d0|`` the centre's signed distance from the line through them, ``u`` the unit direction
opposite the side site), each free of the kinks of a minimum or a clamp (MARGINS, in order):

* ``clear0``, ``clear1`` = ``|d0| - r``, ``|d1| - r``: each site outside the circle (else nothing wraps);
* ``upper``, ``lower`` = ``r - turn``, ``r + turn``: the line through the sites cuts the circle where both are >= 0;
* ``foot0``, ``foot1`` = ``-(d1 - d0) . d0 / |d1 - d0|``, ``(d1 - d0) . d1 / |d1 - d0|``: the foot of the centre on
  that line lies between the sites where both are > 0 (so the segment itself cuts the circle);
* ``before``, ``after`` = ``r (d0 / |d0|) x u``, ``r u x (d1 / |d1|)`` (NaN without a side site): both of the sign of
  ``turn`` where the side site lies behind the geom, opposite the short wedge between the two sites;
* ``inside`` = ``r - |s|`` (``s`` the side site in the geom's frame, 3D; NaN without one): MuJoCo's inside wrap.

MuJoCo 4.0 (measured against its wrap points on myoArm, 2000 postures: every wrapping geom agrees) wraps where both
sites are outside and the segment cuts the circle or the side site is behind (inside wrap: where the segment does
not cut it), the long way round (side ``3 - short``) where the side site is behind, else the short way, side 1 where
``turn > 0`` (``states_from_margins``). A state switches only where one margin crosses zero, so the switch is where
a smooth function crosses zero, and ``|m| / |grad m|`` estimates how far it is.

numpy and MuJoCo only; one posture per MuJoCo call, the labelling batched over a chunk of postures.
"""
from __future__ import annotations

import mujoco
import numpy as np

from ..errors import BodySchemaInputError

CHUNK = 4096  # postures whose wrap points are held at once (memory: CHUNK x muscles x points x 3 floats)
_GEOM_WRAPS = (int(mujoco.mjtWrap.mjWRAP_SPHERE), int(mujoco.mjtWrap.mjWRAP_CYLINDER))
_SPHERE = int(mujoco.mjtWrap.mjWRAP_SPHERE)
MARGINS = ("clear0", "clear1", "upper", "lower", "foot0", "foot1", "before", "after", "inside")  # last axis


def wrap_geoms(model) -> list[list[tuple[int, int, bool]]]:
    """Per muscle, its wrapping geoms in path order: ``(geom id, points before it when nothing wraps, is_sphere)``.
    Every site and pulley of a path writes one point to ``wrap_xpos``, every wrapped geom two."""
    m, out = model.mj_model, []
    for tendon in model.muscle_ids:
        adr, num, points, geoms = m.tendon_adr[tendon], m.tendon_num[tendon], 0, []
        for k in range(adr, adr + num):
            kind = int(m.wrap_type[k])
            if kind in _GEOM_WRAPS:
                geoms.append((int(m.wrap_objid[k]), points, kind == _SPHERE))
            else:
                points += 1
        out.append(geoms)
    return out


def wrap_states(model, q) -> np.ndarray:
    """``(B, M)`` int64: each muscle's wrapping state at postures ``q (B, N)`` [rad] (module docstring's code; 0 for
    a muscle with no wrapping geom). ``model``: a ``sim.MusculoskeletalModel`` with its MJCF; ``q`` in its range
    is not required (MuJoCo wraps any posture)."""
    if not getattr(model, "has_physics", True):
        raise BodySchemaInputError("wrap_states needs the robot's MJCF (recorded data has no wrapping geoms)")
    q = model.check_q(q)
    full, geoms = model.joint_map.full_q(q), wrap_geoms(model)
    width = 1 + max((len(g) for g in geoms), default=0)
    slots = np.array([(m, j, g, before, sphere) for m, muscle in enumerate(geoms)
                      for j, (g, before, sphere) in enumerate(muscle)], np.int64).reshape(-1, 5)
    out = np.zeros((len(q), len(geoms)), np.int64)
    if not len(slots):
        return out
    span = max(before for muscle in geoms for _, before, _ in muscle) + 2 * width + 2  # a path's points, at most
    for start in range(0, len(q), CHUNK):
        rows = slice(start, start + CHUNK)
        points, centre, frame = _wrap_points(model, full[rows], slots, span)
        codes = _slot_codes(points, centre, frame, slots)
        np.add.at(out[rows].T, slots[:, 0], (codes * 3 ** slots[:, 1]).T)  # in place: out[rows] is a view
    return out


def _wrap_points(model, full: np.ndarray, slots: np.ndarray, span: int):
    """MuJoCo's path points of each slot's muscle ``(B, S, span)`` (object id, point 3), and each slot's geom centre
    ``(B, S, 3)`` and frame ``(B, S, 3, 3)`` at postures ``full (B, nq)``."""
    m, d = model.mj_model, model._data
    tendons, geom = np.asarray(model.muscle_ids)[slots[:, 0]], slots[:, 2]
    n_points = 2 * m.nwrap
    obj, xpos = np.empty((len(full), len(slots), span), np.int64), np.empty((len(full), len(slots), span, 3))
    centre, frame = np.empty((len(full), len(slots), 3)), np.empty((len(full), len(slots), 3, 3))
    for b in range(len(full)):  # MuJoCo evaluates one posture per call
        d.qpos[:] = full[b]
        mujoco.mj_kinematics(m, d)
        mujoco.mj_tendon(m, d)
        index = np.minimum(d.ten_wrapadr[tendons][:, None] + np.arange(span), n_points - 1)
        obj[b], xpos[b] = d.wrap_obj.reshape(-1)[index], d.wrap_xpos.reshape(-1, 3)[index]
        centre[b], frame[b] = d.geom_xpos[geom], d.geom_xmat[geom].reshape(-1, 3, 3)
    return (obj, xpos), centre, frame


def _slot_codes(points, centre: np.ndarray, frame: np.ndarray, slots: np.ndarray) -> np.ndarray:
    """``(B, S)`` codes 0 / 1 / 2 of each slot (module docstring), its geom's place in the path found after the
    muscle's earlier geoms (each wrapped one adds two points)."""
    (obj, xpos), (n, n_slots) = points, centre.shape[:2]
    codes, shift = np.zeros((n, n_slots), np.int64), np.zeros((n, n_slots), np.int64)
    rows = np.arange(n)[:, None]
    for j in range(int(slots[:, 1].max()) + 1):  # a muscle's j-th geom after its first j - 1 are placed
        at = slots[:, 1] == j
        where = slots[at, 3][None, :] + shift[:, at]  # (B, S_j): the geom's first tangent point
        wrapped = obj[rows, np.flatnonzero(at)[None, :], where] == slots[at, 2][None, :]
        local = lambda k: np.einsum("bsji,bsj->bsi", frame[:, at], xpos[rows, np.flatnonzero(at)[None, :], k]  # noqa: E731
                                    - centre[:, at])
        p0, t1, p1 = local(where - 1), local(where), local(where + 2)
        normal = np.where(slots[at, 4][None, :, None] == 1, np.cross(p0, p1), np.array([0.0, 0.0, 1.0]))
        side = np.einsum("bsi,bsi->bs", normal, np.cross(p0, t1))
        codes[:, at] = np.where(wrapped, np.where(side > 0, 1, 2), 0)
        later = (slots[:, 0][None, :] == slots[at, 0][:, None]) & (slots[:, 1] > j)[None, :]  # (S_j, S)
        shift += 2 * wrapped.astype(np.int64) @ later.astype(np.int64)
    return codes


def wrap_margins(model, q) -> np.ndarray:
    """``(B, M, J, 9)`` [m]: each muscle's margins (``MARGINS``, module docstring) at each of its wrapping geoms
    ``J`` in path order (``wrap_geoms``; NaN past a muscle's last geom) at postures ``q (B, N)`` [rad]."""
    if not getattr(model, "has_physics", True):
        raise BodySchemaInputError("wrap_margins needs the robot's MJCF (recorded data has no wrapping geoms)")
    q = model.check_q(q)
    full, slots = model.joint_map.full_q(q), _margin_slots(model)
    width = max((j + 1 for _, j, *_ in slots), default=0)
    out = np.full((len(q), model.n_muscles, width, len(MARGINS)), np.nan)
    if not slots:
        return out
    table = np.array([row[:6] for row in slots], np.int64)
    radius, sphere = np.array([row[6] for row in slots]), np.array([row[7] for row in slots])
    for start in range(0, len(q), CHUNK):
        rows = slice(start, start + CHUNK)
        ends, side = _local_points(model, full[rows], table, sphere)
        out[rows, table[:, 0], table[:, 1]] = _margins(ends, side, radius, table[:, 5] >= 0)
    return out


def states_from_margins(margins: np.ndarray) -> np.ndarray:
    """``(B, M)`` int64 codes of ``wrap_states`` from margins ``(B, M, J, 9)`` (``wrap_margins``, or a regression
    of them): the module docstring's rule, per geom."""
    return (_slot_states(margins) * 3 ** np.arange(margins.shape[2])).sum(-1)


def _slot_states(margins: np.ndarray) -> np.ndarray:
    """``(..., J)`` codes 0 / 1 / 2 per wrapping geom from margins ``(..., J, 9)`` (NaN geoms: 0)."""
    clear0, clear1, upper, lower, foot0, foot1, before, after, inside = np.moveaxis(margins, -1, 0)
    turn = 0.5 * (lower - upper)
    with np.errstate(invalid="ignore"):  # NaN compares False: no side site, or no geom
        cuts = (upper >= 0) & (lower >= 0) & (foot0 > 0) & (foot1 > 0)
        within = inside > 0
        behind = ~within & np.where(turn > 0, np.minimum(before, after) > 0, np.maximum(before, after) < 0)
        wrapped = (clear0 > 0) & (clear1 > 0) & np.where(within, ~cuts, cuts | behind)
        short = np.where(turn > 0, 1, 2)
    return np.where(wrapped, np.where(behind, 3 - short, short), 0)


def _margin_slots(model) -> list[tuple]:
    """Per wrapping geom of each muscle: ``(muscle, j, geom, site before, site after, side site or -1, radius,
    is_sphere)``; MuJoCo places every wrapping geom between two sites."""
    m, out = model.mj_model, []
    for i, tendon in enumerate(model.muscle_ids):
        adr, num = m.tendon_adr[tendon], m.tendon_num[tendon]
        kinds = [int(m.wrap_type[k]) for k in range(adr, adr + num)]
        geoms = [k for k, kind in zip(range(adr, adr + num), kinds) if kind in _GEOM_WRAPS]
        for j, k in enumerate(geoms):
            g = int(m.wrap_objid[k])
            out.append((i, j, g, int(m.wrap_objid[k - 1]), int(m.wrap_objid[k + 1]), int(round(m.wrap_prm[k])),
                        float(m.geom_size[g][0]), int(m.wrap_type[k]) == _SPHERE))
    return out


def _local_points(model, full: np.ndarray, table: np.ndarray, sphere: np.ndarray):
    """Each slot's sites before and after in its 2D wrapping frame ``(B, S, 2, 2)`` and its side site in the geom's
    3D frame ``(B, S, 3)``: the 2D projection, then the 3D distance from the centre (zero without a side site)."""
    m, d = model.mj_model, model._data
    geom, before, after, sided = table[:, 2], table[:, 3], table[:, 4], table[:, 5] >= 0
    side_site = np.where(sided, table[:, 5], 0)
    local = np.empty((len(full), len(table), 3, 3))  # site before, site after, side site: in the geom's frame
    for b in range(len(full)):  # MuJoCo evaluates one posture per call
        d.qpos[:] = full[b]
        mujoco.mj_kinematics(m, d)
        points = np.stack([d.site_xpos[before], d.site_xpos[after], d.site_xpos[side_site]], 1)
        local[b] = np.einsum("sji,skj->ski", d.geom_xmat[geom].reshape(-1, 3, 3), points - d.geom_xpos[geom][:, None])
    p0, p1, s = local[:, :, 0], local[:, :, 1], local[:, :, 2]
    axis0, axis1 = np.broadcast_to(np.eye(3)[0], p0.shape), np.broadcast_to(np.eye(3)[1], p0.shape)
    axis0 = np.where(sphere[None, :, None], p0 / np.linalg.norm(p0, axis=-1, keepdims=True), axis0)
    normal = np.cross(p0, p1)  # a sphere wraps in the plane of the centre and both sites (mju_wrap)
    normal /= np.maximum(np.linalg.norm(normal, axis=-1, keepdims=True), 1e-300)
    axis1 = np.where(sphere[None, :, None], np.cross(normal, axis0), axis1)
    project = lambda v: np.stack([(v * axis0).sum(-1), (v * axis1).sum(-1)], -1)  # noqa: E731
    ends = np.stack([project(p0), project(p1)], 2)
    side = np.concatenate([project(s), np.linalg.norm(s, axis=-1, keepdims=True)], -1)
    return ends, np.where(sided[None, :, None], side, 0.0)


def _margins(ends: np.ndarray, side: np.ndarray, radius: np.ndarray, sided: np.ndarray) -> np.ndarray:
    """``(B, S, 9)`` margins (``MARGINS``) from ``_local_points``' 2D sites and side sites; ``radius``, ``sided``
    per slot ``(S,)``."""
    d0, d1, r = ends[:, :, 0], ends[:, :, 1], radius[None, :]
    length = np.maximum(np.linalg.norm(d1 - d0, axis=-1), 1e-300)
    along = (d1 - d0) / length[..., None]
    unit = lambda v: v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-300)  # noqa: E731
    away = -unit(side[..., :2])
    turn = _cross2(d0, d1) / length
    present = lambda v: np.where(sided[None, :], v, np.nan)  # noqa: E731
    return np.stack([np.linalg.norm(d0, axis=-1) - r, np.linalg.norm(d1, axis=-1) - r, r - turn, r + turn,
                     -(along * d0).sum(-1), (along * d1).sum(-1), present(r * _cross2(unit(d0), away)),
                     present(r * _cross2(away, unit(d1))), present(r - side[..., 2])], -1)


def _cross2(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]
