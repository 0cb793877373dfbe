"""``PathConfig``: the options of a per-muscle path model (``networks.per_muscle.PerMusclePath``) in one typed object,
checked in one place, for the network and for ``StructuredSchema``'s ``path_*`` arguments alike. Plain Python."""
from __future__ import annotations

from dataclasses import dataclass, fields
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
    """A per-muscle path's options.

    degree, max_terms: each muscle's polynomial has the highest total degree ``<= degree`` with at most ``max_terms``
        terms over the joints it crosses (``degrees.muscle_degrees``).
    term_budget: None, or the most terms over all muscles together: what ``max_terms`` leaves is spent raising the
        lowest degrees first (the muscles that cross many joints), up to ``degree``.
    degrees: None, or each muscle's total degree ``(M,)`` (then ``degree``, ``max_terms`` and ``term_budget`` are not
        used; ``per_muscle.degrees_within_tolerance`` chooses them from data).
    hidden, n_hidden: width and number of hidden layers of each muscle's MLP (n_hidden 0: no MLP).
    branches, gate_degree: 2: two polynomials and a gate of total degree ``<= gate_degree`` where a path jumps
        (``networks.branches``).
    cells, cell_degrees: 1 (none), or pieces per joint: the muscles a smooth polynomial fits worst get ``cells ** n``
        cells over their ``n`` cut joints, one polynomial each (``networks.cells``); ``cell_degrees`` (M,) the fit's
        choice (0: no cells), which a checkpoint rebuilds.
    blocks: None, or ``(M, N)`` ints: each muscle's length as a sum of one polynomial per group of its joints
        (``per_muscle.check_blocks``; ``sim.separable.separable_blocks`` finds them in an MJCF).
    cell_trim: None, or each cell refitted without the samples it misses by more than this many times the kept
        ones' median (``cell_fit._trimmed``).
    cell_joints: which joints cut a celled muscle's box (``cells.cell_cuts``), one of ``CELL_JOINTS``.
    cell_keep: what a muscle's cells must improve on the fitted samples to be kept (``cell_fit._kept``), one of
        ``CELL_KEEP``.
    """

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

    def options(self) -> dict:
        """Every option by name."""
        return {f.name: getattr(self, f.name) for f in fields(self)}
