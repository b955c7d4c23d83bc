"""Run a mill scene to steady state, record a measurement window, save and reload.

Procedure (documented in ``docs/mill-dem.md``):

1. The empty mill is fed from t = 0. The engine runs in chunks of
   ``chunk_s``; after every chunk :func:`msmill.dem.mill.stats.detect_steady_state`
   tests the number of particles in the mill (two consecutive windows of
   ``steady_window_s`` whose means differ by less than ``rel_tol`` and whose
   joint linear trend is below ``trend_tol``). The onset of steady state
   (start of the first passing pair of windows) is reported as
   ``steady_state_time_s``; the time it was detected is
   ``steady_state_detected_s``.
2. From the detection time the run continues for ``measure_s`` (the
   measurement window); snapshots every ``snapshot_every_s`` throughout.
3. The statistics (:func:`msmill.dem.mill.stats.compute_statistics`) use the
   measurement window only.

The time step is the engine's default rule with ``safety = 0.2`` of the Hertz
contact time at the highest expected impact speed. A larger safety (0.3) was
tried and rejected: rock hit by fast rotating flinger plates then left faster
than ``(1 + e)`` times the plate speed (energy gain, then run-away speeds).

If no steady state is found by ``max_time_s`` the last ``measure_s`` is used
as the window and ``steady_state_time_s`` is None (the run is flagged in its
provenance).
"""

from __future__ import annotations

import subprocess
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import tomli_w

from msmill._version import __version__
from msmill.dem.mill.checks import check_run_budget, check_run_inputs
from msmill.dem.mill.scene import MillScene, RockMaterial, build_scene
from msmill.dem.mill.stats import (
    MillStatistics,
    StatsSettings,
    compute_statistics,
    detect_steady_state,
    snapshots_frame,
)
from msmill.errors import MsmillInputError
from msmill.machine import Machine, OperatingPoint
from msmill.stageparams import DesignPoint

__all__ = ["MillRun", "RunSettings", "design_point", "load_raw", "run_mill", "save_run", "stats_from_dir"]


@dataclass(frozen=True)
class RunSettings:
    """Settings of a run to steady state plus measurement window (times in s)."""

    max_time_s: float = 4.0
    chunk_s: float = 0.1
    steady_window_s: float = 0.4
    rel_tol: float = 0.05
    trend_tol: float = 0.05
    measure_s: float = 0.5
    snapshot_every_s: float = 0.005
    max_overlap_fraction: float = 0.05
    safety: float = 0.2
    dt_s: float | None = None
    seed: int = 0


@dataclass
class MillRun:
    """A finished run: scene, raw tables, timing and statistics."""

    scene: MillScene
    settings: RunSettings
    events: pd.DataFrame
    removed: pd.DataFrame
    timeseries: pd.DataFrame
    snapshots: pd.DataFrame
    steady_state_time_s: float | None
    steady_state_detected_s: float | None
    window_s: tuple[float, float]
    wall_s: float
    stats: MillStatistics | None = None
    extra: dict[str, Any] = field(default_factory=dict)


def design_point(machine: Machine, op: OperatingPoint, size_mm: float) -> DesignPoint:
    """The :class:`DesignPoint` of a run."""
    return DesignPoint(size_mm=size_mm, feed_tph=op.feed_tph, speed_rpm=op.upper_speed_rpm, gate_deg=op.gate_deg,
                       stage_speeds_rpm=op.stage_speeds(machine.n_stages))


def git_commit() -> str | None:
    """Current git commit of the source tree, if available."""
    try:
        out = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True, timeout=10,
                             cwd=Path(__file__).parent)
        return out.stdout.strip() or None
    except (OSError, subprocess.SubprocessError):
        return None


def run_mill(
    machine: Machine,
    op: OperatingPoint,
    size_mm: float | None = None,
    feed_psd: tuple[Any, Any] | None = None,
    mode: str = "slice",
    rock: RockMaterial | None = None,
    ore: str | None = None,
    settings: RunSettings | None = None,
    stats_settings: StatsSettings | None = None,
    progress: Callable[[float, int, str], None] | None = None,
) -> MillRun:
    """Build the scene, run to steady state plus a measurement window, compute statistics.

    Parameters
    ----------
    machine, op, size_mm, feed_psd, mode, rock, ore
        See :func:`msmill.dem.mill.scene.build_scene`.
    settings : RunSettings, optional
    stats_settings : StatsSettings, optional
    progress : callable, optional
        Called after every chunk with ``(time_s, n_particles, phase)``, phase
        ``"transient"`` or ``"measure"``.
    """
    rs = settings or RunSettings()
    check_run_inputs(machine, rs, size_mm, feed_psd)  # before any work: times, sizes (dem/mill/checks.py)
    wall0 = time.perf_counter()
    commit0 = git_commit()  # the code the run starts from (HEAD may move while it runs)
    scene = build_scene(machine, op, size_mm=size_mm, feed_psd=feed_psd, mode=mode, rock=rock, ore=ore,
                        max_overlap_fraction=rs.max_overlap_fraction, seed=rs.seed)
    check_run_budget(scene, rs)  # step count and rocks fed within msmill.validate.LIMITS
    sim = scene.sim
    kw = {"dt_s": rs.dt_s, "max_relative_speed_m_s": scene.max_impact_speed_m_s, "safety": rs.safety,
          "snapshot_every_s": rs.snapshot_every_s, "progress": False}
    found = None

    def remaining(t_end: float) -> float:
        # time left, treating less than half a step as nothing (the engine runs whole steps)
        left = t_end - sim.time_s
        return left if left > 0.5 * (sim.dt_s or 0.0) + 1e-12 else 0.0

    while remaining(rs.max_time_s) > 0:
        sim.run(min(rs.chunk_s, remaining(rs.max_time_s)), **kw)
        ts = sim.timeseries()
        if progress:
            progress(sim.time_s, int(sim.n_particles), "transient")
        found = detect_steady_state(ts["time_s"].to_numpy(), ts["n_particles"].to_numpy(), rs.steady_window_s,
                                    rs.rel_tol, rs.trend_tol)
        if found is not None:
            break
    t_start = sim.time_s if found is not None else max(0.0, sim.time_s - rs.measure_s)
    if found is not None:
        t_stop = sim.time_s + rs.measure_s
        while remaining(t_stop) > 0:
            sim.run(min(rs.chunk_s, remaining(t_stop)), **kw)
            if progress:
                progress(sim.time_s, int(sim.n_particles), "measure")
    wall = time.perf_counter() - wall0
    snaps = snapshots_frame(sim.snapshots())
    snaps = snaps.drop_duplicates(subset=["time_s", "particle_id"]).reset_index(drop=True)
    snaps["snap"] = pd.factorize(snaps["time_s"], sort=True)[0]
    run = MillRun(
        scene=scene, settings=rs, events=sim.events(), removed=sim.removed(), timeseries=sim.timeseries(),
        snapshots=snaps, steady_state_time_s=found[0] if found else None,
        steady_state_detected_s=found[1] if found else None, window_s=(float(t_start), float(sim.time_s)),
        wall_s=wall,
    )
    run.extra["git_commit"] = commit0
    run.extra["dt_s"] = float(sim.dt_s)
    run.extra["n_particles_end"] = int(sim.n_particles)
    run.stats = _compute(run, stats_settings)
    return run


def _provenance(run: MillRun) -> dict[str, Any]:
    return {
        "generator": "msmill.dem.mill.run",
        "msmill_version": __version__,
        "git_commit": run.extra.get("git_commit", git_commit()),
        "date_utc": datetime.now(UTC).isoformat(timespec="seconds"),
        "machine": run.scene.machine.name,
        "scene": run.scene.info,
        "run_settings": asdict(run.settings),
        "dt_s": run.extra.get("dt_s"),
        "wall_s": run.wall_s,
        "steady_state_detected_s": run.steady_state_detected_s,
        "steady_state_reached": run.steady_state_time_s is not None,
        "end_time_s": run.window_s[1],
    }


def _compute(run: MillRun, stats_settings: StatsSettings | None) -> MillStatistics:
    sc = run.scene
    edges = None
    if sc.sizes_mm.size > 1:
        mids = np.sqrt(sc.sizes_mm[1:] * sc.sizes_mm[:-1]) / 2000
        edges = np.concatenate([[0.0], mids, [np.inf]])
    return compute_statistics(
        sc.machine, design_point(sc.machine, sc.op, sc.size_mm), run.events, run.removed, run.timeseries,
        run.snapshots, run.window_s, mode=sc.mode, rock_density_kg_m3=sc.rock.density_kg_m3,
        steady_state_time_s=run.steady_state_time_s, settings=stats_settings, size_edges_m=edges,
        provenance=_provenance(run),
    )


# --------------------------------------------------------------------------- saving
def save_run(run: MillRun, out_dir: str | Path, vtk: bool = False) -> Path:
    """Write raw tables (Parquet), statistics (JSON), machine and run settings (TOML).

    Files: ``events.parquet``, ``removed.parquet``, ``timeseries.parquet``,
    ``snapshots.parquet``, ``statistics.json``, ``machine.toml``, ``run.toml``
    and optionally ``final.vtu``. Plots are an edge concern:
    :func:`msmill.plots.dem.plot_run`.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    run.events.to_parquet(out / "events.parquet", index=False)
    run.removed.to_parquet(out / "removed.parquet", index=False)
    run.timeseries.to_parquet(out / "timeseries.parquet", index=False)
    run.snapshots.to_parquet(out / "snapshots.parquet", index=False)
    run.scene.machine.to_toml(out / "machine.toml")
    sc = run.scene
    settings = {
        "design": {"size_mm": sc.size_mm, "feed_tph": sc.op.feed_tph, "gate_deg": sc.op.gate_deg,
                   "stage_speeds_rpm": sc.op.stage_speeds(sc.machine.n_stages),
                   "speed_rpm": sc.op.upper_speed_rpm, "mode": sc.mode},
        "feed": {"sizes_mm": sc.sizes_mm.tolist(), "mass_fractions": sc.mass_fractions.tolist()},
        "rock": asdict(sc.rock),
        "run": {k: v for k, v in asdict(run.settings).items() if v is not None},
        "result": {"steady_state_time_s": run.steady_state_time_s if run.steady_state_time_s is not None else -1.0,
                   "steady_state_detected_s": run.steady_state_detected_s
                   if run.steady_state_detected_s is not None else -1.0,
                   "window_start_s": run.window_s[0], "window_end_s": run.window_s[1], "wall_s": run.wall_s,
                   "dt_s": run.extra.get("dt_s", 0.0)},
    }
    (out / "run.toml").write_text(tomli_w.dumps(_toml_safe(settings)), encoding="utf-8")
    if run.stats is not None:
        run.stats.run.to_json(out / "statistics.json")
    if vtk and hasattr(run.scene.sim, "write_vtu"):
        run.scene.sim.write_vtu(out / "final.vtu")
    return out


def _toml_safe(d: Any) -> Any:
    if isinstance(d, dict):
        return {str(k): _toml_safe(v) for k, v in d.items() if v is not None}
    if isinstance(d, list | tuple):
        return [_toml_safe(v) for v in d]
    if isinstance(d, np.generic):
        return d.item()
    return d


def load_raw(run_dir: str | Path) -> dict[str, Any]:
    """Read the raw tables and settings a :func:`save_run` directory holds."""
    d = Path(run_dir)
    if not d.is_dir():
        raise MsmillInputError("run_dir", str(d), "an existing directory written by 'msmill dem run'")
    if not (d / "events.parquet").exists():
        raise MsmillInputError("run_dir", str(d), "a directory written by 'msmill dem run' (events.parquet missing)")
    from msmill.validate import read_toml

    settings = read_toml(d / "run.toml", "run_dir/run.toml", "run.toml of a DEM run")
    for key in ("design", "result", "feed", "rock"):
        if not isinstance(settings.get(key), dict):
            raise MsmillInputError(f"run.toml.{key}", settings.get(key), "a table written by 'msmill dem run'")
    raw: dict[str, Any] = {"settings": settings, "machine": Machine.from_toml(d / "machine.toml")}
    for name in ("events", "removed", "timeseries", "snapshots"):
        try:
            raw[name] = pd.read_parquet(d / f"{name}.parquet")
        except Exception as exc:  # pyarrow raises many types for a damaged file
            raise MsmillInputError(f"{name}.parquet", str(d / f"{name}.parquet"),
                                   f"a readable Parquet file written by 'msmill dem run' ({type(exc).__name__})") from None
    return raw


def stats_from_dir(run_dir: str | Path, stats_settings: StatsSettings | None = None) -> MillStatistics:
    """Recompute the statistics of a saved run from its raw events and snapshots."""
    raw = load_raw(run_dir)
    s = raw["settings"]
    m: Machine = raw["machine"]
    d = s["design"]
    op = OperatingPoint(feed_tph=d["feed_tph"], stage_speeds_rpm=d["stage_speeds_rpm"], gate_deg=d["gate_deg"])
    res = s["result"]
    steady = res["steady_state_time_s"] if res["steady_state_time_s"] >= 0 else None
    sizes = np.asarray(s["feed"]["sizes_mm"])
    edges = None
    if sizes.size > 1:
        mids = np.sqrt(sizes[1:] * sizes[:-1]) / 2000
        edges = np.concatenate([[0.0], mids, [np.inf]])
    prov = {"generator": "msmill.dem.mill.run.stats_from_dir", "msmill_version": __version__,
            "source_dir": str(run_dir), "run_settings": s.get("run", {}), "wall_s": res.get("wall_s")}
    design = DesignPoint(size_mm=d["size_mm"], feed_tph=op.feed_tph, speed_rpm=d["speed_rpm"], gate_deg=op.gate_deg,
                         stage_speeds_rpm=op.stage_speeds(m.n_stages))
    return compute_statistics(
        m, design, raw["events"], raw["removed"], raw["timeseries"], raw["snapshots"],
        (res["window_start_s"], res["window_end_s"]), mode=d["mode"],
        rock_density_kg_m3=s["rock"]["density_kg_m3"], steady_state_time_s=steady, settings=stats_settings,
        size_edges_m=edges, provenance=prov,
    )
