"""``PathConfig``: the options of a per-muscle path model (``networks.per_muscle.PerMusclePath``) in one typed object,
checked in one place, for the network and for ``StructuredSchema``'s ``path_*`` arguments alike. Plain Python."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Optional

from ..errors import BodySchemaInputError

CELL_JOINTS = ("crossed", "largest_group")  # which joints cut a muscle's box (``cells.cell_cuts``)
CELL_KEEP = ("median_and_p99", "median")  # what a muscle's cells must improve to be kept (``cell_fit._kept``)
# each option's name among ``StructuredSchema``'s arguments (its refusals name those)
SCHEMA_NAMES = dict(degree="path_degree", hidden="path_hidden", n_hidden="path_layers", max_terms="path_terms",
                    branches="path_branches", gate_degree="path_gate_degree", term_budget="path_term_budget",
                    degrees="path_degrees", cells="path_cells", cell_degrees="path_cell_degrees",
                    blocks="path_blocks", cell_trim="path_cell_trim", cell_joints="path_cell_joints",
                    cell_keep="path_cell_keep")
SCHEMA_GATE_DEGREE = 8  # ``StructuredSchema(path_gate_degree=...)``'s default (a checkpoint without it had it)


@dataclass(frozen=True)
class PathConfig:
    """A per-muscle path's options: each field is the ``StructuredSchema`` argument ``SCHEMA_NAMES`` names, whose
    docstring states its contract (``n_hidden``: ``path_layers``, ``cells``: ``path_cells``, ...)."""

    degree: int = 6
    hidden: int = 32
    n_hidden: int = 2
    max_terms: int = 10 ** 6
    branches: int = 1
    gate_degree: int = 4
    term_budget: Optional[int] = None
    degrees: Any = None
    cells: int = 1
    cell_degrees: Any = None
    blocks: Any = None
    cell_trim: Optional[float] = None
    cell_joints: str = "crossed"
    cell_keep: str = "median_and_p99"

    @classmethod
    def from_schema(cls, hparams) -> "PathConfig":
        """The options of ``StructuredSchema``'s ``path_*`` arguments (a checkpoint's older hparams: the defaults
        of the options it lacks), checked with their names."""
        given = {field: hparams.get(name) for field, name in SCHEMA_NAMES.items() if hparams.get(name) is not None}
        return cls(**{"gate_degree": SCHEMA_GATE_DEGREE, **given}).checked(SCHEMA_NAMES)

    def checked(self, names: Optional[dict] = None) -> "PathConfig":
        """Itself, or one ``BodySchemaInputError`` naming the first bad option (by ``names``: the caller's name for
        each) and what is allowed."""
        name = lambda field: (names or {}).get(field, field)  # noqa: E731
        for field, low in (("degree", 1), ("hidden", 1), ("n_hidden", 0), ("max_terms", 2), ("gate_degree", 1),
                           ("cells", 1)):
            value = getattr(self, field)
            if isinstance(value, bool) or not isinstance(value, int) or value < low:
                raise BodySchemaInputError(f"{name(field)}={value!r} must be an integer >= {low}"
                                           + (" (pieces per joint; 1: no cells)" if field == "cells" else ""))
        if self.branches not in (1, 2) or isinstance(self.branches, bool):
            raise BodySchemaInputError(f"{name('branches')}={self.branches!r}; allowed: 1 (one polynomial per muscle) "
                                       f"or 2 (two and a gate where a muscle's path jumps)")
        trim = self.cell_trim
        if trim is not None and (isinstance(trim, bool) or not isinstance(trim, (int, float)) or not trim > 1):
            raise BodySchemaInputError(f"{name('cell_trim')}={trim!r} must be None or a number > 1 (times the median "
                                       f"miss)")
        for field, allowed in (("cell_joints", CELL_JOINTS), ("cell_keep", CELL_KEEP)):
            if getattr(self, field) not in allowed:
                raise BodySchemaInputError(f"{name(field)}={getattr(self, field)!r}; allowed: {list(allowed)}")
        return self
