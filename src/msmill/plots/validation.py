"""Plots of validation, calibration, sweeps and optimisation (paper Figs. 11-13 and more).

Figures are :class:`matplotlib.figure.Figure` objects (Agg, no pyplot state);
render them with :func:`msmill.plots.model.png_bytes`.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from msmill.plots.model import _figure, style_psd_axes

__all__ = ["approach_plot", "ks_swarm", "overlay", "pareto_plot", "sweep_plot"]


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


def _label(value: Any) -> str:
    """A legend value: a number in ``:g`` form, a category (a rotation sense) as it is."""
    return value if isinstance(value, str) else f"{value:g}"


def sweep_plot(table: Any, x: str, y: str = "p80_mm", hue: str | None = None, title: str = "") -> Any:
    """One output of a sweep against one operating variable (lines per value of ``hue``, numeric or a category)."""
    fig = _figure()
    ax = fig.add_subplot()
    groups = [(None, table)] if hue is None else list(table.groupby(hue, sort=True))
    for key, g in groups:
        g = g.sort_values(x)
        ax.plot(g[x], g[y], marker="o", label=None if key is None else f"{hue} = {_label(key)}")
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


def approach_plot(rows: list, reps: list[dict], smooth_s: float = 0.25) -> Any:
    """Model against the DEM replicas while the mill fills, one column per size with replicas.

    Top: hold-up over its steady value (DEM: each replica in grey and the
    ensemble mean in black, over the ensemble's mean after 4 s; model: over
    its steady solve). Bottom: product rate over the feed rate (DEM: the
    ensemble's, a ``smooth_s`` running mean). Onsets are marked.

    Parameters
    ----------
    rows : list of :class:`msmill.model.transport_check.Row`
        Rows of :func:`~msmill.model.transport_check.compare` with their replicas attached.
    reps : list of dict
        The replica runs (:func:`~msmill.model.transport_check.load_replicas`).
    smooth_s : float
        Running-mean length of the DEM product rate (s).
    """
    from msmill.errors import MsmillInputError
    from msmill.model.transport_check import replicas_on_grid

    sel = [r for r in rows if r.n_replicas and r.model_series is not None]
    if not sel:
        raise MsmillInputError("replicas", len(reps), "replicas of at least one run's point to plot against")
    fig = _figure(3.2 * len(sel), 5.6)
    axs = fig.subplots(2, len(sel), sharex=True, squeeze=False)
    for j, row in enumerate(sel):
        mine = [r for r in reps if abs(float(r["size_mm"]) - row.size_mm) < 1e-6 * row.size_mm]
        t, held, out, feed = replicas_on_grid(mine)
        ref = held.mean(axis=0)[t >= 4.0].mean() if t[-1] > 4.5 else held.mean(axis=0)[-50:].mean()
        tm, hm, pm = row.model_series
        ax = axs[0, j]
        ax.plot(t, held.T / ref, color="0.82", lw=0.5)
        ax.plot(t, held.mean(axis=0) / ref, "k", lw=1.2, label=f"DEM, {len(mine)} run{'s' * (len(mine) != 1)}")
        ax.plot(tm, hm, "C3", lw=1.2, label="model")
        for v, c in ((row.tss_dem_rep_s, "k"), (row.tss_model_today_s, "C3")):
            if np.isfinite(v):
                ax.axvline(v, color=c, ls=":", lw=1)
        ax.set_title(f"{row.size_mm:g} mm")
        ax.set_ylim(0, 1.3)
        ax = axs[1, j]
        k = max(1, round(smooth_s / (t[1] - t[0])))
        rate = np.gradient(out.mean(axis=0), t) / feed.mean()
        ax.plot(t[k // 2: k // 2 + len(rate) - k + 1], np.convolve(rate, np.ones(k) / k, mode="valid"), "k", lw=1.2)
        ax.plot(tm, pm, "C3", lw=1.2)
        ax.set_ylim(0, 1.4)
        ax.set_xlim(0, max(6.0, float(t[-1])))
        ax.set_xlabel("time (s)")
    axs[0, 0].set_ylabel("hold-up / steady")
    axs[1, 0].set_ylabel(f"product / feed ({smooth_s:g} s mean)")
    axs[0, 0].legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    return fig
