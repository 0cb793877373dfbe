"""Load a trained schema from its ``.ckpt`` alone: the checkpoint carries the robot and the normalizer.

Checkpoints are untrusted input: they travel between labs and are loaded inside controllers. One loader reads
them for every entry point (``load_schema``, ``load_datamodule``, ``BodySchema.load_from_checkpoint``, the tools,
``bodyschema validate/test/predict --ckpt_path``) and checks, in this order, before anything is built:

1. the file: ``torch.load(weights_only=True)`` (no pickled code), the entries this package and Lightning read;
2. the class: looked up among the schema classes already defined in this process (``SCHEMA_CLASSES``, filled by
   subclassing ``BodySchema``) or the one the caller passes; nothing a checkpoint names is ever imported;
3. the hyperparameters: against the class's signature (unknown or missing keys, types, sizes in sane ranges);
4. the robot: required entries, spring constants, XML free of file references and of oversized allocations
   (``check_robot_xml``, before MuJoCo sees it);
5. a skeleton of the schema built on the ``meta`` device (no memory; MuJoCo compiles the checked XML here): the
   robot's hash, then every tensor's name, dtype and shape, before the real schema is allocated.

Each problem is one ``BodySchemaInputError`` naming the checkpoint and the field. Non-finite weight values are not
refused here: adaptation answers them with the status ``non_finite``.
"""
from __future__ import annotations

import inspect
import math
import os
import re
import sys
import typing
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, fields
from xml.parsers import expat

import torch

from ..errors import BodySchemaInputError

# Lightning writes these two private hyperparameters when the CLI instantiates the model; its own loaders import
# ``_instantiator`` and ``_class_path``, so they are checked too (the CLI runs Lightning's loader after ours)
LIGHTNING_INSTANTIATOR = "lightning.pytorch.cli.instantiate_module"
PRIVATE_HPARAMS = ("_class_path", "_instantiator")

# sizes a schema's hyperparameters may ask for: (lowest, highest) allowed. Wide enough for any body we train
# (MyoSuite's myoArm: 63 muscles), small enough that a forged value cannot stall or exhaust the machine.
SIZE_LIMITS = {"hidden": (1, 16384), "n_hidden": (1, 64), "latent_dim": (1, 16384), "n_timesteps": (1, 10_000),
               "sample_steps": (1, 10_000), "batch_size": (1, 10_000_000)}
SEED_LIMITS = (0, 2 ** 63 - 1)  # any hyperparameter whose name ends in "seed"
MAX_WEIGHT_ELEMENTS = 50_000_000  # parameters + buffers a schema may hold (200 MB of float32)
MAX_DATASET_SAMPLES = 10_000_000  # n_samples of a checkpoint's data module (load_datamodule regenerates it)

ROBOT_ENTRIES = ("model_xml", "muscles", "spring")  # BodySchema(robot=...) reads exactly these
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


# ---------------------------------------------------------------------------- 1. the file
def read_checkpoint(path: str) -> dict:
    """``torch.load(weights_only=True)`` with one clear error for a missing, truncated or foreign file."""
    if not os.path.isfile(path):
        raise BodySchemaInputError(f"checkpoint {path!r} does not exist")
    try:
        checkpoint = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:
        detail = (str(err).splitlines() or [""])[0]
        detail = detail if len(detail) <= 200 else detail[:200].rsplit(" ", 1)[0] + " ..."
        raise BodySchemaInputError(f"checkpoint {path!r} cannot be read ({type(err).__name__}: "
                                   f"{detail}); is it truncated or not a checkpoint?") from None
    if not isinstance(checkpoint, dict) or "bodyschema" not in checkpoint or "state_dict" not in checkpoint:
        raise BodySchemaInputError(f"{path!r} is not a lightning_bodyschema checkpoint")
    return checkpoint


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


def _check_entries(checkpoint: dict, where: str) -> dict:
    """The entries every loader reads, and the ones Lightning's restore reads for validate/test/predict."""
    meta = _entry(checkpoint, "bodyschema", dict, where)
    _entry(meta, "class_path", str, f"{where}: bodyschema")
    sha = _entry(meta, "model_xml_sha256", str, f"{where}: bodyschema")
    if not re.fullmatch(r"[0-9a-f]{64}", sha):
        raise BodySchemaInputError(f"{where}: bodyschema.model_xml_sha256 = {sha[:80]!r} is not a sha256 hex digest")
    _entry(checkpoint, "hyper_parameters", dict, where)
    _entry(checkpoint, "state_dict", Mapping, where)
    rng = checkpoint.get("torch_rng_state")
    if rng is not None:  # on_load_checkpoint hands it to torch.set_rng_state when Lightning restores
        like = torch.get_rng_state()
        if not torch.is_tensor(rng) or rng.dtype != like.dtype or rng.shape != like.shape:
            shape = tuple(rng.shape) if torch.is_tensor(rng) else type(rng).__name__
            raise BodySchemaInputError(f"{where}: torch_rng_state is {shape}; expected a {like.dtype} tensor of "
                                       f"shape {tuple(like.shape)}")
    cuda = checkpoint.get("torch_cuda_rng_state")  # one uint8 state per GPU, for torch.cuda.set_rng_state_all
    if cuda is not None and not (isinstance(cuda, list) and len(cuda) <= 1024 and all(
            torch.is_tensor(t) and t.dtype == torch.uint8 and t.ndim == 1 for t in cuda)):
        raise BodySchemaInputError(f"{where}: torch_cuda_rng_state is {_describe(cuda)}; expected a list of 1-D "
                                   "uint8 tensors (one per GPU)")
    version = checkpoint.get("pytorch-lightning_version")
    if version is not None and not (isinstance(version, str) and re.fullmatch(r"\d+(\.\d+){0,3}\S{0,32}", version)):
        raise BodySchemaInputError(f"{where}: pytorch-lightning_version = {str(version)[:80]!r} is not a version")
    for key in ("callbacks", "loops", "EquilibriumDataModule", "datamodule_hyper_parameters"):
        if checkpoint.get(key) is not None:
            _entry(checkpoint, key, dict, where)
    return meta


# ---------------------------------------------------------------------------- 2. the class
def schema_class(class_path: str, cls=None, where: str = "checkpoint"):
    """The schema class a checkpoint names, resolved without importing anything.

    ``cls``: the class the caller vouches for (``load_schema(path, cls=...)``); its name must be the checkpoint's
    (the module may differ: a file moved or imported under another package path).
    """
    from .base import SCHEMA_CLASSES, BodySchema, schema_class_path

    if cls is not None:
        if not (isinstance(cls, type) and issubclass(cls, BodySchema)):
            raise BodySchemaInputError(f"cls={cls!r} is not a BodySchema subclass")
        if not _same_name(class_path, cls):
            raise BodySchemaInputError(f"{where} holds a {class_path!r}, not a {schema_class_path(cls)!r}")
        return cls
    known = SCHEMA_CLASSES.get(class_path) or _already_imported(class_path)
    if known is None:
        raise BodySchemaInputError(
            f"{where} names schema class {class_path!r}, which is not a known schema class; a checkpoint never makes "
            "code get imported: import the module that defines it first (tools: --import MODULE), or pass the class "
            f"(load_schema(path, cls=...)); known: {sorted(SCHEMA_CLASSES)}")
    return known


def _same_name(class_path: str, cls) -> bool:
    return class_path == cls.__qualname__ or class_path.endswith("." + cls.__qualname__)


def _already_imported(class_path: str):
    """A registered schema class reached through a module that is already imported (e.g. the re-export
    ``lightning_bodyschema.schemas.DiffusionSchema``), else None. Looks in ``sys.modules`` only."""
    from .base import SCHEMA_CLASSES

    module_name, _, name = class_path.rpartition(".")
    value = getattr(sys.modules.get(module_name), name, None) if module_name else None
    return value if isinstance(value, type) and value in SCHEMA_CLASSES.values() else None


# ---------------------------------------------------------------------------- 3. the hyperparameters
def check_hparams(cls, hparams: dict, where: str, overrides: dict | None = None, vouched: bool = False) -> dict:
    """The constructor arguments of ``cls`` from a checkpoint's ``hyper_parameters`` (plus ``overrides``), checked
    against the signature: unknown and missing keys, types (from the annotations), sizes (``SIZE_LIMITS``).
    ``vouched``: the caller passed ``cls`` (Lightning's ``_class_path`` then needs only the same class name)."""
    for key in hparams:
        if not isinstance(key, str):
            raise BodySchemaInputError(f"{where}: hyper_parameters has a non-text key {key!r}")
    _check_private(cls, hparams, where, vouched)
    given = {k: v for k, v in hparams.items() if not k.startswith("_")}
    given.update(overrides or {})
    signature = inspect.signature(cls.__init__)
    params = {n: p for n, p in list(signature.parameters.items())[1:]
              if p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD)}
    open_ended = any(p.kind == p.VAR_KEYWORD for p in signature.parameters.values())
    unknown = [k for k in given if k not in params]
    if unknown and not open_ended:
        raise BodySchemaInputError(f"{where}: hyper_parameters has unknown key {unknown[0]!r}; {cls.__name__} "
                                   f"accepts {list(params)}")
    missing = [n for n, p in params.items() if n not in given and (p.default is p.empty or n == "robot")]
    if missing:
        raise BodySchemaInputError(f"{where}: hyper_parameters is missing {missing[0]!r} ({cls.__name__} needs it)")
    hints = _type_hints(cls)
    for name, value in given.items():
        if name != "robot" and name in hints:
            _check_value(value, hints[name], f"{where}: hyper_parameters.{name}")
        _check_size(name, value, where)
    return given


def _check_private(cls, hparams: dict, where: str, vouched: bool):
    from .base import BodySchema, schema_class_path

    extra = [k for k in hparams if k.startswith("_") and k not in PRIVATE_HPARAMS]
    if extra:
        raise BodySchemaInputError(f"{where}: hyper_parameters has unknown key {extra[0]!r}")
    instantiator = hparams.get("_instantiator", LIGHTNING_INSTANTIATOR)
    if instantiator != LIGHTNING_INSTANTIATOR:
        raise BodySchemaInputError(f"{where}: hyper_parameters._instantiator = {str(instantiator)[:120]!r}; "
                                   f"only {LIGHTNING_INSTANTIATOR!r} is allowed")
    if "_class_path" in hparams:
        named = hparams["_class_path"]
        if not isinstance(named, str):
            same = False
        elif vouched or not issubclass(cls, BodySchema):
            same = _same_name(named, cls)
        else:
            same = schema_class(named, where=where) is cls
        if not same:
            raise BodySchemaInputError(f"{where}: hyper_parameters._class_path = {str(named)[:120]!r} is not "
                                       f"its class {schema_class_path(cls)!r}")


def _type_hints(cls) -> dict:
    try:
        return typing.get_type_hints(cls.__init__)
    except Exception:  # an annotation that does not evaluate: check plain data only
        return {}


def _check_value(value, hint, where: str):
    """Refuse a value that is not of the annotated type (ints for floats allowed; bools never count as numbers)."""
    if not _matches(value, hint):
        shown = repr(value) if len(repr(value)) <= 80 else f"a {type(value).__name__}"
        raise BodySchemaInputError(f"{where} = {shown}; expected {_hint_name(hint)}")


def _matches(value, hint) -> bool:
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if hint is typing.Any or hint is inspect.Parameter.empty:
        return _plain(value)
    if hint is type(None):
        return value is None
    if origin is typing.Union or type(hint).__name__ == "UnionType":
        return any(_matches(value, a) for a in args)
    if hint is bool:
        return isinstance(value, bool)
    if hint is int:
        return isinstance(value, int) and not isinstance(value, bool)
    if hint is float:
        return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    if hint is str:
        return isinstance(value, str)
    if origin in (list, tuple, Sequence) or hint in (list, tuple, Sequence):
        return (isinstance(value, (list, tuple)) and len(value) <= MAX_SIZE_ATTRIBUTE
                and all(_matches(v, args[0] if args else typing.Any) for v in value))
    if origin in (dict, Mapping) or hint in (dict, Mapping):
        return isinstance(value, dict) and _plain(value)
    return _plain(value)


def _plain(value, depth: int = 0) -> bool:
    """Plain data (None, bool, int, float, str, and lists/dicts of them): what hyperparameters are."""
    if depth > 8:
        return False
    if value is None or isinstance(value, (bool, int, str)):
        return True
    if isinstance(value, float):
        return math.isfinite(value)
    if isinstance(value, (list, tuple)):
        return all(_plain(v, depth + 1) for v in value)
    if isinstance(value, dict):
        return all(isinstance(k, str) and _plain(v, depth + 1) for k, v in value.items())
    return False


def _hint_name(hint) -> str:
    return getattr(hint, "__name__", None) or str(hint).replace("typing.", "")


def _check_size(name: str, value, where: str):
    limits = SIZE_LIMITS.get(name) or (SEED_LIMITS if name.endswith("seed") else None)
    if limits is None or value is None:
        return
    lo, hi = limits
    if isinstance(value, bool) or not isinstance(value, int) or not lo <= value <= hi:
        raise BodySchemaInputError(f"{where}: hyper_parameters.{name} = {str(value)[:80]}; expected an integer in "
                                   f"{lo}..{hi}")


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
    unknown = [k for k in robot if k not in ROBOT_ENTRIES]
    if unknown:
        raise BodySchemaInputError(f"{where}: robot has unknown entry {unknown[0]!r}; allowed: {list(ROBOT_ENTRIES)}")
    xml = _entry(robot, "model_xml", str, f"{where}: robot")
    muscles = _entry(robot, "muscles", list, f"{where}: robot")
    if not muscles or len(muscles) > MAX_SIZE_ATTRIBUTE or not all(isinstance(m, str) for m in muscles):
        raise BodySchemaInputError(f"{where}: robot.muscles must be a non-empty list of tendon names")
    if len(set(muscles)) != len(muscles):
        raise BodySchemaInputError(f"{where}: robot.muscles names a muscle twice: {muscles}")
    _check_spring(_entry(robot, "spring", dict, f"{where}: robot"), len(muscles), where)
    check_robot_xml(xml, f"{where}: robot.model_xml")


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


# ---------------------------------------------------------------------------- 5. the weights
def check_weights(cls, hparams: dict, state_dict, where: str, recorded_sha256: str | None = None):
    """Every tensor of ``state_dict`` against a skeleton of ``cls(**hparams)`` built on the ``meta`` device (no memory
    allocated): names, dtypes (a float may be any float width: it is cast as before), shapes. Before the weights,
    the skeleton's compiled robot must have the hash the checkpoint recorded (``recorded_sha256``)."""
    try:
        with torch.device("meta"):
            skeleton = cls(**hparams)
    except BodySchemaInputError as err:  # the robot does not compile, or a value the class refuses
        raise BodySchemaInputError(f"{where}: {err}") from None
    except (TypeError, ValueError, RuntimeError, NotImplementedError) as err:
        raise BodySchemaInputError(f"{where}: {cls.__name__} cannot be built from its hyperparameters on the meta "
                                   f"device ({type(err).__name__}: {str(err).splitlines()[0][:200]})") from None
    built_sha256 = skeleton.robot_model.xml_hash
    if recorded_sha256 is not None and built_sha256 != recorded_sha256:
        raise BodySchemaInputError(f"{where}: its robot XML does not match its recorded hash "
                                   f"({built_sha256[:12]} != {recorded_sha256[:12]})")
    expected = skeleton.state_dict()
    n_elements = sum(t.numel() for t in expected.values())
    if n_elements > MAX_WEIGHT_ELEMENTS:
        raise BodySchemaInputError(f"{where}: its hyperparameters ask for {n_elements} weights; at most "
                                   f"{MAX_WEIGHT_ELEMENTS} are allowed")
    for name, tensor in state_dict.items():
        if name not in expected:
            raise BodySchemaInputError(f"{where}: state_dict has unexpected tensor {str(name)[:120]!r} "
                                       f"({cls.__name__} has no such weight)")
        want = expected[name]
        if not torch.is_tensor(tensor) or tensor.layout != torch.strided or tensor.is_quantized:
            raise BodySchemaInputError(f"{where}: state_dict[{name!r}] is {_describe(tensor)}; expected a dense "
                                       f"{want.dtype} tensor of shape {tuple(want.shape)}")
        if tensor.dtype != want.dtype and not (tensor.is_floating_point() and want.is_floating_point()):
            raise BodySchemaInputError(f"{where}: state_dict[{name!r}] has dtype {tensor.dtype}; expected {want.dtype}")
        if tensor.shape != want.shape:
            raise BodySchemaInputError(f"{where}: state_dict[{name!r}] has shape {tuple(tensor.shape)}; the "
                                       f"hyperparameters imply {tuple(want.shape)}")
    missing = [name for name in expected if name not in state_dict]
    if missing:
        raise BodySchemaInputError(f"{where}: state_dict is missing tensor {missing[0]!r} of shape "
                                   f"{tuple(expected[missing[0]].shape)} ({len(missing)} missing)")


def _describe(value) -> str:
    if torch.is_tensor(value):
        return f"a {value.layout} {value.dtype} tensor"
    return f"a {type(value).__name__}"


# ---------------------------------------------------------------------------- everything, in order
@dataclass
class CheckedCheckpoint:
    """A checkpoint that passed every check: its class, constructor arguments and the file's contents."""

    cls: type
    hparams: dict
    checkpoint: dict


def check_checkpoint(checkpoint: dict, path: str, cls=None, overrides: dict | None = None) -> CheckedCheckpoint:
    """Run checks 1-5 (module docstring) on a ``read_checkpoint`` result; the first problem raises."""
    where = f"checkpoint {path!r}"
    meta = _check_entries(checkpoint, where)
    vouched = cls is not None
    cls = schema_class(meta["class_path"], cls, where)
    hparams = check_hparams(cls, checkpoint["hyper_parameters"], where, overrides, vouched)
    check_robot(hparams["robot"], where)
    check_weights(cls, hparams, checkpoint["state_dict"], where, meta["model_xml_sha256"])
    return CheckedCheckpoint(cls, hparams, checkpoint)


def load_schema(path: str, expected_model_xml_sha256: str | None = None, cls=None, overrides: dict | None = None):
    """Rebuild the trained schema in eval mode on the CPU from ``path`` alone, after every check.

    ``expected_model_xml_sha256``: refuse a checkpoint trained on another robot than this one.
    ``cls``: the schema class, for a user's class whose module is not imported (its name must be the checkpoint's);
    by default the class is looked up among the schema classes this process has defined.
    ``overrides``: hyperparameters to replace (checked the same way), as in ``load_from_checkpoint(path, **kw)``.
    """
    checked = check_checkpoint(read_checkpoint(path), path, cls, overrides)
    recorded = checked.checkpoint["bodyschema"]["model_xml_sha256"]
    if expected_model_xml_sha256 and recorded != expected_model_xml_sha256:
        raise BodySchemaInputError(
            f"checkpoint {path!r} was trained on another robot model (xml sha256 {recorded[:12]} "
            f"!= {expected_model_xml_sha256[:12]})")
    schema = checked.cls(**checked.hparams)
    schema.load_state_dict(checked.checkpoint["state_dict"])
    return schema.eval()


def load_datamodule(path: str, cache_dir: str | None = None):
    """The data module a checkpoint was trained with, rebuilt from the checkpoint alone (robot XML inside)."""
    from ..data import EquilibriumDataModule

    checkpoint = read_checkpoint(path)
    checked = check_checkpoint(checkpoint, path)
    robot = checked.hparams["robot"]
    where = f"checkpoint {path!r}: datamodule_hyper_parameters"
    saved = dict(checkpoint.get("datamodule_hyper_parameters") or {})
    robot_args = dict(model=robot["model_xml"], muscles=robot["muscles"], gravity=None, cache_dir=cache_dir,
                      **robot["spring"])
    hparams = check_hparams(EquilibriumDataModule, saved, where, overrides=robot_args)
    if not isinstance(hparams.get("n_samples", 0), int) or hparams.get("n_samples", 0) > MAX_DATASET_SAMPLES:
        raise BodySchemaInputError(f"{where}.n_samples = {hparams['n_samples']}; at most {MAX_DATASET_SAMPLES}")
    datamodule = EquilibriumDataModule(**hparams)
    datamodule.setup("test")
    return datamodule
