"""Predicted vs true healthy commands: one panel for motor lengths, one for tensions."""
from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402


def reconstruction_figure(l_true_m, l_pred_m, f_true_n, f_pred_n, title: str = ""):
    """Scatter of predicted against true (l_motor [mm], f [N]) with the identity line."""
    fig, axes = plt.subplots(1, 2, figsize=(8, 3.6))
    for ax, true, pred, label in ((axes[0], 1e3 * np.asarray(l_true_m), 1e3 * np.asarray(l_pred_m), "l_motor [mm]"),
                                  (axes[1], np.asarray(f_true_n), np.asarray(f_pred_n), "f [N]")):
        ax.scatter(true.ravel(), pred.ravel(), s=4, alpha=0.5)
        lo, hi = float(min(true.min(), pred.min())), float(max(true.max(), pred.max()))
        ax.plot([lo, hi], [lo, hi], "k--", lw=0.8)
        ax.set_xlabel(f"true {label}")
        ax.set_ylabel(f"predicted {label}")
    fig.suptitle(title)
    fig.tight_layout()
    return fig
