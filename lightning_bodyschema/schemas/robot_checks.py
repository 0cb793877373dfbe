"""Check 4 of a checkpoint (``loading.check_checkpoint``): the robot it carries, as data, before MuJoCo sees it.

Required entries and spring constants (``check_robot``; a recorded-data robot: names and limits), and robot XML free
of file references and of oversized allocations (``check_robot_xml``). Also the field helper every check uses
(``_entry``). Each problem is one ``BodySchemaInputError`` naming the checkpoint and the field.
"""
from __future__ import annotations

import math
import re
import sys
from dataclasses import fields
from xml.parsers import expat

from ..errors import BodySchemaInputError

ROBOT_ENTRIES = ("model_xml", "muscles", "spring")  # BodySchema(robot=...) reads exactly these
MODEL_FREE_ROBOT_ENTRIES = ("joints", "q_range", "muscles", "l_range", "f_range", "spring")  # recorded data
# highest spring constants a checkpoint may carry (the paper's: 1000 N, 20 1/m, 150 N; MyoSuite's strongest muscle
# ~2200 N): far beyond any body, and low enough that the physics QP stays well conditioned (f_max_n = 1e300 made
# one feasibility check take a minute)
SPRING_LIMITS = {"k_n": 1e9, "alpha_per_m": 1e6, "f_max_n": 1e6}

# robot XML limits, checked on the text before MuJoCo parses it
MAX_XML_CHARS = 32_000_000
MAX_XML_ALLOCATION = 10_000_000  # texels, height-field samples, composite/flexcomp/replicate elements
MAX_SIZE_ATTRIBUTE = 1_000_000  # integer entries of <size> (njmax, nstack, nuserdata, nuser_*, ...)
MAX_SIZE_MEMORY_BYTES = 1 << 30  # <size memory="..."/>: MuJoCo's arena, allocated for every MjData
_XML_COUNTS = {"texture": ("width", "height"), "hfield": ("nrow", "ncol"), "composite": ("count",),
               "flexcomp": ("count",), "replicate": ("count",)}


# ---------------------------------------------------------------------------- field helpers
def _entry(mapping, key: str, kind, where: str):
    """``mapping[key]``, refused when missing or not a ``kind``."""
    if key not in mapping:
        raise BodySchemaInputError(f"{where}: the entry {key!r} is missing")
    value = mapping[key]
    if not isinstance(value, kind) or isinstance(value, bool) and kind is not bool:
        raise BodySchemaInputError(f"{where}: {key!r} is a {type(value).__name__}; expected {_kind_name(kind)}")
    return value


def _kind_name(kind) -> str:
    kinds = kind if isinstance(kind, tuple) else (kind,)
    return " or ".join(k.__name__ for k in kinds)


# ---------------------------------------------------------------------------- 4. the robot
def check_robot_xml(xml: str, where: str = "robot XML") -> None:
    """Refuse robot XML that is not self-contained or asks MuJoCo for an oversized allocation, before MuJoCo sees it.

    A checkpoint's robot must rebuild from its text alone: no ``<include>``, no ``file=`` (mesh, texture, hfield,
    skin, model, ...), and text, not a model name or path. The text is read by expat with no DTD allowed (so no
    entity is ever expanded or fetched); texture texels, height-field samples, composite/flexcomp/replicate counts
    and ``<size>`` entries are bounded (``MAX_XML_ALLOCATION``, ``MAX_SIZE_ATTRIBUTE``, ``MAX_SIZE_MEMORY_BYTES``).
    A model with meshes must carry them inline (``vertex=``/``face=``).
    """
    if not isinstance(xml, str):
        raise BodySchemaInputError(f"{where} is a {type(xml).__name__}; expected MJCF text")
    if len(xml) > MAX_XML_CHARS:
        raise BodySchemaInputError(f"{where} has {len(xml)} characters; at most {MAX_XML_CHARS} are allowed")
    if not xml.lstrip().startswith("<"):
        raise BodySchemaInputError(f"{where} is {xml[:60]!r}, not MJCF text (a checkpoint carries the XML itself, "
                                   "never a model name or path)")

    def refuse(message):
        raise BodySchemaInputError(f"{where}: {message}; a checkpoint's XML must be self-contained")

    def on_doctype(*_):
        refuse("it declares a DOCTYPE (DTDs and entities are not allowed)")

    def on_element(tag, attributes):
        if tag == "include":
            refuse(f"<include file={attributes.get('file')!r}> references a file")
        if "file" in attributes:
            refuse(f"<{tag} file={attributes['file']!r}> references a file")
        _check_xml_sizes(tag, attributes, where)

    parser = expat.ParserCreate()
    parser.SetParamEntityParsing(expat.XML_PARAM_ENTITY_PARSING_NEVER)
    parser.StartDoctypeDeclHandler = on_doctype
    parser.EntityDeclHandler = on_doctype
    parser.ExternalEntityRefHandler = on_doctype
    parser.StartElementHandler = on_element
    try:
        parser.Parse(xml, True)
    except expat.ExpatError as err:
        raise BodySchemaInputError(f"{where} does not parse as XML: {err}") from None


def _check_xml_sizes(tag: str, attributes: dict, where: str):
    if tag in _XML_COUNTS:
        numbers = [n for a in _XML_COUNTS[tag] for n in _xml_ints(attributes.get(a, ""), f"<{tag} {a}>", where)]
        if math.prod(numbers or [0]) > MAX_XML_ALLOCATION:
            shown = " ".join(f'{a}="{attributes.get(a)}"' for a in _XML_COUNTS[tag] if a in attributes)
            raise BodySchemaInputError(f"{where}: <{tag} {shown}> asks for {math.prod(numbers)} elements; at most "
                                       f"{MAX_XML_ALLOCATION} are allowed")
    if tag != "size":
        return
    for name, text in attributes.items():
        if name == "memory":
            _check_memory(text, where)
        elif name.startswith("n"):
            values = _xml_ints(text, f"<size {name}>", where)
            if any(v > MAX_SIZE_ATTRIBUTE for v in values):
                raise BodySchemaInputError(f"{where}: <size {name}=\"{text}\"> exceeds {MAX_SIZE_ATTRIBUTE}")


def _xml_ints(text: str, what: str, where: str) -> list[int]:
    try:
        return [int(float(token)) for token in text.split()]
    except (ValueError, OverflowError):
        raise BodySchemaInputError(f"{where}: {what}=\"{text[:60]}\" is not a list of integers") from None


def _check_memory(text: str, where: str):
    match = re.fullmatch(r"\s*(\d+)\s*([KMGTPE]?)\s*", text)
    size = int(match.group(1)) * 1024 ** " KMGTPE".index(match.group(2) or " ") if match else None
    if size is None or size > MAX_SIZE_MEMORY_BYTES:
        raise BodySchemaInputError(f"{where}: <size memory=\"{text[:40]}\"> must be a byte count of at most "
                                   f"{MAX_SIZE_MEMORY_BYTES} (1G)")


def check_robot(robot, where: str) -> None:
    """The robot a checkpoint carries, as data: entries, spring, self-contained XML (``check_robot_xml``). MuJoCo
    compiles it afterwards, inside the meta-device skeleton (``check_weights``), where its hash is compared."""
    if not isinstance(robot, dict):
        raise BodySchemaInputError(f"{where}: hyper_parameters.robot is a {type(robot).__name__}; expected a dict "
                                   f"with {list(ROBOT_ENTRIES)}")
    if "model_xml" not in robot and "joints" in robot:  # trained on recorded data: names and limits, no model
        return _check_model_free_robot(robot, where)
    unknown = [k for k in robot if k not in ROBOT_ENTRIES]
    if unknown:
        raise BodySchemaInputError(f"{where}: robot has unknown entry {unknown[0]!r}; allowed: {list(ROBOT_ENTRIES)}")
    xml = _entry(robot, "model_xml", str, f"{where}: robot")
    muscles = _names(robot, "muscles", where)
    _check_spring(_entry(robot, "spring", dict, f"{where}: robot"), len(muscles), where)
    check_robot_xml(xml, f"{where}: robot.model_xml")


def _names(robot: dict, key: str, where: str) -> list:
    names = _entry(robot, key, list, f"{where}: robot")
    if not names or len(names) > MAX_SIZE_ATTRIBUTE or not all(isinstance(m, str) for m in names):
        raise BodySchemaInputError(f"{where}: robot.{key} must be a non-empty list of names")
    if len(set(names)) != len(names):
        raise BodySchemaInputError(f"{where}: robot.{key} names one twice: {names}")
    return names


def _check_model_free_robot(robot: dict, where: str) -> None:
    """A recorded-data robot (``sim.robot.ModelFreeRobot``), as data: names, [lo, hi] limits, spring. Its hash
    is compared with the recorded one where the skeleton is built (``check_weights``), as a model's is."""
    unknown = [k for k in robot if k not in MODEL_FREE_ROBOT_ENTRIES]
    if unknown:
        raise BodySchemaInputError(f"{where}: robot has unknown entry {unknown[0]!r}; allowed: "
                                   f"{list(MODEL_FREE_ROBOT_ENTRIES)}")
    joints, muscles = _names(robot, "joints", where), _names(robot, "muscles", where)
    for key, n, finite in (("q_range", len(joints), True), ("l_range", len(muscles), False),
                           ("f_range", len(muscles), False)):
        limits = _entry(robot, key, list, f"{where}: robot")
        good = len(limits) == n and all(
            isinstance(pair, list) and len(pair) == 2 and all(_real(v, finite) for v in pair) and pair[0] < pair[1]
            for pair in limits)
        if not good:
            raise BodySchemaInputError(f"{where}: robot.{key} = {str(limits)[:80]}; expected {n} pairs [lo, hi] of "
                                       f"{'finite ' if finite else ''}numbers with lo < hi")
    _check_spring(_entry(robot, "spring", dict, f"{where}: robot"), len(muscles), where)


def _real(value, finite: bool) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and not math.isnan(value) and (
        math.isfinite(value) or not finite)


def _check_spring(spring: dict, n_muscles: int, where: str):
    from ..sim import SpringParams

    allowed = [f.name for f in fields(SpringParams)]
    for name in spring:
        if name not in allowed:
            raise BodySchemaInputError(f"{where}: robot.spring has unknown entry {name!r}; allowed: {allowed}")
    for name in allowed:
        limit = SPRING_LIMITS.get(name, sys.float_info.max)
        value = _entry(spring, name, (int, float, list), f"{where}: robot.spring")
        values = value if isinstance(value, list) else [value]
        good = (len(values) in (1, n_muscles) if isinstance(value, list) else True) and all(
            isinstance(v, (int, float)) and not isinstance(v, bool) and 0 < v <= limit for v in values)
        if not good:
            raise BodySchemaInputError(f"{where}: robot.spring.{name} = {str(value)[:80]}; expected a number in "
                                       f"(0, {limit:g}], or a list of {n_muscles} (one per muscle)")
