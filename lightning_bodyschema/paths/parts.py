"""A muscle's path topology and its numbers, read from a compiled MjModel.

A spatial tendon runs from site to site; between two sites it may wrap a sphere or a cylinder, with an optional side
site choosing the side. Its *numbers* are what a CAD model gives only approximately: each site's position in its body
(3), each wrapping geom's position in its body (3) and radius (1), each side site's position in its body (3); the
geoms' orientations (a cylinder's axis) and which body each point rides are topology, kept from the MJCF.
"""
from __future__ import annotations

import mujoco
import numpy as np

from ..errors import BodySchemaInputError

KINDS = ("site", "geom", "radius", "side")
_SITE, _SPHERE, _CYLINDER = (int(mujoco.mjtWrap.mjWRAP_SITE), int(mujoco.mjtWrap.mjWRAP_SPHERE),
                             int(mujoco.mjtWrap.mjWRAP_CYLINDER))


def path_parts(m: mujoco.MjModel, tendon: int) -> list[tuple]:
    """The tendon's path in order: ``("site", id)`` or ``("geom", id, side site id or -1)``."""
    parts = []
    for k in range(m.tendon_adr[tendon], m.tendon_adr[tendon] + m.tendon_num[tendon]):
        kind, obj = int(m.wrap_type[k]), int(m.wrap_objid[k])
        if kind == _SITE:
            parts.append(("site", obj))
        elif kind in (_SPHERE, _CYLINDER):
            parts.append(("geom", obj, int(round(m.wrap_prm[k]))))
        else:
            raise BodySchemaInputError(f"tendon {mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_TENDON, tendon)!r} has a "
                                       f"wrap of type {kind}: only sites, spheres and cylinders are modelled")
    return parts


def numbers(m: mujoco.MjModel, parts: list[tuple]) -> list[tuple[str, int, int]]:
    """The path's numbers ``(kind, part, component)``: each site's 3, each geom's 3 and radius, each side site's 3
    (part: the index in ``parts``; a side site's is its geom's)."""
    out = []
    for i, part in enumerate(parts):
        if part[0] == "site":
            out += [("site", i, c) for c in range(3)]
        else:
            out += [("geom", i, c) for c in range(3)] + [("radius", i, 0)]
            out += [("side", i, c) for c in range(3)] if part[2] >= 0 else []
    return out


def true_values(m: mujoco.MjModel, parts, table) -> np.ndarray:
    """The MJCF's value of each number of ``table`` [m]."""
    def value(kind, i, c):
        part = parts[i]
        return {"site": lambda: m.site_pos[part[1], c], "geom": lambda: m.geom_pos[part[1], c],
                "radius": lambda: m.geom_size[part[1], 0], "side": lambda: m.site_pos[part[2], c]}[kind]()
    return np.array([value(*row) for row in table], float)
