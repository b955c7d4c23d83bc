"""Figures of the training campaign's results page (``msmill campaign report``, ``docs/campaign-results.md``).

Each function writes one PNG: the learning curve, the design points, the DEM cost per run, the
surrogate's trends and the capacity map. The numbers come from :mod:`msmill.pipeline.results`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from msmill.pipeline.results import PAPER_KL, PAPER_RUNS, QUANTITIES, sweep
from msmill.stageparams import DESIGN_INPUTS

__all__ = ["LABELS", "plot_capacity", "plot_cost", "plot_design", "plot_learning", "plot_trends"]

#: axis labels of the design inputs
LABELS = {"size_mm": "rock size (mm)", "feed_tph": "feed rate (t/h)", "speed_rpm": "upper-stage speed (rpm)",
          "gate_deg": "gate angle (deg)"}


def plot_learning(curve: Any, path: Path) -> None:
    """LOO mean KL (nats) against the number of runs (``learning_curve``), the paper's figure, the floor."""
    import matplotlib.pyplot as plt

    from msmill.surrogate.accuracy import FINE_SIZE_MM
    from msmill.surrogate.targets import N_LEVELS

    fig, ax = plt.subplots(figsize=(6, 4))
    ax.plot(curve["runs"], curve["kl_velocity"], "o-", label="ours: LOO mean KL, velocities")
    ax.plot(curve["runs"], curve["kl_count"], "s--", label="ours: LOO mean KL, secondary count")
    if "kl_velocity_fine" in curve and curve["kl_velocity_fine"].notna().any():
        ax.plot(curve["runs"], curve["kl_velocity_fine"], "^-.",
                label=f"ours: LOO mean KL, velocities, runs below {FINE_SIZE_MM:g} mm")
    ax.axhline(curve["representation_kl"].iloc[-1], color="grey", ls=":",
               label=f"{N_LEVELS}-quantile representation floor (velocities)")
    ax.plot([PAPER_RUNS], [PAPER_KL], "r*", ms=14, label=f"paper: {PAPER_KL} after {PAPER_RUNS} runs")
    ax.set(xscale="log", yscale="log", xlabel="DEM runs in the training set", ylabel="mean KL divergence")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_design(runs: Any, path: Path) -> None:
    """Pair plot of the design points run (``run_table``)."""
    import matplotlib.pyplot as plt
    from pandas.plotting import scatter_matrix

    axes = scatter_matrix(runs[list(DESIGN_INPUTS)], figsize=(7, 7), diagonal="hist", s=30, alpha=0.8)
    for ax in axes.ravel():
        ax.xaxis.label.set_size(8)
        ax.yaxis.label.set_size(8)
    plt.suptitle(f"{len(runs)} steady slice runs")
    plt.savefig(path, dpi=100)
    plt.close("all")


def plot_cost(runs: Any, path: Path) -> tuple[float, float] | None:
    """Wall time per run against size (log-log, power-law fit) and feed rate.

    Returns
    -------
    (exponent, prefactor) or None
        ``wall_s ~ prefactor * size_mm ** exponent``; None with fewer than 3 runs or one size.
    """
    import matplotlib.pyplot as plt

    r = runs.dropna(subset=["wall_s"])
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(9, 3.6))
    sc = a1.scatter(r["size_mm"], r["wall_s"] / 60, c=r["feed_tph"], cmap="viridis")
    fit = None
    if len(r) >= 3 and r["size_mm"].nunique() >= 2:
        k, c = np.polyfit(np.log(r["size_mm"]), np.log(r["wall_s"]), 1)
        xs = np.geomspace(r["size_mm"].min(), r["size_mm"].max(), 20)
        a1.plot(xs, np.exp(c) * xs ** k / 60, "k--", label=f"wall ~ size^{k:.2f}")
        a1.legend(fontsize=8)
        fit = (float(k), float(np.exp(c)))
    a1.set(xscale="log", yscale="log", xlabel=LABELS["size_mm"], ylabel="DEM wall time per run (min)")
    fig.colorbar(sc, ax=a1, label="feed (t/h)")
    sc2 = a2.scatter(r["feed_tph"], r["wall_s"] / 60, c=np.log(r["size_mm"]), cmap="plasma")
    a2.set(yscale="log", xlabel=LABELS["feed_tph"], ylabel="DEM wall time per run (min)")
    fig.colorbar(sc2, ax=a2, label="ln size (mm)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return fit


def plot_trends(provider: Any, at: dict[str, float], path: Path) -> None:
    """4 x 4 grid of the surrogate's posterior means: rows = inputs, columns = quantities, one line per stage."""
    import matplotlib.pyplot as plt

    d = provider.surrogate.domain_
    fig, axes = plt.subplots(4, 4, figsize=(13, 11), sharey="col")
    for i, var in enumerate(DESIGN_INPUTS):
        lo, hi = d[i]
        xs = np.geomspace(lo, hi, 15) if var == "size_mm" else np.linspace(lo, hi, 9)
        mean, _ = sweep(provider, var, xs, at)
        for j, q in enumerate(QUANTITIES):
            ax = axes[i, j]
            for s in range(mean[q].shape[0]):
                ax.plot(xs, mean[q][s], label=f"stage {s + 1}")
            ax.set_xlabel(LABELS[var], fontsize=8)
            if i == 0:
                ax.set_title(q.replace("_", " "))
            if var == "size_mm":
                ax.set_xscale("log")
    axes[0, 0].legend(fontsize=7)
    fig.suptitle("surrogate posterior mean, other inputs at the trained domain's centre: " +
                 ", ".join(f"{LABELS[k].split(' (')[0]} {v:.4g}" for k, v in at.items()), fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def _overlay(ax: Any, pts: list, x: str, y: str) -> None:
    """The envelope's runs projected on (x, y): steady as circles, choked as red crosses (feed) and dots (passed)."""
    st = [p for p in pts if p.outcome == "steady"]
    ch = [p for p in pts if p.outcome == "choked"]
    ax.scatter([getattr(p, x) for p in st], [getattr(p, y) for p in st], s=14, facecolors="none",
               edgecolors="k", lw=0.7, label=f"steady ({len(st)})")
    ax.scatter([getattr(p, x) for p in ch], [getattr(p, y) for p in ch], s=60, marker="x", c="r", lw=2,
               label=f"choked ({len(ch)}): feed")
    if y == "feed_tph":
        ax.scatter([getattr(p, x) for p in ch], [p.throughput_tph for p in ch], s=25, c="r", marker="v",
                   label="choked: throughput passed")


def _capacity_map(fig: Any, ax: Any, model: Any, pts: list, mid_size_mm: float) -> None:
    """Median capacity (t/h) over gate x speed at ``mid_size_mm``, hatched above the largest feed run."""
    hi_feed = model.domain["feed_tph"][1]
    g, v = np.meshgrid(np.linspace(0, 80, 81), np.linspace(1200, 1900, 71))
    cap = np.exp(model.log_capacity(mid_size_mm, v.ravel(), g.ravel())[0]).reshape(g.shape)
    levels = np.arange(0, 10 * np.ceil(min(cap.max(), 3 * hi_feed) / 10) + 10, 10)
    cs = ax.contourf(g, v, np.minimum(cap, levels[-1]), levels=levels, cmap="viridis")
    ax.contourf(g, v, cap, levels=[hi_feed, np.inf], colors="none", hatches=["//"])
    ax.contour(g, v, cap, levels=[hi_feed], colors="w", linewidths=1)
    fig.colorbar(cs, ax=ax, label="capacity (t/h) at P(steady) = 1/2")
    _overlay(ax, pts, "gate_deg", "speed_rpm")
    ax.set(xlabel=LABELS["gate_deg"], ylabel=LABELS["speed_rpm"],
           title=f"capacity at {mid_size_mm:.3g} mm (hatched: above the largest\nfeed run, {hi_feed:.0f} t/h)")


def plot_capacity(model: Any, pts: list, mid_size_mm: float, path: Path) -> None:
    """Capacity over gate x speed at mid size; P(steady) over gate x feed and size x feed; runs overlaid."""
    import matplotlib.pyplot as plt

    hi_feed = model.domain["feed_tph"][1]
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.6))
    _capacity_map(fig, axes[0], model, pts, mid_size_mm)
    speed = 1550.0
    for ax, (xname, xs), fixed in ((axes[1], ("gate_deg", np.linspace(0, 80, 81)), f"{mid_size_mm:.3g} mm"),
                                   (axes[2], ("size_mm", np.geomspace(5, 32, 60)), "gate 10 deg")):
        x, f = np.meshgrid(xs, np.linspace(2, 100, 99))
        size = x if xname == "size_mm" else mid_size_mm
        gate = x if xname == "gate_deg" else 10.0
        pr = model.probability_steady(np.broadcast_to(size, x.shape).ravel(), f.ravel(), speed,
                                      np.broadcast_to(gate, x.shape).ravel()).reshape(x.shape)
        pc = ax.pcolormesh(x, f, pr, cmap="RdYlGn", vmin=0, vmax=1, shading="auto")
        c = ax.contour(x, f, pr, levels=[0.1, 0.5, 0.9], colors="k", linestyles=["--", "-", "--"], linewidths=1)
        ax.clabel(c, fmt="%.1f", fontsize=7)
        _overlay(ax, pts, xname, "feed_tph")
        ax.axhline(hi_feed, color="grey", lw=0.8, ls=":")
        ax.set(xlabel=LABELS[xname], ylabel=LABELS["feed_tph"], xscale="log" if xname == "size_mm" else "linear",
               title=f"P(steady) at {fixed}, {speed:g} rpm")
        if xname == "size_mm":
            ax.set_xticks([6, 10, 15, 20, 30], labels=["6", "10", "15", "20", "30"])
    fig.colorbar(pc, ax=axes[2], label="probability of steady flow")
    axes[1].legend(fontsize=7, loc="upper left")
    fig.suptitle("runs at all sizes, speeds and gates projected onto each panel", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
