"""Plots of the surrogate's accuracy: leave-one-out predictions against the DEM values."""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["loo_figure"]

_PANELS = (("streams (fraction)", ("kickback", "refeed", "pass_through")),
           ("primary hit probability", ("hit_probability",)),
           ("mean impact velocity (m/s)", ("primary_velocity_mean_m_s", "secondary_velocity_mean_m_s")),
           ("secondary impacts per primary", ("secondary_lambda",)))


def loo_figure(report: Any, title: str = "") -> Any:
    """Predicted (leave-one-out) against DEM values, one panel per kind of quantity.

    Parameters
    ----------
    report : msmill.surrogate.accuracy.LooReport
        The scores.
    title : str, optional
        Figure title.

    Returns
    -------
    matplotlib Figure
    """
    from matplotlib.figure import Figure

    fig = Figure(figsize=(9.0, 7.5))
    pairs = report.pairs
    for k, (label, quantities) in enumerate(_PANELS):
        ax = fig.add_subplot(2, 2, k + 1)
        lo, hi = np.inf, -np.inf
        for q in quantities:
            d = pairs[pairs["quantity"] == q]
            ax.scatter(d["dem"], d["predicted"], s=14, label=q.replace("_m_s", "").replace("_", " "))
            lo = min(lo, d["dem"].min(), d["predicted"].min())
            hi = max(hi, d["dem"].max(), d["predicted"].max())
        pad = 0.05 * (hi - lo if hi > lo else 1.0)
        ax.plot([lo - pad, hi + pad], [lo - pad, hi + pad], "k-", lw=0.8)
        ax.set_xlabel(f"DEM: {label}")
        ax.set_ylabel("surrogate (LOO)")
        ax.grid(True, alpha=0.3)
        if len(quantities) > 1:
            ax.legend(fontsize=7, loc="upper left")
    s = report.summary()
    fig.suptitle(title or f"{report.method}, {s['n_runs']} runs: mean KL velocity {s['mean_kl_velocity']:.3g}, "
                          f"count {s['mean_kl_count']:.3g}")
    fig.subplots_adjust(left=0.09, right=0.97, bottom=0.08, top=0.92, wspace=0.28, hspace=0.3)
    return fig
