"""Plots of validation, calibration, sweeps and optimisation (paper Figs. 11-13 and more).

Figures are :class:`matplotlib.figure.Figure` objects (Agg, no pyplot state);
render them with :func:`msmill.plots.model.png_bytes`.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from msmill.plots.model import _figure, style_psd_axes

__all__ = ["ks_swarm", "overlay", "pareto_plot", "sweep_plot"]


def _beeswarm_offsets(values: np.ndarray, width: float = 0.35, bin_frac: float = 0.02) -> np.ndarray:
    """Horizontal offsets of a simple beeswarm: points in the same value bin spread left and right."""
    v = np.asarray(values, dtype=float)
    span = max(float(np.ptp(v)), 1e-9)
    bins = np.floor((v - v.min()) / (bin_frac * span + 1e-12)).astype(int)
    off = np.zeros(v.size)
    for b in np.unique(bins):
        idx = np.flatnonzero(bins == b)
        k = np.arange(idx.size)
        off[idx] = ((k + 1) // 2) * np.where(k % 2 == 0, 1, -1) * 0.06
    return np.clip(off, -width, width)


def ks_swarm(table: Any, title: str = "") -> Any:
    """Swarm plot of K-S by ore (paper Fig. 13); experiments outside the design space hollow."""
    fig = _figure()
    ax = fig.add_subplot()
    ores = list(dict.fromkeys(table["ore"]))
    for i, ore in enumerate(ores):
        g = table[table["ore"] == ore]
        ks = g["ks"].to_numpy()
        x = i + _beeswarm_offsets(ks)
        out = g["outside_design_space"].to_numpy(dtype=bool)
        ax.scatter(x[~out], ks[~out], s=28, color=f"C{i}", label=f"{ore} (n={len(g)})")
        if out.any():
            ax.scatter(x[out], ks[out], s=28, facecolors="none", edgecolors=f"C{i}",
                       label=f"{ore}: outside design space")
        ax.hlines(np.median(ks), i - 0.3, i + 0.3, colors="k", lw=1)
    ax.set_xticks(range(len(ores)), ores)
    ax.set_xlim(-0.6, len(ores) - 0.4)
    ax.set_ylim(bottom=0)
    ax.set_ylabel("Kolmogorov-Smirnov statistic")
    ax.grid(True, axis="y", alpha=0.3)
    ax.legend(loc="upper left", fontsize=8)
    ax.set_title(title or "K-S between measured and predicted products (line: median)")
    return fig


def _curve(psd: Any) -> tuple[np.ndarray, np.ndarray]:
    return (np.concatenate([[psd.grid.edges_mm[0]], psd.sizes_mm]),
            np.concatenate([[0.0], psd.passing_pct]))


def overlay(measured: Any, predicted: Any, title: str, feed: Any = None, band: Any = None) -> Any:
    """Measured against predicted product passing (paper Figs. 11-12); optional feed and band.

    ``band`` is ``(sizes_mm, low_pct, high_pct)``.
    """
    fig = _figure()
    ax = fig.add_subplot()
    if feed is not None:
        ax.plot(*_curve(feed), ":", color="grey", label="feed")
    if band is not None:
        ax.fill_between(band[0], band[1], band[2], color="C1", alpha=0.25, label="prediction band")
    ax.plot(*_curve(predicted), "-", color="C1", label="predicted")
    x, y = _curve(measured)
    ax.plot(x[1:], y[1:], "o", ms=4, color="C0", label="measured")
    style_psd_axes(ax, title)
    return fig


def sweep_plot(table: Any, x: str, y: str = "p80_mm", hue: str | None = None, title: str = "") -> Any:
    """One output of a sweep against one operating variable (lines per value of ``hue``)."""
    fig = _figure()
    ax = fig.add_subplot()
    groups = [(None, table)] if hue is None else list(table.groupby(hue, sort=True))
    for key, g in groups:
        g = g.sort_values(x)
        ax.plot(g[x], g[y], marker="o", label=None if key is None else f"{hue} = {key:g}")
    ax.set_xlabel(x)
    ax.set_ylabel(y)
    ax.grid(True, alpha=0.3)
    if hue is not None:
        ax.legend(fontsize=8)
    ax.set_title(title or f"{y} against {x}")
    return fig


def pareto_plot(table: Any, front: Any, best: Any = None, target_p80_mm: float | None = None,
                energy: str = "specific_energy_kwh_t") -> Any:
    """P80 against specific energy of all candidates, the Pareto front and the chosen point."""
    fig = _figure()
    ax = fig.add_subplot()
    ax.scatter(table[energy], table["p80_mm"], s=12, color="0.6", label="candidates")
    f = front.sort_values(energy)
    ax.plot(f[energy], f["p80_mm"], "-o", ms=4, color="C3", label="Pareto front")
    if target_p80_mm is not None:
        ax.axhline(target_p80_mm, ls="--", color="k", lw=0.8, label=f"target P80 {target_p80_mm:g} mm")
    if best is not None:
        ax.scatter([best[energy]], [best["p80_mm"]], s=90, marker="*", color="C2", zorder=5, label="chosen")
    ax.set_xlabel(energy)
    ax.set_ylabel("P80 (mm)")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title("P80 against specific energy")
    return fig
