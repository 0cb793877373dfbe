"""Box plots of the fault benchmark, laid out like the paper's figure "exp-results".

Rows: the metrics (E_cut [N], E_fix [mm], then E_weak [N] and E_band [mm] when the cases have such faults,
E_tau [N m], E_q [rad]); columns: the conditions of the cases (CUT, FIX, BOTH; + WEAK, BAND for the binding
protocol); one box per model (and per command kind, when several are asked for), after optional reference boxes
(the unadapted command, the physics oracle). A metric that is undefined under a condition (E_fix under CUT:
nothing is jammed; E_cut under FIX: nothing is ruptured) shows "n/a". A panel whose values span more than two
decades gets a symmetric-log axis, linear near 0 (so exact zeros, as the oracle's, stay visible) and
logarithmic above. Save with ``plots.arm.save_figure_atomic``.
"""
from __future__ import annotations

from typing import Sequence

import matplotlib

matplotlib.use("Agg")
import numpy as np  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402

from ..errors import BodySchemaInputError  # noqa: E402
from ..evaluation.benchmark import READINGS, BenchmarkResult  # noqa: E402
from ..evaluation.metrics import EXTRA_METRICS, METRICS  # noqa: E402

CONDITION_ORDER = ("CUT", "FIX", "BOTH", "WEAK", "BAND", "MIXED", "NONE")
# metric -> (factor from SI, axis label); E_fix / E_band are stored in metres and shown in millimetres
METRIC_UNITS = {"E_cut": (1.0, "E_cut [N]"), "E_fix": (1e3, "E_fix [mm]"), "E_weak": (1.0, "E_weak [N]"),
                "E_band": (1e3, "E_band [mm]"), "E_tau": (1.0, "E_tau [N m]"), "E_q": (1.0, "E_q [rad]")}
ROW_ORDER = ("E_cut", "E_fix", "E_weak", "E_band", "E_tau", "E_q")
# below this (display units) a symlog axis is linear: about the smallest difference the tables care about
LINTHRESH = {"E_cut": 1e-2, "E_fix": 1e-3, "E_weak": 1e-2, "E_band": 1e-3, "E_tau": 1e-3, "E_q": 1e-4}
DECADES_FOR_LOG = 2.0  # a panel whose values span more than this many decades above LINTHRESH gets a symlog axis
SUBSETS = ("all", "feasible", "feasible_active")
_TAB10 = ["#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f", "#bcbd22", "#17becf"]
_REFERENCE_STYLE = {"unadapted": ("0.45", True), "oracle": ("k", False)}  # kind -> (colour, hatched)


def _check(results, reading, subset, kinds, references):
    if not results:
        raise BodySchemaInputError("fault_boxplots needs at least one {model name: BenchmarkResult}")
    if reading not in READINGS:
        raise BodySchemaInputError(f"unknown reading {reading!r}; allowed: {list(READINGS)}")
    if subset not in SUBSETS:
        raise BodySchemaInputError(f"unknown subset {subset!r}; allowed: {list(SUBSETS)}")
    named = [(name, result, k) for name, result in results.items() for k in kinds]
    named += [(label, result, k) for label, (result, k) in references.items()]
    for name, result, k in named:
        if k not in result.metrics:
            raise BodySchemaInputError(f"result {name!r} has no {k!r} commands; it has {list(result.metrics)}")


def panel_values(result: BenchmarkResult, metric: str, cond: str, reading: str = "phys", subset: str = "all",
                 kind: str = "adapted") -> np.ndarray:
    """The finite values of one metric (display units) over one condition's cases in ``subset``."""
    rows = result.cases.cond == cond
    if subset != "all":
        rows = rows & result.feasible[reading]
    if subset == "feasible_active":
        rows = rows & result.active
    values = METRIC_UNITS[metric][0] * np.asarray(result.metrics[kind][reading][metric], float)[rows]
    return values[np.isfinite(values)]


def _defined(series, metric, cond) -> bool:
    """Whether the metric exists at all under ``cond`` (some case of some command has a finite value)."""
    return any(np.isfinite(np.asarray(r.metrics[k][reading][metric], float)[r.cases.cond == cond]).any()
               for _, r, k, _ in series for reading in r.metrics[k])


def _series(results, kinds, references):
    """[(label, result, kind, (colour, hatched))]: the reference boxes first, then each model's kinds."""
    out = [(label, result, k, _REFERENCE_STYLE.get(k, ("0.3", False))) for label, (result, k) in references.items()]
    for i, (name, result) in enumerate(results.items()):
        for k in kinds:
            label = name if len(kinds) == 1 else f"{name}\n{k}"
            out.append((label, result, k, (_TAB10[i % len(_TAB10)], k == "unadapted")))
    return out


def fault_boxplots(results: dict[str, BenchmarkResult], reading: str = "phys", subset: str = "all",
                   kind: str | Sequence[str] = "adapted", title: str | None = None,
                   references: dict | None = None) -> Figure:
    """A grid of box plots (metrics x conditions), one box per model name (the dict key).

    Args:
        results: {model name: BenchmarkResult}, boxes in the dict's order (e.g. AE-3 ... VAE-30, Diff).
        reading: ``"phys"`` (jammed muscles pull) or ``"paper"`` (the paper's metric definitions).
        subset: ``"all"`` cases, only the ``"feasible"`` ones (under the same reading), or ``"feasible_active"``
            (feasible, and the healthy command breaks a fault: ``BenchmarkResult.active``).
        kind: ``"adapted"``, ``"unadapted"``, or both (a sequence): then each model gets one box per kind,
            unadapted drawn hatched, so the effect of adaptation is visible model by model.
        references: {label: (BenchmarkResult, kind)} boxes drawn first, e.g.
            ``{"unadapted (Diff)": (diff, "unadapted"), "oracle": (diff, "oracle")}``.
    Returns a matplotlib Figure (Agg canvas, not registered with pyplot: no need to close it).
    """
    kinds = (kind,) if isinstance(kind, str) else tuple(kind)
    references = dict(references or {})
    _check(results, reading, subset, kinds, references)
    series = _series(results, kinds, references)
    present = set().union(*(r.cases.cond.tolist() for r in results.values()))
    conditions = [c for c in CONDITION_ORDER if c in present]
    metrics = [m for m in ROW_ORDER if m in METRICS
               or any(_defined(series, m, c) for c in conditions if m in EXTRA_METRICS)]
    width = max(7.5, 1.5 + 0.42 * len(series) * len(conditions))
    fig = Figure(figsize=(width, 2.25 * len(metrics)), layout="constrained")
    axes = fig.subplots(len(metrics), len(conditions), squeeze=False, sharex=True)
    for row, metric in enumerate(metrics):
        for col, cond in enumerate(conditions):
            ax = axes[row, col]
            _panel(ax, series, metric, cond, reading, subset)
            if row == 0:
                ax.set_title(cond)
            if col == 0:
                ax.set_ylabel(METRIC_UNITS[metric][1])
    labels = [label for label, *_ in series]
    for ax in axes[-1]:
        tilt = len(labels) > 3
        ax.set_xticks(np.arange(1, len(labels) + 1), labels, rotation=45 if tilt else 0,
                      ha="right" if tilt else "center", rotation_mode="anchor", fontsize=8)
    fig.suptitle(title or f"fault benchmark: {', '.join(kinds)} commands, {reading} reading, {subset} cases")
    return fig


def _panel(ax, series, metric, cond, reading, subset):
    ax.set_xlim(0.4, len(series) + 0.6)
    ax.grid(axis="y", lw=0.4, alpha=0.5)
    if not _defined(series, metric, cond):
        ax.text(0.5, 0.5, "n/a", transform=ax.transAxes, ha="center", va="center", color="0.4", fontsize=12)
        ax.set_yticks([])
        return
    data, positions, styles, empty = [], [], [], []
    for slot, (_, result, k, style) in enumerate(series, start=1):
        values = panel_values(result, metric, cond, reading, subset, k)
        if values.size:
            data.append(values)
            positions.append(slot)
            styles.append(style)
        else:  # matplotlib cannot draw an empty box: mark the slot (no case, or every command non-finite)
            empty.append(slot)
    for slot in empty:
        ax.text(slot, 0.5, "none", transform=ax.get_xaxis_transform(), ha="center", va="center", rotation=90,
                color="0.5", fontsize=7)
    if not data:
        return
    boxes = ax.boxplot(data, positions=positions, widths=0.6, patch_artist=True, manage_ticks=False,
                       flierprops={"markersize": 3, "alpha": 0.6}, medianprops={"color": "k"})
    for patch, (color, hatched) in zip(boxes["boxes"], styles):
        patch.set_facecolor("white" if hatched else color)
        patch.set_edgecolor(color)
        patch.set_alpha(0.8)
        if hatched:
            patch.set_hatch("///")
    _scale(ax, np.concatenate(data), metric)


def _scale(ax, values, metric):
    """A symmetric-log axis when the panel's values span more than DECADES_FOR_LOG decades above LINTHRESH."""
    top = np.max(np.abs(values)) if values.size else 0.0
    if top > LINTHRESH[metric] * 10 ** DECADES_FOR_LOG:
        ax.set_yscale("symlog", linthresh=LINTHRESH[metric], linscale=0.5)
        ax.set_ylim(bottom=0.0)
