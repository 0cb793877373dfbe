"""Where a robot's MJCF comes from, and how it becomes one self-contained XML text.

Sources: a packaged model name, ``myo:<name>`` (a MyoSuite model built by the optional ``myo-sim``
package), an MJCF file path (its includes and meshes load relative to the file), or MJCF text.

A checkpoint stores the robot as XML text, so that text must rebuild the same physics on a machine
that has neither ``myo-sim`` nor the mesh files: ``self_contained_xml`` gives every body its compiled
mass and inertia explicitly and then drops what only draws the model (mesh geoms, meshes, textures,
materials, skins, height fields), plus keyframes and sensors. Bodies, joints, equality couplings,
tendons with their sites and wrapping geometry, and collision primitives stay. A mesh geom that also
collides goes with the meshes, and so does every ``<contact><pair>`` naming a dropped geom (the static
equilibrium has no contact forces; the settle simulation then has no contacts on those meshes);
``<contact><exclude>`` names bodies, which all stay. Composed models whose default classes repeat a name
(MyoSuite's two-arm and two-hand bodies attach one arm twice) keep one copy of each class (the copies
differ only in the materials dropped here); two different classes under one name are refused.
"""
from __future__ import annotations

import contextlib
import os
import re
import sys
import warnings
import xml.etree.ElementTree as ET
from importlib import resources

import mujoco
import numpy as np

from ..errors import BodySchemaInputError
from .install import MYO_SIM_INSTALL, mujoco_broken_message

MYO_PREFIX = "myo:"
MYO_EXTRA_HINT = f"install it without its mujoco<4 pin, which would replace MuJoCo 4: {MYO_SIM_INSTALL}"
_VISUAL_ASSETS = ("skins", "meshes", "materials", "textures", "hfields")


def packaged_model_names() -> list[str]:
    """Names of the MJCF models shipped in ``lightning_bodyschema/assets`` (e.g. ``paper_arm``)."""
    files = resources.files("lightning_bodyschema.assets").iterdir()
    return sorted(f.name[:-4] for f in files if f.name.endswith(".xml"))


def packaged_model_xml(name: str) -> str:
    """The MJCF text of a packaged model: ``paper_arm``, ``arm3_8``, ``opensim_like_arm``, ..."""
    names = packaged_model_names()
    if name not in names:
        raise BodySchemaInputError(f"unknown packaged model {name!r}; packaged models are {names}")
    return resources.files("lightning_bodyschema.assets").joinpath(f"{name}.xml").read_text()


def _myo_sim():
    """The ``myo_sim`` module, or one clear error naming the install (or MuJoCo's repair when that broke it)."""
    try:
        import myo_sim
    except ImportError as err:
        if (err.name or "").startswith("mujoco"):
            raise BodySchemaInputError(f"MyoSuite models (myo:<name>): {mujoco_broken_message(err)}") from None
        myo_sim = None
    if myo_sim is None:  # also when sys.modules["myo_sim"] is None (how tests simulate its absence)
        raise BodySchemaInputError(f"MyoSuite models (myo:<name>) need myo-sim, which is not installed: "
                                   f"{MYO_EXTRA_HINT}")
    return myo_sim


@contextlib.contextmanager
def quiet_attach_warnings():
    """MuJoCo's "Attaching a spec with an empty prefix may prevent the model from being saved correctly", which
    myo-sim's composition of bodies triggers on every load, silenced (we save the compiled model's own XML, not the
    spec); MuJoCo's other warnings go to stderr as before."""
    previous = mujoco.get_mju_user_warning()

    def warn(message: str):
        if "empty prefix" in message:
            return
        if previous is not None:
            previous(message)
        else:
            print(f"WARNING: {message}", file=sys.stderr)

    mujoco.set_mju_user_warning(warn)
    try:
        yield
    finally:
        mujoco.set_mju_user_warning(previous)


def load_myo_spec(name: str) -> mujoco.MjSpec:
    """A MyoSuite model by ``myo_sim`` name (``myoelbow_2dof``, ``myoarm``, ``myohand``, ...)."""
    myo_sim = _myo_sim()
    try:
        with warnings.catch_warnings(), quiet_attach_warnings():  # myo-sim's composition attaches specs
            warnings.simplefilter("ignore")
            return myo_sim.load_spec(name)
    except ValueError as err:  # myo_sim's message lists the names it knows
        raise BodySchemaInputError(f"model 'myo:{name}': {str(err).strip()}") from None


def load_spec(source: str) -> mujoco.MjSpec:
    """Parse an MJCF given as a packaged model name, ``myo:<name>``, a file path, or XML text."""
    if source in packaged_model_names():
        return mujoco.MjSpec.from_string(packaged_model_xml(source))
    if source.startswith(MYO_PREFIX):
        return load_myo_spec(source[len(MYO_PREFIX):])
    if source.lstrip().startswith("<"):
        try:
            return mujoco.MjSpec.from_string(source)
        except Exception as err:  # MuJoCo raises plain ValueError with its parser message
            raise BodySchemaInputError(f"model XML does not parse: {str(err).strip()}") from None
    if not os.path.isfile(source):
        raise BodySchemaInputError(
            f"model {source!r} does not exist: it is neither a packaged model {packaged_model_names()} "
            "nor an MJCF file (give a packaged name, myo:<name> for a MyoSuite model, an MJCF path, or MJCF text)")
    try:
        return mujoco.MjSpec.from_file(source)  # includes and meshdir resolve relative to the file
    except Exception as err:
        raise BodySchemaInputError(f"model file {source!r} does not parse: {str(err).strip()}") from None


def compile_spec(spec: mujoco.MjSpec) -> mujoco.MjModel:
    try:
        with warnings.catch_warnings(), quiet_attach_warnings():  # specs composed by myo-sim: empty prefixes
            warnings.simplefilter("ignore")
            return spec.compile()
    except Exception as err:
        raise BodySchemaInputError(f"model does not compile: {str(err).strip()}") from None


def _needs_stripping(spec: mujoco.MjSpec) -> bool:
    return any(len(getattr(spec, kind)) for kind in _VISUAL_ASSETS) or len(spec.keys) or len(spec.sensors)


def self_contained_xml(spec: mujoco.MjSpec) -> str:
    """XML text of ``spec`` (actuators already removed) that needs no other file and keeps its physics.

    A model without visual assets, keyframes or sensors is written as it is (the packaged arms).
    Otherwise every body's compiled mass, centre of mass and principal inertia become explicit
    (they were computed from meshes), then mesh geoms and visual assets are deleted.
    """
    if not _needs_stripping(spec):
        compile_spec(spec)
        return spec.to_xml()
    compiled = compile_spec(spec)
    for body in spec.bodies:
        i = mujoco.mj_name2id(compiled, mujoco.mjtObj.mjOBJ_BODY, body.name)
        if i <= 0:
            continue  # the world body has no inertia
        body.explicitinertial = True
        body.mass, body.ipos = compiled.body_mass[i], compiled.body_ipos[i]
        body.iquat, body.inertia = compiled.body_iquat[i], compiled.body_inertia[i]
        body.fullinertia = np.full(6, np.nan)  # principal axes given by iquat
    _drop_mesh_geoms(spec)
    for kind in ("geoms", "sites", "tendons"):
        for element in getattr(spec, kind):
            element.material = ""
    for kind in _VISUAL_ASSETS + ("keys", "sensors"):
        for element in list(getattr(spec, kind)):
            spec.delete(element)
    spec.meshdir, spec.texturedir = "", ""
    # materials may also be named by default classes: drop every reference, then let MuJoCo re-canonicalize
    compile_spec(spec)  # to_xml writes the compiled state
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        xml = re.sub(r'\s(material|mesh|hfield|texture)="[^"]*"', "", spec.to_xml())
    xml = _dedupe_default_classes(xml)
    try:
        return mujoco.MjSpec.from_string(xml).to_xml()
    except Exception as err:
        raise BodySchemaInputError(f"model could not be made self-contained: {str(err).strip()}") from None


def _drop_mesh_geoms(spec: mujoco.MjSpec):
    """Delete mesh and height-field geoms, and the contact pairs that name one of them."""
    dropped = set()
    for geom in list(spec.geoms):
        if geom.type in (mujoco.mjtGeom.mjGEOM_MESH, mujoco.mjtGeom.mjGEOM_HFIELD):
            dropped.add(geom.name)
            spec.delete(geom)
    dropped.discard("")
    for pair in list(spec.pairs):
        if pair.geomname1 in dropped or pair.geomname2 in dropped:
            spec.delete(pair)


def _dedupe_default_classes(xml: str) -> str:
    """MJCF text with a default class written twice, identically, written once (MuJoCo reads no repeated name)."""
    names = re.findall(r'<default class="([^"]*)"', xml)
    if len(names) == len(set(names)):
        return xml
    root = ET.fromstring(xml)
    first: dict[str, bytes] = {}
    for parent in list(root.iter("default")):
        for child in list(parent.findall("default")):
            tail, child.tail = child.tail, None  # the whitespace after an element is not part of it
            name, text = child.get("class"), ET.tostring(child)
            child.tail = tail
            if name not in first:
                first[name] = text
            elif first[name] == text:
                parent.remove(child)
            else:
                raise BodySchemaInputError(f"model has two different default classes named {name!r}; "
                                           "give them different names")
    return ET.tostring(root, encoding="unicode")
