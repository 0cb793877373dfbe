"""A perturbed copy of a robot: the model a researcher has is only approximately the robot (model mismatch).

``mismatched_robot(model, fraction, seed)`` scales, each by its own factor drawn uniformly in
[1 - fraction, 1 + fraction]:

* moment arms: the radius of every geom a muscle wraps over, and the position (in its body's frame) of every
  site a muscle path passes through;
* link masses: every geom with a mass;
* spring constants: k and alpha of every muscle (f_max, a motor rating, is kept).

Joint ranges, names and gravity are kept. Never imports Lightning.
"""
from __future__ import annotations

import mujoco
import numpy as np

from ..errors import BodySchemaInputError
from .mjcf import exact_xml
from .model import MusculoskeletalModel
from .spring import SpringParams


def _muscle_path_objects(model: MusculoskeletalModel) -> tuple[set, set]:
    """Names of the geoms wrapped and the sites passed by the model's muscles (not side sites)."""
    m = model.mj_model
    geoms, sites = set(), set()
    for tendon in model.muscle_ids:
        for w in range(m.tendon_adr[tendon], m.tendon_adr[tendon] + m.tendon_num[tendon]):
            kind, obj = int(m.wrap_type[w]), int(m.wrap_objid[w])
            if kind == int(mujoco.mjtWrap.mjWRAP_SITE):
                sites.add(mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_SITE, obj))
            elif kind in (int(mujoco.mjtWrap.mjWRAP_CYLINDER), int(mujoco.mjtWrap.mjWRAP_SPHERE)):
                geoms.add(mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_GEOM, obj))
    return geoms, sites


def mismatched_robot(model: MusculoskeletalModel, spring: SpringParams, fraction: float, seed: int
                     ) -> tuple[MusculoskeletalModel, SpringParams]:
    """(perturbed model, perturbed spring): see the module docstring. ``fraction`` 0 returns equal copies."""
    if not 0.0 <= fraction < 1.0:
        raise BodySchemaInputError(f"mismatch fraction {fraction!r} must lie in [0, 1) (0.1 = up to +-10 %)")
    if int(seed) != seed or seed < 0:
        raise BodySchemaInputError(f"mismatch seed {seed!r} must be an integer >= 0")
    rng = np.random.default_rng(seed)

    def factor(shape=()):
        return 1.0 + fraction * rng.uniform(-1.0, 1.0, shape)

    wrapped, passed = _muscle_path_objects(model)
    spec = mujoco.MjSpec.from_string(model.xml)
    for geom in sorted(spec.geoms, key=lambda g: g.name):  # a fixed order: same seed, same robot
        if geom.name in wrapped:
            geom.size[0] *= factor()
        if geom.mass > 0:
            geom.mass *= factor()
    for site in sorted(spec.sites, key=lambda s: s.name):
        if site.name in passed:
            site.pos = np.asarray(site.pos) * factor(3)
    n = model.n_muscles
    perturbed_spring = SpringParams(
        (np.broadcast_to(np.asarray(spring.k_n, float), (n,)) * factor(n)).tolist(),
        (np.broadcast_to(np.asarray(spring.alpha_per_m, float), (n,)) * factor(n)).tolist(),
        spring.f_max_n)
    return MusculoskeletalModel(exact_xml(spec), muscles=model.muscle_names), perturbed_spring
