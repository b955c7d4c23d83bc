"""Plots of mill DEM runs: particles in the mill (paper Fig. 3) and per-stage impacts (Fig. 8)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

__all__ = ["plot_particles_in_mill", "plot_stage_impacts"]


def _plt() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_particles_in_mill(
    timeseries: pd.DataFrame,
    path: str | Path | None = None,
    steady_state_time_s: float | None = None,
    window_s: tuple[float, float] | None = None,
    ax: Any = None,
) -> Any:
    """Number of particles in the mill against time, with the steady-state onset and window marked.

    Parameters
    ----------
    timeseries : DataFrame
        ``time_s`` and ``n_particles`` columns (engine ``timeseries()``).
    path : path, optional
        Save the figure there (PNG).
    steady_state_time_s : float, optional
        Onset of steady state (s), drawn as a dashed line.
    window_s : (float, float), optional
        Measurement window (s), shaded.
    """
    plt = _plt()
    fig = None
    if ax is None:
        fig, ax = plt.subplots(figsize=(6, 3.5))
    ax.plot(timeseries["time_s"], timeseries["n_particles"], lw=1.2, color="C0")
    if steady_state_time_s is not None:
        ax.axvline(steady_state_time_s, ls="--", color="k", lw=1, label=f"steady from {steady_state_time_s:.2f} s")
    if window_s is not None:
        ax.axvspan(*window_s, color="C1", alpha=0.15, label="measurement window")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("particles in mill")
    ax.grid(alpha=0.3)
    if steady_state_time_s is not None or window_s is not None:
        ax.legend(loc="lower right", fontsize=8)
    if fig is not None and path is not None:
        fig.tight_layout()
        fig.savefig(path, dpi=120)
        plt.close(fig)
    return ax


def plot_stage_impacts(stats: Any, path: str | Path | None = None) -> Any:
    """Per stage: secondary-impact count histogram with its Poisson fit, and impact-velocity
    histograms (primary and secondary) with their Gaussian-mixture fits (paper Fig. 8).

    Parameters
    ----------
    stats : msmill.dem.mill.stats.MillStatistics
        Statistics with raw samples.
    path : path, optional
        Save the figure there (PNG).
    """
    from scipy import stats as sps

    plt = _plt()
    run = stats.run
    n = run.n_stages
    fig, axes = plt.subplots(n, 2, figsize=(9, 2.2 * n), squeeze=False)
    for i, st in enumerate(run.stages):
        smp = stats.samples.get(st.stage, {})
        a0, a1 = axes[i]
        cnt = np.asarray(smp.get("secondary_counts", []))
        if cnt.size:
            k = np.arange(0, max(int(cnt.max()), 1) + 2)
            emp = np.bincount(cnt.astype(int), minlength=k.size)[: k.size] / cnt.size
            a0.bar(k, emp, color="C0", alpha=0.6, label="DEM")
            a0.plot(k, sps.poisson.pmf(k, st.secondary_lambda), "o-", color="C3", ms=3,
                    label=f"Poisson λ={st.secondary_lambda:.2f}, KL={st.secondary_lambda_kl or 0:.3f}")
            sel = st.secondary_count_selection
            if sel is not None and sel.chosen != "poisson" and st.secondary_count is not None:
                a0.plot(k, st.secondary_count.pmf(int(k[-1])), "s-", color="C1", ms=3,
                        label=f"{sel.chosen.replace('_', ' ')}, KL={sel.kl:.3f}")
            a0.set_yscale("log")
            a0.legend(fontsize=7)
        a0.set_ylabel(f"stage {st.stage}\nprobability")
        for key, gm, kl, color, label in (
            ("primary_velocity_m_s", st.primary_velocity, st.primary_velocity_kl, "C2", "primary"),
            ("secondary_velocity_m_s", st.secondary_velocity, st.secondary_velocity_kl, "C0", "secondary"),
        ):
            v = np.asarray(smp.get(key, []))
            if v.size < 2:
                continue
            a1.hist(v, bins=40, density=True, color=color, alpha=0.4)
            x = np.linspace(v.min(), v.max(), 300)
            a1.plot(x, gm.pdf(x), color=color, lw=1.2,
                    label=f"{label}: K={gm.n_components}, KL={kl or 0:.3f}")
        if a1.get_legend_handles_labels()[0]:
            a1.legend(fontsize=7)
    axes[-1][0].set_xlabel("secondary impacts per primary impact")
    axes[-1][1].set_xlabel("relative normal impact velocity (m/s)")
    fig.tight_layout()
    if path is not None:
        fig.savefig(path, dpi=110)
        plt.close(fig)
    return fig


def plot_run(run: Any, out_dir: str | Path) -> list[Path]:
    """Write the plots of a mill DEM run (``msmill.dem.mill.run.MillRun``) into ``out_dir``.

    ``particles_in_mill.png`` (paper Fig. 3) and, when statistics exist,
    ``stage_impacts.png`` (paper Fig. 8). Returns the files written.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written = [out / "particles_in_mill.png"]
    plot_particles_in_mill(run.timeseries, written[0],
                           steady_state_time_s=run.steady_state_time_s, window_s=run.window_s)
    if run.stats is not None:
        written.append(out / "stage_impacts.png")
        plot_stage_impacts(run.stats, written[-1])
    return written
