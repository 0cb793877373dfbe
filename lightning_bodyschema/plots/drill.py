"""The fault drill's figure: posture error and tension readings over time, the fault and its detection marked."""
from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import numpy as np  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402

from .arm import save_figure_atomic  # noqa: E402

MOST_TENSIONS = 8  # the muscles whose tension changed most are drawn (a 50-muscle arm would be a blur)


def plot_drill(result, settings, muscles, summary: dict, path: str) -> None:
    """Two panels over time: |q - q_ref| [rad] (log scale) and the tension readings [N] of the muscles that changed
    most; vertical lines at the fault and at the detection; saved atomically to ``path`` (PNG)."""
    fig = Figure(figsize=(8, 6), constrained_layout=True)
    ax_q, ax_f = fig.subplots(2, 1, sharex=True)
    ax_q.semilogy(result.t_s, np.maximum(result.error_rad, 1e-6), color="k", lw=1)
    ax_q.set_ylabel("posture error |q - q_ref| [rad]")
    f = result.f_n if np.isfinite(result.f_n).any() else result.l_m - result.l_cmd_m
    change = np.nanmax(np.abs(f - f[:1]), axis=0)
    for m in np.argsort(-np.nan_to_num(change))[:MOST_TENSIONS]:
        ax_f.plot(result.t_s, f[:, m], lw=1, label=muscles[m])
    ax_f.set_ylabel("tension reading [N]" if np.isfinite(result.f_n).any() else "encoder - command [m]")
    ax_f.set_xlabel("time [s]")
    ax_f.legend(fontsize=7, ncol=2, loc="upper right")
    for ax in (ax_q, ax_f):
        ax.axvline(settings.at_s, color="tab:red", ls="--", lw=1, label="fault")
        if np.isfinite(result.detected_s):
            ax.axvline(result.detected_s, color="tab:green", ls="--", lw=1, label="detected")
    title = f"fault {summary['fault']}; "
    title += (f"detected after {1e3 * summary['detection_delay_s']:.0f} ms as {summary['identified']}"
              if summary["detection_delay_s"] is not None else "not detected")
    ax_q.set_title(title, fontsize=9)
    ax_q.legend(fontsize=7, loc="upper left")
    save_figure_atomic(fig, path)
