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
refused here: adaptation answers them with the status ``non_finite``. Checks 2, 3 and 5 live in ``checks.py``,
check 4 in ``robot_checks.py``; this module reads the file and builds the schema.
"""
from __future__ import annotations

import os
import re
from collections.abc import Mapping
from dataclasses import dataclass

import torch

from ..errors import BodySchemaInputError
from .checks import _describe, check_hparams, check_weights, schema_class
from .registry import CHECKPOINT_FORMAT
from .robot_checks import _entry, check_robot
# the checks' limits and entry points, also importable from here
from .checks import (LIGHTNING_INSTANTIATOR, MAX_WEIGHT_ELEMENTS, PRIVATE_HPARAMS, SEED_LIMITS,  # noqa: F401
                     SIZE_LIMITS)
from .robot_checks import (MAX_SIZE_ATTRIBUTE, MAX_SIZE_MEMORY_BYTES, MAX_XML_ALLOCATION,  # noqa: F401
                           MAX_XML_CHARS, MODEL_FREE_ROBOT_ENTRIES, ROBOT_ENTRIES, SPRING_LIMITS, check_robot_xml)

MAX_DATASET_SAMPLES = 10_000_000  # n_samples of a checkpoint's data module (load_datamodule regenerates it)


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


def _check_entries(checkpoint: dict, where: str) -> dict:
    """The entries every loader reads, and the ones Lightning's restore reads for validate/test/predict."""
    meta = _entry(checkpoint, "bodyschema", dict, where)
    _entry(meta, "class_path", str, f"{where}: bodyschema")
    sha = _entry(meta, "model_xml_sha256", str, f"{where}: bodyschema")
    if not re.fullmatch(r"[0-9a-f]{64}", sha):
        raise BodySchemaInputError(f"{where}: bodyschema.model_xml_sha256 = {sha[:80]!r} is not a sha256 hex digest")
    fmt = meta.get("format", 1)
    if isinstance(fmt, bool) or not isinstance(fmt, int) or not 1 <= fmt <= CHECKPOINT_FORMAT:
        raise BodySchemaInputError(f"{where}: bodyschema.format = {repr(fmt)[:80]}; this version reads formats 1 to "
                                   f"{CHECKPOINT_FORMAT} (a newer one: update lightning_bodyschema)")
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


def check_device(device, what: str = "device") -> torch.device:
    """``device`` (``"cpu"``, ``"cuda"``, ``"cuda:1"``, a ``torch.device``) as a ``torch.device`` this machine has;
    anything else is a ``BodySchemaInputError`` naming it."""
    try:
        parsed = torch.device(device)
    except (RuntimeError, TypeError, ValueError):
        raise BodySchemaInputError(f"{what}={device!r} is not a torch device; give 'cpu', 'cuda' or 'cuda:N'") from None
    if parsed.type == "cuda" and (not torch.cuda.is_available() or (parsed.index or 0) >= torch.cuda.device_count()):
        raise BodySchemaInputError(f"{what}={device!r}: this machine has {torch.cuda.device_count()} CUDA device(s) "
                                   "(torch.cuda.is_available() is False or the index is too high); use 'cpu'")
    return parsed


def load_schema(path: str, expected_model_xml_sha256: str | None = None, cls=None, overrides: dict | None = None,
                map_location=None):
    """Rebuild the trained schema in eval mode from ``path`` alone, after every check: on the CPU, then moved to
    ``map_location`` (``"cuda"``, ``"cuda:1"``, a ``torch.device``; None: stay on the CPU). The checkpoint is always
    read on the CPU; ``schema.to(device)`` later moves it the same way. On any device, ``infer``/``adapt``/
    ``adapter``/``adapt_to_target`` take numpy arrays or tensors and return numpy arrays.

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
    device = None if map_location is None else check_device(map_location, "map_location")
    schema = checked.cls(**checked.hparams)
    refusal = schema.checkpoint_refusal(checked.checkpoint["bodyschema"])
    if refusal:
        raise BodySchemaInputError(f"checkpoint {path!r}: {refusal}")
    schema.load_state_dict(checked.checkpoint["state_dict"])
    schema.checkpoint_path = path  # where its data module can be rebuilt from (the diagnosis's body error)
    return schema.eval() if device is None else schema.eval().to(device)


def load_datamodule(path: str, cache_dir: str | None = None):
    """The data module a checkpoint was trained with, rebuilt from the checkpoint alone (robot XML inside)."""
    from ..data import EquilibriumDataModule

    checkpoint = read_checkpoint(path)
    checked = check_checkpoint(checkpoint, path)
    robot = checked.hparams["robot"]
    where = f"checkpoint {path!r}: datamodule_hyper_parameters"
    saved = dict(checkpoint.get("datamodule_hyper_parameters") or {})
    if "model_xml" not in robot:  # trained on recorded data: the file it was read from rebuilds the splits
        from ..data import RecordedDataModule

        datamodule = RecordedDataModule(**check_hparams(RecordedDataModule, saved, where))
        datamodule.setup("test")
        return datamodule
    robot_args = dict(model=robot["model_xml"], muscles=robot["muscles"], gravity=None, cache_dir=cache_dir,
                      **robot["spring"])
    hparams = check_hparams(EquilibriumDataModule, saved, where, overrides=robot_args)
    if not isinstance(hparams.get("n_samples", 0), int) or hparams.get("n_samples", 0) > MAX_DATASET_SAMPLES:
        raise BodySchemaInputError(f"{where}.n_samples = {hparams['n_samples']}; at most {MAX_DATASET_SAMPLES}")
    datamodule = EquilibriumDataModule(**hparams)
    datamodule.setup("test")
    return datamodule
