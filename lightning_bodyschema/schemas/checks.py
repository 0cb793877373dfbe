"""Checks 2, 3 and 5 of a checkpoint (``loading.check_checkpoint`` runs them in order, check 4 is ``robot_checks``).

2. the class: looked up among the schema classes already defined in this process (``schema_class``); nothing a
   checkpoint names is ever imported;
3. the hyperparameters: against the class's signature (``check_hparams``: unknown or missing keys, types, sizes);
5. the weights: every tensor's name, dtype and shape against a skeleton built on the ``meta`` device
   (``check_weights``), after the robot's hash.

Each problem is one ``BodySchemaInputError`` naming the checkpoint and the field.
"""
from __future__ import annotations

import inspect
import math
import sys
import typing
from collections.abc import Mapping, Sequence

import torch

from ..errors import BodySchemaInputError
from .registry import SCHEMA_CLASSES, is_schema_class, schema_class_path
from .robot_checks import MAX_SIZE_ATTRIBUTE

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


# ---------------------------------------------------------------------------- 2. the class
def schema_class(class_path: str, cls=None, where: str = "checkpoint"):
    """The schema class a checkpoint names, resolved without importing anything.

    ``cls``: the class the caller vouches for (``load_schema(path, cls=...)``); its name must be the checkpoint's
    (the module may differ: a file moved or imported under another package path).
    """
    if cls is not None:
        if not is_schema_class(cls):
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
        elif vouched or not is_schema_class(cls):
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
