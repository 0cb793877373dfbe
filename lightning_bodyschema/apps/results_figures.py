"""Figures of the paper reproduction (``tools/reproduce_paper.py``): the fault-benchmark box plots and the
inference-time bars, written under ``docs/`` beside RESULTS.md."""
from __future__ import annotations

import os

import numpy as np

TIMING_FORMATS = {"unadapted": "%.3f", "adapted": "%.1f", "oracle": "%.3f"}  # the RESULTS.md table's precision


def timing_figure(timings: dict, oracle_s: float | None = None):
    """Bars of milliseconds per case with and without adaptation per schema, and the physics oracle's, labelled
    with the precision of the RESULTS.md table."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.6, 3.6))
    names = list(timings)
    width = 0.38
    for k, (kind, color) in enumerate((("unadapted", "tab:gray"), ("adapted", "tab:blue"))):
        values = [1e3 * timings[n][kind] for n in names]
        bars = ax.bar(np.arange(len(names)) + (k - 0.5) * width, values, width, label=f"{kind} (ours)", color=color)
        ax.bar_label(bars, fmt=TIMING_FORMATS[kind], fontsize=7)
    ticks = list(names)
    if oracle_s is not None:
        bars = ax.bar([len(names)], [1e3 * oracle_s], width, color="k", label="physics oracle (exact model)")
        ax.bar_label(bars, fmt=TIMING_FORMATS["oracle"], fontsize=7)
        ticks.append("oracle")
    ax.axhline(700, color="tab:red", ls="--", lw=1, label="paper, adapted (0.7 s)")
    ax.set_xticks(np.arange(len(ticks)), ticks)
    ax.set_yscale("log")
    ax.set_xlabel("schema (one BOTH case, CPU, one thread)")
    ax.set_ylabel("ms per case (median)")
    ax.set_title("Inference time with and without adaptation")
    ax.legend(fontsize=7)
    fig.tight_layout()
    return fig


def write_figures(out: str, results: dict, binding: dict, timings: dict, oracle_s: float):
    """docs/paper_boxplots.png (phys reading, feasible cases: what the claims use), paper_boxplots_paper_reading.png
    (the paper's definitions, all cases), binding_boxplots.png (binding protocol) and paper_timing.png; each box
    plot has the unadapted command and the physics oracle as reference boxes."""
    from ..plots.arm import save_figure_atomic
    from ..plots.boxplots import fault_boxplots

    os.makedirs(os.path.join(out, "docs"), exist_ok=True)
    for name, by_name, reading, subset, what in (
            ("paper_boxplots", results, "phys", "feasible", "paper protocol"),
            ("paper_boxplots_paper_reading", results, "paper", "all", "paper protocol, the paper's metric definitions"),
            ("binding_boxplots", binding, "phys", "all", "binding protocol (every case feasible, every fault binding)")):
        reference = by_name.get("Diff", next(iter(by_name.values())))
        fig = fault_boxplots(by_name, reading=reading, subset=subset,
                             references={"unadapted (Diff)": (reference, "unadapted"), "oracle": (reference, "oracle")},
                             title=f"Fault benchmark, {what}: adapted commands, {reading} reading, {subset} cases")
        save_figure_atomic(fig, os.path.join(out, "docs", f"{name}.png"))
    if timings:
        save_figure_atomic(timing_figure(timings, oracle_s), os.path.join(out, "docs", "paper_timing.png"))
