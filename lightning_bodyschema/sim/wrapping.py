"""Which wrapping state each muscle's path is in, posture by posture: the pieces inside which MuJoCo's length is smooth.

A spatial tendon's path runs from site to site and, at each wrapping geom (sphere or cylinder) between two sites,
either goes straight (the geom is not wrapped) or wraps around it on one of two sides (``mju_wrap``: of the two
tangent solutions, the one nearer the side site, or the shorter without one). Inside one combination of these
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

numpy and MuJoCo only; one posture per MuJoCo call, the labelling batched over a chunk of postures.
"""
from __future__ import annotations

import mujoco
import numpy as np

from ..errors import BodySchemaInputError

CHUNK = 4096  # postures whose wrap points are held at once (memory: CHUNK x muscles x points x 3 floats)
_GEOM_WRAPS = (int(mujoco.mjtWrap.mjWRAP_SPHERE), int(mujoco.mjtWrap.mjWRAP_CYLINDER))
_SPHERE = int(mujoco.mjtWrap.mjWRAP_SPHERE)


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
