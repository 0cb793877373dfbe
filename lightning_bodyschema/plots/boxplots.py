"""Box plots of the fault benchmark, laid out like the paper's figure "exp-results".

Rows: E_cut [N], E_fix [mm], E_tau [N m], E_q [rad]; columns: CUT, FIX, BOTH; one box per model
(and per command kind, when several are asked for). A metric that is undefined under a condition
(E_fix under CUT: nothing is jammed; E_cut under FIX: nothing is ruptured) shows "n/a".
Save with ``plots.arm.save_figure_atomic``.
"""
from __future__ import annotations

from typing import Sequence

import matplotlib

matplotlib.use("Agg")
import numpy as np  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402

from ..errors import BodySchemaInputError  # noqa: E402
from ..evaluation.benchmark import READINGS, BenchmarkResult  # noqa: E402
from ..evaluation.metrics import METRICS  # noqa: E402

PANEL_CONDITIONS = ("CUT", "FIX", "BOTH")
# metric -> (factor from SI, axis label); E_fix is stored in metres and shown in millimetres
METRIC_UNITS = {"E_cut": (1.0, "E_cut [N]"), "E_fix": (1e3, "E_fix [mm]"),
                "E_tau": (1.0, "E_tau [N m]"), "E_q": (1.0, "E_q [rad]")}
SUBSETS = ("all", "feasible")
_TAB10 = ["#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f", "#bcbd22", "#17becf"]


def _check(results, reading, subset, kinds):
    if not results:
        raise BodySchemaInputError("fault_boxplots needs at least one {model name: BenchmarkResult}")
    if reading not in READINGS:
        raise BodySchemaInputError(f"unknown reading {reading!r}; allowed: {list(READINGS)}")
    if subset not in SUBSETS:
        raise BodySchemaInputError(f"unknown subset {subset!r}; allowed: {list(SUBSETS)}")
    for name, result in results.items():
        missing = [k for k in kinds if k not in result.metrics]
        if missing:
            raise BodySchemaInputError(f"result {name!r} has no {missing} commands; it has {list(result.metrics)}")


def panel_values(result: BenchmarkResult, metric: str, cond: str, reading: str = "phys", subset: str = "all",
                 kind: str = "adapted") -> np.ndarray:
    """The finite values of one metric (display units) over one condition's cases in ``subset``."""
    rows = result.cases.cond == cond
    if subset == "feasible":
        rows = rows & result.feasible[reading]
    values = METRIC_UNITS[metric][0] * np.asarray(result.metrics[kind][reading][metric], float)[rows]
    return values[np.isfinite(values)]


def _defined(results, metric, cond, kinds) -> bool:
    """Whether the metric exists at all under ``cond`` (some case of some model has a finite value)."""
    return any(np.isfinite(np.asarray(r.metrics[k][reading][metric], float)[r.cases.cond == cond]).any()
               for r in results.values() for k in kinds for reading in r.metrics[k])


def fault_boxplots(results: dict[str, BenchmarkResult], reading: str = "phys", subset: str = "all",
                   kind: str | Sequence[str] = "adapted", title: str | None = None) -> Figure:
    """A 4 x 3 grid of box plots (metrics x conditions), one box per model name (the dict key).

    Args:
        results: {model name: BenchmarkResult}, boxes in the dict's order (e.g. AE-3 ... VAE-30, Diff).
        reading: ``"phys"`` (jammed muscles pull) or ``"paper"`` (the paper's metric definitions).
        subset: ``"all"`` cases or only the ``"feasible"`` ones (under the same reading).
        kind: ``"adapted"``, ``"unadapted"``, or both (a sequence): then each model gets one box per kind,
            unadapted drawn hatched, so the effect of adaptation is visible model by model.
    Returns a matplotlib Figure (Agg canvas, not registered with pyplot: no need to close it).
    """
    kinds = (kind,) if isinstance(kind, str) else tuple(kind)
    _check(results, reading, subset, kinds)
    names = list(results)
    labels = [n if len(kinds) == 1 else f"{n}\n{k}" for n in names for k in kinds]
    width = max(7.5, 1.5 + 0.6 * len(labels) * len(PANEL_CONDITIONS))
    fig = Figure(figsize=(width, 9.0), layout="constrained")
    axes = fig.subplots(len(METRICS), len(PANEL_CONDITIONS), squeeze=False, sharex=True)
    for row, metric in enumerate(METRICS):
        for col, cond in enumerate(PANEL_CONDITIONS):
            ax = axes[row, col]
            _panel(ax, results, metric, cond, reading, subset, kinds, len(labels))
            if row == 0:
                ax.set_title(cond)
            if col == 0:
                ax.set_ylabel(METRIC_UNITS[metric][1])
    for ax in axes[-1]:
        tilt = len(labels) > 3
        ax.set_xticks(np.arange(1, len(labels) + 1), labels, rotation=45 if tilt else 0,
                      ha="right" if tilt else "center", rotation_mode="anchor", fontsize=8)
    fig.suptitle(title or f"fault benchmark: {', '.join(kinds)} commands, {reading} reading, {subset} cases")
    return fig


def _panel(ax, results, metric, cond, reading, subset, kinds, n_boxes):
    ax.set_xlim(0.4, n_boxes + 0.6)
    ax.grid(axis="y", lw=0.4, alpha=0.5)
    if not _defined(results, metric, cond, kinds):
        ax.text(0.5, 0.5, "n/a", transform=ax.transAxes, ha="center", va="center", color="0.4", fontsize=12)
        ax.set_yticks([])
        return
    data, positions, styles, empty = [], [], [], []
    for i, result in enumerate(results.values()):
        for j, k in enumerate(kinds):
            values = panel_values(result, metric, cond, reading, subset, k)
            slot = 1 + i * len(kinds) + j
            if values.size:
                data.append(values)
                positions.append(slot)
                styles.append((_TAB10[i % len(_TAB10)], k == "unadapted"))
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
