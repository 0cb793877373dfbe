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
import ctypes
import functools
import glob
import os
import re
import warnings
import xml.etree.ElementTree as ET
from importlib import resources

import mujoco
import numpy as np

from ..errors import BodySchemaInputError
from ..notes import note
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
    spec); MuJoCo's other warnings become notes (``notes.note``: stderr, or a tool's log when its run is refused)."""
    previous = mujoco.get_mju_user_warning()

    def warn(message: str):
        if "empty prefix" in message:
            return
        if previous is not None:
            previous(message)
        else:
            note(f"MuJoCo warning: {message.strip()}")

    mujoco.set_mju_user_warning(warn)
    try:
        yield
    finally:
        mujoco.set_mju_user_warning(previous)


_FULL_DIGITS = 17  # a double printed with 17 significant digits reads back as the same double
# a number in an attribute value (not a digit inside a name such as "r_0.5")
_LONG_NUMBER = re.compile(r"(?<![\w.])[-+]?\d*\.?\d+(?:[eE][-+]?\d+)?(?![\w.])")


@functools.lru_cache(maxsize=1)
def _mujoco_precision_hooks():
    """MuJoCo's exported ``_mjPRIVATE__get/set_xml_precision`` (the XML writer's significant digits, 6 by default,
    thread-local), or None where this MuJoCo build lacks them or they have another signature (older builds took a
    printf format): the getter must answer a digit count before the setter is trusted."""
    folder = os.path.dirname(mujoco.__file__)
    for path in sorted(glob.glob(os.path.join(folder, "*mujoco*.so*")) + glob.glob(os.path.join(folder, "*mujoco*.dylib"))
                       + glob.glob(os.path.join(folder, "mujoco*.dll"))):
        try:
            lib = ctypes.CDLL(path)
            get, put = lib._mjPRIVATE__get_xml_precision, lib._mjPRIVATE__set_xml_precision
        except (OSError, AttributeError):
            continue
        get.restype, get.argtypes, put.restype, put.argtypes = ctypes.c_int, [], None, [ctypes.c_int]
        return (get, put) if 1 <= get() <= 30 else None
    return None


@contextlib.contextmanager
def full_precision_xml():
    """``MjSpec.to_xml`` writes every number so that it reads back as the same double (17 significant digits)
    inside this block; outside it MuJoCo keeps 6, which moves a MyoSuite body's compiled masses and frames by up
    to 5e-6 relative. Yields False (and warns) where MuJoCo offers no way to raise the precision."""
    hooks = _mujoco_precision_hooks()
    if hooks is None:
        warnings.warn("this MuJoCo build cannot write XML at full precision: the stored model keeps 6 significant "
                      "digits of its compiled numbers", RuntimeWarning, stacklevel=3)
        yield False
        return
    get, put = hooks
    previous = get()
    put(_FULL_DIGITS)
    try:
        yield True
    finally:
        put(previous)


def _shortest_number(text: str, single: bool) -> str:
    """The shortest text that reads back as the number ``text`` (a double; a float where ``single``)."""
    digits = len(re.sub(r"[eE].*|[^0-9]", "", text).lstrip("0"))
    if digits < 16 or not re.search(r"[.eE]", text):  # short already, or an integer
        return text
    value = float(text)
    if single and float(np.float32(value)) == value:
        return str(np.float32(value))
    return repr(value)


def _shortest_numbers(xml: str) -> str:
    """Every number printed at full precision rewritten as the shortest text that reads back as the same value:
    0.10000000000000001 becomes 0.1 again, so a hand-written model keeps its text. MuJoCo stores colours
    (``rgba``) and everything under ``<visual>`` as floats: 0.699999988079071 becomes 0.7."""
    def numbers(text: str, single: bool) -> str:
        return _LONG_NUMBER.sub(lambda m: _shortest_number(m.group(0), single), text)

    def attribute(match: re.Match) -> str:
        return f'{match.group(1)}="{numbers(match.group(2), match.group(1) == "rgba")}"'

    parts = re.split(r"(<visual>.*?</visual>)", xml, maxsplit=1, flags=re.S)
    return "".join(numbers(part, True) if part.startswith("<visual>")
                   else re.sub(r'(?<=\s)([\w:-]+)="([^"]*)"', attribute, part) for part in parts)


def exact_xml(spec: mujoco.MjSpec) -> str:
    """``spec.to_xml()`` with every number exact (see ``full_precision_xml``) and as short as it can be."""
    with full_precision_xml():
        return _shortest_numbers(spec.to_xml())


def stored_xml(spec: mujoco.MjSpec) -> str:
    """The XML text that stores ``spec`` (compiled): MuJoCo's own 6-digit text where it compiles to the model the
    exact text compiles to (``same_compiled_model``), else the exact text. The 6-digit text is what every stored
    body was before, so a body that rounding never moved (a packaged arm, a body read back from a checkpoint)
    keeps its text and its hash."""
    exact, rounded = exact_xml(spec), spec.to_xml()
    if rounded == exact:
        return exact
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        same = same_compiled_model(mujoco.MjModel.from_xml_string(exact), mujoco.MjModel.from_xml_string(rounded))
    return rounded if same else exact


SAME_MODEL_RTOL = 1e-15  # a few units in the last place of a double: what recompiling a normalized quaternion moves


def same_compiled_model(a: mujoco.MjModel, b: mujoco.MjModel, rtol: float = SAME_MODEL_RTOL) -> bool:
    """Every numeric array of two compiled models equal within ``rtol`` of its row's magnitude (integers and the
    options exactly). A spring's rest length counts only where its stiffness is non-zero: it acts nowhere else."""
    arrays = [n for n in dir(a) if not n.startswith("_") and isinstance(getattr(a, n), np.ndarray)]
    if any(np.shape(getattr(a, n)) != np.shape(getattr(b, n)) for n in arrays):
        return False
    idle = {"tendon_lengthspring": (a.tendon_stiffness == 0) & (b.tendon_stiffness == 0)}
    for name in arrays:
        x, y = np.array(getattr(a, name)), np.array(getattr(b, name))
        if name in idle:
            x[idle[name]], y[idle[name]] = 0, 0
        if not _rows_agree(x, y, rtol):
            return False
    options = [n for n in dir(a.opt) if not n.startswith("_")]
    return all(np.array_equal(getattr(a.opt, n), getattr(b.opt, n)) for n in options
               if isinstance(getattr(a.opt, n), (int, float, np.ndarray)))


def _rows_agree(x: np.ndarray, y: np.ndarray, rtol: float) -> bool:
    """Floats: each element within ``rtol`` of the largest magnitude in its row (last axis), NaN where the other is
    NaN, an infinite bound where the other's is; anything else exactly equal."""
    if x.dtype.kind != "f" or x.size == 0:
        return np.array_equal(x, y)
    if not np.array_equal(np.isnan(x), np.isnan(y)):
        return False
    x, y = np.nan_to_num(x), np.nan_to_num(y)
    scale = np.maximum(np.abs(x), np.abs(y)).max(axis=-1, keepdims=True) if x.ndim else np.maximum(abs(x), abs(y))
    return bool(np.all(np.abs(x - y) <= rtol * scale))


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
        return stored_xml(spec)
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
        xml = re.sub(r'\s(material|mesh|hfield|texture)="[^"]*"', "", exact_xml(spec))
    xml = _dedupe_default_classes(xml)
    try:
        return stored_xml(mujoco.MjSpec.from_string(xml))
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
