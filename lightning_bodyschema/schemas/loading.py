"""Load a trained schema from its ``.ckpt`` alone: the checkpoint carries the robot and the normalizer.

Checkpoints are untrusted input: read with ``weights_only=True`` (no pickled code), and the class
named inside must be a ``BodySchema`` subclass.
"""
from __future__ import annotations

import importlib
import os

import torch

from ..errors import BodySchemaInputError


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


def _schema_class(class_path: str):
    from .base import BodySchema

    module_name, _, name = class_path.rpartition(".")
    try:
        cls = getattr(importlib.import_module(module_name), name)
    except (ImportError, AttributeError):
        raise BodySchemaInputError(f"checkpoint names schema class {class_path!r}, which cannot be imported") from None
    if not (isinstance(cls, type) and issubclass(cls, BodySchema)):
        raise BodySchemaInputError(f"checkpoint class {class_path!r} is not a BodySchema")
    return cls


def load_schema(path: str, expected_model_xml_sha256: str | None = None):
    """Rebuild the trained schema in eval mode on the CPU from ``path`` alone.

    ``expected_model_xml_sha256``: refuse a checkpoint trained on another robot than this one.
    """
    checkpoint = read_checkpoint(path)
    meta = checkpoint["bodyschema"]
    if expected_model_xml_sha256 and meta["model_xml_sha256"] != expected_model_xml_sha256:
        raise BodySchemaInputError(
            f"checkpoint {path!r} was trained on another robot model (xml sha256 {meta['model_xml_sha256'][:12]} "
            f"!= {expected_model_xml_sha256[:12]})")
    cls = _schema_class(meta["class_path"])
    hparams = {k: v for k, v in checkpoint["hyper_parameters"].items() if not k.startswith("_")}
    schema = cls(**hparams)
    schema.load_state_dict(checkpoint["state_dict"])
    if schema.robot_model.xml_hash != meta["model_xml_sha256"]:
        raise BodySchemaInputError(f"checkpoint {path!r}: its robot XML does not match its recorded hash")
    return schema.eval()


def load_datamodule(path: str, cache_dir: str | None = None):
    """The data module a checkpoint was trained with, rebuilt from the checkpoint alone (robot XML inside)."""
    from ..data import EquilibriumDataModule

    checkpoint = read_checkpoint(path)
    robot = checkpoint["hyper_parameters"]["robot"]
    hparams = {k: v for k, v in (checkpoint.get("datamodule_hyper_parameters") or {}).items() if not k.startswith("_")}
    if not robot.get("model_xml"):  # trained on recorded data: the file it was read from rebuilds the splits
        from ..data import RecordedDataModule

        datamodule = RecordedDataModule(**hparams)
        datamodule.setup("test")
        return datamodule
    hparams.update(model=robot["model_xml"], muscles=robot["muscles"], gravity=None, cache_dir=cache_dir,
                   **{k: v for k, v in robot["spring"].items()})
    datamodule = EquilibriumDataModule(**hparams)
    datamodule.setup("test")
    return datamodule
