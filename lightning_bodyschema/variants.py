"""THE check of an adaptation variant's name, for every caller (the schema's ``Adapter``, ``FaultBenchmark``, the
tools): a variant is one of the ``VARIANTS`` its schema class declares. Imports nothing of the package but errors,
so every layer can use it."""
from __future__ import annotations

from typing import Iterable, Union

from .errors import BodySchemaInputError


def schema_variants(schemas) -> tuple[str, ...]:
    """The variant names of ``schemas`` (a schema, a schema class, or an iterable of them: their union, in order)."""
    if isinstance(schemas, Iterable) and not isinstance(schemas, (str, bytes)):
        return tuple(dict.fromkeys(name for s in schemas for name in schema_variants(s)))
    return tuple(getattr(schemas, "VARIANTS", ()))


def check_variant(schemas: Union[object, Iterable], variant, option: str = "variant") -> str:
    """``variant`` if ``schemas`` (see ``schema_variants``) declare it; else one ``BodySchemaInputError`` naming
    ``option`` (how the caller's user spells it, e.g. ``--faults.variant``), the value and the allowed names."""
    allowed = schema_variants(schemas)
    if not isinstance(variant, str) or variant not in allowed:
        raise BodySchemaInputError(f"unknown {option} {variant!r}; allowed: {list(allowed)}")
    return variant
