"""The schema classes a checkpoint may name: filled by subclassing ``BodySchema``, read by the checkpoint checks.

A class is known once the user's code has defined (imported) it; a checkpoint never makes anything get imported.
This module imports nothing of the package, so the checks (``checks.py``) and ``BodySchema`` both use it without
depending on each other.
"""
from __future__ import annotations

# what a checkpoint's weights mean, in its ``bodyschema`` entry (absent: 1). 2: the gravity torque's slide joints
# translate without rotating (a fix; StructuredSchema.checkpoint_refusal)
CHECKPOINT_FORMAT = 2

# class path -> schema class, filled by subclassing (BodySchema.__init_subclass__)
SCHEMA_CLASSES: dict[str, type] = {}
_ROOTS: list[type] = []  # the base class every schema class derives from (BodySchema), set where it is defined


def schema_class_path(cls) -> str:
    """``module.QualName``: how checkpoints name a schema class."""
    return f"{cls.__module__}.{cls.__qualname__}"


def register_root(cls: type) -> type:
    """Make ``cls`` the class every schema class must derive from (``is_schema_class``)."""
    _ROOTS[:] = [cls]
    return cls


def register(cls: type) -> None:
    SCHEMA_CLASSES[schema_class_path(cls)] = cls


def is_schema_class(cls) -> bool:
    """True for ``BodySchema`` and its subclasses."""
    return isinstance(cls, type) and any(issubclass(cls, root) for root in _ROOTS)
