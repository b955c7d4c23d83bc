"""Plots of mill-model predictions: feed and product PSDs, and the Fig. 14 time series.

Figures are built with :class:`matplotlib.figure.Figure` (Agg canvas, no
pyplot state), so they can be rendered to bytes before anything is written.
"""

from __future__ import annotations

import io
from typing import Any

import numpy as np

__all__ = ["plot_psds", "plot_timeseries", "png_bytes", "prediction_figures"]


def _figure(width_in: float = 6.4, height_in: float = 4.2) -> Any:
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width_in, height_in))
    fig.subplots_adjust(left=0.12, right=0.88, bottom=0.13, top=0.91)
    return fig


def style_psd_axes(ax: Any, title: str) -> None:
    """Log size axis, cumulative % passing 0-100, grid, legend; ``title`` drawn as plain text (user text)."""
    ax.set_xscale("log")
    ax.set_xlabel("size (mm)")
    ax.set_ylabel("cumulative passing (%)")
    ax.set_ylim(0, 100)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(loc="upper left")
    ax.set_title(title, parse_math=False)  # no mathtext: a '$' in a title is text


def _shade_classes(ax: Any, edges_mm: np.ndarray, mask: np.ndarray | None, label: str, color: str) -> None:
    """Shade the size classes flagged in ``mask`` (contiguous runs as one span, one legend entry)."""
    if mask is None or not np.any(mask):
        return
    m = np.asarray(mask, dtype=bool)
    starts = np.flatnonzero(m & ~np.r_[False, m[:-1]])
    ends = np.flatnonzero(m & ~np.r_[m[1:], False])
    for k, (i, j) in enumerate(zip(starts, ends, strict=True)):
        ax.axvspan(edges_mm[i], edges_mm[j + 1], color=color, alpha=0.5, lw=0, zorder=0,
                   label=label if k == 0 else None)


def plot_psds(result: Any, ax: Any = None, title: str = "") -> Any:
    """Feed and product cumulative % passing against size (log axis).

    Parameters
    ----------
    result : msmill.model.MillResult
        A prediction.
    ax : matplotlib Axes, optional
        Draw there; a new figure otherwise.
    title : str, optional
        Axes title.

    Returns
    -------
    matplotlib Axes
    """
    if ax is None:
        ax = _figure().add_subplot()
    for psd, label, style in ((result.feed_psd, f"feed (F80 {result.f80_mm:.3g} mm)", "--"),
                              (result.product_psd, f"product (P80 {result.p80_mm:.3g} mm)", "-")):
        x = np.concatenate([[psd.grid.edges_mm[0]], psd.sizes_mm])
        y = np.concatenate([[0.0], psd.passing_pct])
        ax.plot(x, y, style, marker=".", label=label)
    _shade_classes(ax, result.product_psd.grid.edges_mm, getattr(result, "extrapolated_classes", None),
                   "stage statistics extrapolated in size", "0.85")
    _shade_classes(ax, result.product_psd.grid.edges_mm, getattr(result, "thin_data_classes", None),
                   "stage statistics from thin data", "#f4d9a6")
    band = getattr(result, "psd_band", None)
    if band is not None:
        lo, hi = result.p80_band_mm
        ax.fill_between(band.index.to_numpy(), band["product_passing_pct_p05"], band["product_passing_pct_p95"],
                        alpha=0.3, label=f"product 5-95 % band (P80 {lo:.3g}-{hi:.3g} mm, "
                                         f"{result.band_samples} samples)")
    style_psd_axes(ax, title or f"reduction ratio F80/P80 = {result.reduction_ratio:.2f}")
    return ax


def plot_timeseries(result: Any, ax: Any = None, title: str = "") -> Any:
    """Feed rate, product rate and mass held in the mill against time (paper Fig. 14).

    Rates (t/h) on the left axis, hold-up (kg) on the right axis; the time to
    steady state is marked.
    """
    if ax is None:
        ax = _figure().add_subplot()
    ts = result.timeseries
    ax.plot(ts["time_s"], ts["feed_tph"], "--", label="feed (t/h)")
    ax.plot(ts["time_s"], ts["product_tph"], label="product (t/h)")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("mass flow (t/h)")
    ax.set_ylim(bottom=0)
    ax2 = ax.twinx()
    ax2.plot(ts["time_s"], ts["holdup_t"] * 1000.0, color="tab:green", label="held in mill (kg)")
    ax2.set_ylabel("held in mill (kg)")
    ax2.set_ylim(bottom=0)
    if np.isfinite(result.time_to_steady_state_s):
        ax.axvline(result.time_to_steady_state_s, color="grey", lw=0.8, ls=":",
                   label=f"steady state ({result.time_to_steady_state_s:.2f} s)")
    lines = ax.get_legend_handles_labels()
    lines2 = ax2.get_legend_handles_labels()
    ax.legend(lines[0] + lines2[0], lines[1] + lines2[1], loc="lower right")
    ax.set_title(title or "mass in and out of the mill from start-up", parse_math=False)
    return ax


def prediction_figures(result: Any, title: str = "") -> dict[str, Any]:
    """Both figures of a prediction: ``{"psd": Figure, "timeseries": Figure}``."""
    out = {}
    for key, fn in (("psd", plot_psds), ("timeseries", plot_timeseries)):
        fig = _figure()
        fn(result, ax=fig.add_subplot(), title=title)
        out[key] = fig
    return out


def png_bytes(fig: Any, dpi: int = 120) -> bytes:
    """Render a figure to PNG bytes (Agg)."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    return buf.getvalue()
