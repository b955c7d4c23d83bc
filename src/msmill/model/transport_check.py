"""The mill model's transport against the DEM runs it was built from (non-breaking rock).

Each DEM run (a stage-table run or a steady campaign run) is compared with the
model run on rock that never breaks, one size class around the run's rock
size, at the run's operating point, with that run's statistics only
(:class:`~msmill.model.providers.RunProvider`): the mean residence time
(Little's law) and the time to steady state by one criterion
(:func:`msmill.steadystate.first_steady`) on the DEM's saved series and the
model's march from empty; replicas of a point (other feed seeds) are compared
through their ensemble-mean series. :func:`compare` makes a :class:`Row` per
run, :func:`attach_replicas` adds the replicas' figures, :func:`table_lines`
and :func:`summary` format them. ``benchmarks/transport_vs_dem.py`` drives it
(its docstring says what every figure means); docs/model.md section 7 quotes
its output.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from msmill.dem.mill.run import (
    RunSettings,
    saved_run_feed_kg_s,
    saved_run_filling_transport,
    saved_run_verdict,
)
from msmill.errors import MsmillInputError
from msmill.machine import OperatingPoint
from msmill.model.mill import Mill
from msmill.model.providers import RunProvider, TableProvider, pooled_filling
from msmill.model.result import time_to_steady_state
from msmill.model.submodels import BreakageParameters, Transition
from msmill.psd import PSD, SizeGrid
from msmill.stageparams import FillingTransport, RunStatistics, StageParameterTable, chain_visits
from msmill.steadystate import SteadyStateCriterion, count_only_onset, first_steady

#: Ore parameters are irrelevant with breakage="none"; any valid set.
_ORE = BreakageParameters("unbreakable", A_pct=50.0, b_t_per_kwh=1.0, l_ref_mm=29.0)
_NAN = float("nan")


@dataclass
class Row:
    """One run's figures (s, or relative for ``res_err``)."""

    size_mm: float
    tau_s: float
    res_dem_s: float
    res_model_s: float
    tss_dem_s: float
    tss_model_s: float
    tss_dem_rec_s: float
    tss_model_rec_s: float
    today: bool
    scatter: tuple[float, float] = (_NAN, _NAN)
    #: ``--scatter``: median of the independent-rock marches' onsets and their ensemble-mean series' onset
    scatter_median_s: float = _NAN
    scatter_ensemble_s: float = _NAN
    tss_model_today_s: float = _NAN
    n_replicas: int = 0
    res_dem_rep_s: float = _NAN
    tss_dem_rep_s: float = _NAN
    tss_dem_median_s: float = _NAN
    tss_dem_rep_se_s: float = _NAN
    dem_range: tuple[float, float] = (_NAN, _NAN)
    #: the model's march from empty: time (s), hold-up over its steady hold-up, product rate over the feed rate
    model_series: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None

    @property
    def res_err(self) -> float:
        return (self.res_model_s - self.res_dem_s) / self.res_dem_s if self.res_dem_s else _NAN

    @property
    def tss_err(self) -> float:
        return self.tss_model_s - self.tss_dem_s

    @property
    def tss_err_rec(self) -> float:
        return self.tss_model_rec_s - self.tss_dem_rec_s

    @property
    def res_err_rep(self) -> float:
        """Relative residence error against the mean of the point's runs (the single run's without replicas)."""
        if not self.n_replicas:
            return self.res_err
        return (self.res_model_s - self.res_dem_rep_s) / self.res_dem_rep_s

    @property
    def tss_err_rep(self) -> float:
        """Onset error against the replicas' ensemble-mean onset (the single run's without replicas)."""
        return self.tss_model_today_s - self.tss_dem_rep_s if self.n_replicas else self.tss_err


def load_replicas(path: Path | None) -> list[dict]:
    """The replica runs of ``path`` (``scripts/transport_replicas.py --export``); [] without a file."""
    import json

    if path is None or not path.is_file():
        return []
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError):
        doc = None
    kind = doc.get("kind") if isinstance(doc, dict) else None
    if kind != "msmill_transport_replicas" or not isinstance(doc.get("replicas"), list):
        raise MsmillInputError("replicas", str(path), "a transport-replicas file (JSON of kind "
                               f"'msmill_transport_replicas', here {kind!r})")
    return list(doc["replicas"])


def replica_series(rep: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(time_s, holdup_kg, product_cum_kg)`` of a replica, repeated sample times dropped."""
    s = rep["series"]
    t, held, out = (np.asarray(s[k], dtype=float) for k in ("time_s", "holdup_kg", "product_cum_kg"))
    keep = np.concatenate([[True], np.diff(t) > 0])
    return t[keep], held[keep], out[keep]


def replica_onset(rep: dict, crit: SteadyStateCriterion) -> float:
    """Onset (s) of one replica by ``crit`` on its saved series (NaN if never steady)."""
    found = first_steady(*replica_series(rep), float(rep["feed_kg_s"]), crit)
    return found[0] if found else _NAN


def replica_residence(rep: dict, onset_s: float) -> float:
    """Mean residence time (s) of one replica over its steady part, from its onset to the series' end.

    Little's law on the series: mean hold-up over ``[onset, end]`` / product
    rate over it (a 2-4 s window instead of the run's 0.5 s); the run's own
    window figure (``residence_time_s``) when it never became steady.
    """
    t, held, out = replica_series(rep)
    if not np.isfinite(onset_s) or t[-1] - onset_s < 1.0:
        return float(rep.get("residence_time_s") or _NAN)
    k = t >= onset_s - 1e-9
    rate = (out[-1] - out[k][0]) / (t[-1] - t[k][0])
    return float(np.trapezoid(held[k], t[k]) / (t[k][-1] - t[k][0]) / rate) if rate > 0 else _NAN


def replicas_on_grid(reps: list[dict], every_s: float = 0.01) -> tuple[np.ndarray, np.ndarray, np.ndarray,
                                                                        np.ndarray]:
    """Each replica's hold-up and cumulative product on common times (to the shortest): t, (R, T), (R, T), feeds (R,)."""
    series = [replica_series(r) for r in reps]
    t = np.arange(0.0, min(s[0][-1] for s in series) + 1e-9, every_s)
    held = np.array([np.interp(t, s[0], s[1]) for s in series])
    out = np.array([np.interp(t, s[0], s[2]) for s in series])
    return t, held, out, np.array([float(r["feed_kg_s"]) for r in reps])


def ensemble_series(reps: list[dict], every_s: float = 0.01) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Mean hold-up and cumulative product of the replicas, interpolated on common times (to the shortest)."""
    t, held, out, feed = replicas_on_grid(reps, every_s)
    return t, held.mean(axis=0), out.mean(axis=0), float(feed.mean())


def bootstrap_onset_se(reps: list[dict], crit: SteadyStateCriterion, n_boot: int = 200, seed: int = 0) -> float:
    """Standard error (s) of the ensemble-mean onset: the replicas resampled with replacement (NaN below 3)."""
    if len(reps) < 3:
        return _NAN
    t, held, out, feed = replicas_on_grid(reps)  # once: a resample only averages other rows
    rng = np.random.default_rng(seed)
    ons = []
    for _ in range(n_boot):
        k = rng.integers(0, len(reps), len(reps))
        found = first_steady(t, held[k].mean(axis=0), out[k].mean(axis=0), float(feed[k].mean()), crit)
        ons.append(found[0] if found else _NAN)
    return float(np.nanstd(ons, ddof=1))


def attach_replicas(row: Row, reps: list[dict], crit: SteadyStateCriterion) -> Row:
    """Fill the row's replica figures from the replicas at its size.

    The DEM's time to steady state is the onset of the replicas' **ensemble
    mean** series (hold-up and cumulative product averaged over the runs at
    each time, then the criterion): the series an expected-value model
    predicts. The median of the single runs' onsets and their 5-95 % range
    are printed beside it; the residence time is the mean of the runs'
    :func:`replica_residence`.
    """
    mine = [r for r in reps if abs(float(r["size_mm"]) - row.size_mm) < 1e-6 * row.size_mm]
    if not mine:
        return row
    ons = np.asarray([replica_onset(r, crit) for r in mine], dtype=float)
    res = np.asarray([replica_residence(r, o) for r, o in zip(mine, ons, strict=True)], dtype=float)
    row.n_replicas = len(mine)
    row.res_dem_rep_s = float(np.nanmean(res)) if np.isfinite(res).any() else _NAN
    found = first_steady(*ensemble_series(mine), crit)
    row.tss_dem_rep_s = found[0] if found else _NAN
    row.tss_dem_rep_se_s = bootstrap_onset_se(mine, crit)
    if np.isfinite(ons).any():
        row.tss_dem_median_s = float(np.nanmedian(ons))
        row.dem_range = (float(np.nanpercentile(ons, 5)), float(np.nanpercentile(ons, 95)))
    return row


def export_raw_dir(doc_path: Path) -> Path | None:
    """Folder of the time series an exported run document references (``raw_files``), or None."""
    import json

    raw = json.loads(doc_path.read_text(encoding="utf-8")).get("raw_files") or []
    paths = [Path(r["path"]).parent for r in raw if r.get("kind") == "timeseries" and r.get("path")]
    return paths[0] if paths else None


def dem_run_dir(run: RunStatistics, runs_dir: Path | None) -> Path | None:
    """The folder of the run's saved DEM data (time series), or None if it is not on this machine.

    Candidates in order: ``runs_dir`` itself when it is a run folder, ``runs_dir/size_<d>mm``,
    the run's provenance ``source_dir`` (or that of its recomputed statistics).
    """
    prov = run.provenance or {}
    cands = [runs_dir, runs_dir / f"size_{run.design.size_mm:g}mm"] if runs_dir else []
    cands += [Path(p) for p in (prov.get("source_dir"), (prov.get("statistics_recomputed_by") or {}).get("source_dir"))
              if isinstance(p, str)]
    for d in cands:
        if all((d / f).is_file() for f in ("timeseries.parquet", "run.toml", "machine.toml")):
            return d
    return None


def recorded_onset(time_s: np.ndarray, holdup: np.ndarray, product_cum: np.ndarray, feed_rate: float,
                   run_settings: dict) -> float:
    """Onset (s) of a series by the criterion a run recorded in its ``run_settings`` (NaN if never)."""
    w = float(run_settings.get("steady_window_s", 0.4))
    rel = float(run_settings.get("rel_tol", 0.05))
    trend = float(run_settings.get("trend_tol", 0.05))
    if "balance_tol" in run_settings:
        crit = SteadyStateCriterion(w, float(run_settings["balance_tol"]), trend, rel)
        found = first_steady(time_s, holdup, product_cum, feed_rate, crit)
    else:  # runs made before the mass-balance criterion: the count-only test
        found = count_only_onset(time_s, holdup, w, rel, trend)
    return found[0] if found else _NAN


def _mill(run: RunStatistics, transport: str) -> tuple[Mill, PSD, SizeGrid, OperatingPoint]:
    size = run.design.size_mm
    grid = SizeGrid(np.array([size / 1.1, size * 1.1]))
    op = OperatingPoint(feed_tph=run.design.feed_tph, stage_speeds_rpm=run.design.stage_speeds_rpm,
                        gate_deg=run.design.gate_deg)
    mill = Mill(_ORE, RunProvider(run, source=f"{size:g} mm run"), transport=transport, breakage="none",
                damage="none", grid=grid, damage_classes=1)
    return mill, PSD(grid, np.array([1.0])), grid, op


def scatter_onsets(tr: Transition, rocks_per_step: float, tau_s: float, crit: SteadyStateCriterion,
                   n_sims: int, seed: int = 0) -> tuple[np.ndarray, float]:
    """Onsets of ``n_sims`` marches of whole rocks moving independently by the transport ``tr``.

    Per step every compartment's rocks go to their destinations by a multinomial
    draw from the first size class's one-step matrix, at the speed the run's own
    fill sets (:meth:`Transition.speed_at`, rocks in the mill over the chain's
    steady count; the steady matrix when ``tr`` carries no filling curve); the
    feed (``rocks_per_step``, fractional part carried over) enters compartment 0.
    The marches last 8 s. Returns the single marches' onsets (s, NaN if never)
    and the onset of their ensemble-mean series (NaN if never).
    """
    rng = np.random.default_rng(seed)
    base = tr.matrix[:, 0, :]
    c = base.shape[0]
    steady_rocks = rocks_per_step * float(chain_visits(base).sum())
    by_count: dict[int, np.ndarray] = {}

    def matrix_at(n_rocks: int) -> np.ndarray:  # one matrix per rock count: few distinct ones
        if n_rocks not in by_count:
            p = np.clip(tr.at_speed(tr.speed_at(n_rocks / steady_rocks))[:, 0, :], 0.0, None)
            by_count[n_rocks] = p / p.sum(axis=1, keepdims=True)
        return by_count[n_rocks]

    steps = math.ceil(8.0 / tau_s)
    x = np.zeros((n_sims, c), dtype=np.int64)
    held = np.zeros((n_sims, steps + 1))
    out = np.zeros((n_sims, steps + 1))
    carry = 0.0
    for k in range(1, steps + 1):
        p = np.stack([matrix_at(int(n)) for n in x.sum(axis=1)])  # (n_sims, C, C+1)
        new = sum(rng.multinomial(x[:, j], p[:, j, :]) for j in range(c))
        carry += rocks_per_step
        fed = math.floor(carry)
        carry -= fed
        x = new[:, :c]
        x[:, 0] += fed
        held[:, k] = x.sum(axis=1)
        out[:, k] = out[:, k - 1] + new[:, c]
    t = np.arange(steps + 1) * tau_s
    found = [first_steady(t, held[i], out[i], rocks_per_step / tau_s, crit) for i in range(n_sims)]
    ens = first_steady(t, held.mean(axis=0), out.mean(axis=0), rocks_per_step / tau_s, crit)
    return np.array([f[0] if f else _NAN for f in found]), (ens[0] if ens else _NAN)


def with_filling(run: RunStatistics, runs_dir: Path | None) -> RunStatistics:
    """The run with its filling transport, measured from its saved DEM folder if it has none (and the folder is here)."""
    d = dem_run_dir(run, runs_dir)
    if run.filling_transport is not None or d is None:
        return run
    return run.model_copy(update={"filling_transport": saved_run_filling_transport(d, run.characteristic_time_s)})


def pooled_curve(runs: list[RunStatistics]) -> FillingTransport | None:
    """The runs' filling curves pooled (:func:`msmill.model.providers.pooled_filling`), as one curve."""
    pooled = pooled_filling([r for r in runs if r.filling_transport is not None])
    if pooled is None:
        return None
    total = sum(sum(r.filling_transport.tag_mass_kg) for r in runs if r.filling_transport is not None)
    return FillingTransport(fill=list(pooled[0]), residence_ratio=list(pooled[1]),
                            tag_mass_kg=[total / pooled[0].size] * pooled[0].size)


def table_curve_at(table: StageParameterTable, size_mm: float) -> FillingTransport | None:
    """The filling curve the table provider gives rock of ``size_mm`` (None if its runs carry none)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        params = TableProvider(table).stage_parameters(np.array([size_mm]))
    if params.filling_fill is None:
        return None
    h = np.asarray(params.filling_fill, dtype=float)
    r = np.asarray(params.filling_residence_ratio, dtype=float).reshape(-1, h.size)[0]
    return FillingTransport(fill=h.tolist(), residence_ratio=r.tolist(), tag_mass_kg=[1.0] * h.size)


def filling_rule(table: StageParameterTable, filling: str, runs_dir: Path | None
                 ) -> tuple[Callable[[RunStatistics], FillingTransport | None], list[str]]:
    """The filling curve each compared run gets with the ``dem_matrix_fill`` transport, and what it is.

    Parameters
    ----------
    table : StageParameterTable
        The table whose runs' curves (or saved folders, :func:`with_filling`) make the rule.
    filling : {"table", "pooled", "own"}
        ``table``: the table provider's curve at the run's size; ``pooled``: the table
        runs' curves pooled into one; ``own``: each run's own (the rule returns None).
    runs_dir : Path or None
        Folder of the table's saved DEM runs (for runs without a curve).

    Returns
    -------
    (rule, lines)
        ``rule(run)`` gives the curve (None: the run's own); ``lines`` describe the curves.
    """
    if filling not in ("table", "pooled", "own"):
        raise MsmillInputError("filling", filling, "table, pooled or own")
    n_fill = sum(r.filling_transport is not None for r in table.runs)
    lines = [f"filling transport: {filling} ({n_fill} of {len(table.runs)} table runs carry one; "
             "the others are measured from their saved DEM folders)"]
    with_curves = table.model_copy(update={"runs": [with_filling(r, runs_dir) for r in table.runs]})
    if filling == "pooled":
        pooled = pooled_curve(with_curves.runs)
        lines.append(f"  table's pooled curve: fill {np.round(pooled.fill, 2).tolist()} "
                     f"ratio {np.round(pooled.residence_ratio, 3).tolist()}")
        return (lambda run: pooled), lines
    if filling == "table":
        for r in with_curves.runs:
            c = table_curve_at(with_curves, r.design.size_mm)
            lines.append(f"  {r.design.size_mm:g} mm: fill {np.round(c.fill, 2).tolist()} "
                         f"ratio {np.round(c.residence_ratio, 3).tolist()}")
        return (lambda run: table_curve_at(with_curves, run.design.size_mm)), lines
    return (lambda run: None), lines


def warm_started(run: RunStatistics) -> bool:
    """Whether the run started from a filled mill (its onset says nothing about filling from empty)."""
    return ((run.provenance or {}).get("run_settings") or {}).get("start", "empty") != "empty"


def compare(run: RunStatistics, transport: str, runs_dir: Path | None, n_scatter: int,
            curve: FillingTransport | None = None, cold: RunStatistics | None = None) -> Row:
    """Model against DEM for one run (``curve``: the filling transport to use instead of the run's own).

    A warm-started run (``start = "table"``) has no onset from empty: its time to
    steady state is taken from ``cold``, the cold run of the same point (its
    recorded onset and criterion), or left n/a; its residence time stays its own.
    """
    crit = RunSettings().criterion()
    onset_run = run
    if warm_started(run):
        runs_dir = None  # its saved series starts full
        onset_run = cold if cold is not None else run.model_copy(update={"steady_state_time_s": None})
    d = dem_run_dir(onset_run, runs_dir)
    if transport == "dem_matrix_fill":
        run = run.model_copy(update={"filling_transport": curve}) if curve else with_filling(run, runs_dir)
    mill, feed, grid, op = _mill(run, transport)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = mill.run(feed, op)
        _, streams, _, lm, _ = mill.prepare(grid, op)
    tps = run.design.feed_tph * run.characteristic_time_s / 3600.0
    x = lm.steady_state(lm.feed_vector(np.array([1.0]), tps))
    ts = res.timeseries
    t, held, rate = ts["time_s"].to_numpy(), ts["holdup_t"].to_numpy(), ts["product_tph"].to_numpy()
    tss_model = time_to_steady_state(t, rate, op.feed_tph, holdup_t=held, criterion=crit)
    t0 = np.concatenate([[0.0], t])
    cum = np.concatenate([[0.0], np.cumsum(rate * np.diff(t0) / 3600.0)])
    rec_model = recorded_onset(t0, np.concatenate([[0.0], held]), cum, op.feed_tph / 3600.0,
                               (onset_run.provenance or {}).get("run_settings", {}))
    rec_dem = onset_run.steady_state_time_s if onset_run.steady_state_time_s is not None else _NAN
    tss_model_today = tss_model if tss_model is not None else _NAN
    today = d is not None
    tss_dem = _NAN
    if today:
        v = saved_run_verdict(d, crit)
        tss_dem = v.onset_s if v.onset_s is not None else _NAN
    else:
        tss_dem, tss_model = rec_dem, rec_model
    row = Row(run.design.size_mm, run.characteristic_time_s, run.residence_time_s or _NAN,
              float(x.sum()) / (run.design.feed_tph / 3600.0), tss_dem, tss_model, rec_dem, rec_model, today,
              tss_model_today_s=tss_model_today,
              model_series=(t, held / float(x.sum()), rate / op.feed_tph))
    scene = (run.provenance or {}).get("scene") or {}
    recorded = {"rock_density_kg_m3", "feed_kg_s"} <= scene.keys()
    if n_scatter and (today or recorded):
        if recorded:  # the run's scene, as recorded
            rho, feed_kg_s = float(scene["rock_density_kg_m3"]), float(scene["feed_kg_s"])
        else:
            import tomllib

            rho = tomllib.loads((d / "run.toml").read_text(encoding="utf-8"))["rock"]["density_kg_m3"]
            feed_kg_s = saved_run_feed_kg_s(d)
        rock_kg = rho * math.pi / 6.0 * (run.design.size_mm / 1000.0) ** 3
        rocks = feed_kg_s * run.characteristic_time_s / rock_kg
        ons, row.scatter_ensemble_s = scatter_onsets(streams, rocks, run.characteristic_time_s, crit, n_scatter)
        if np.isfinite(ons).any():
            row.scatter = (float(np.nanpercentile(ons, 5)), float(np.nanpercentile(ons, 95)))
            row.scatter_median_s = float(np.nanmedian(ons))
    return row


def _fmt(v: float, w: int, sign: str = "") -> str:
    return f"{v:{sign}{w}.2f}" if np.isfinite(v) else f"{'n/a':>{w}}"


def table_lines(rows: list[Row]) -> list[str]:
    """The table of ``rows`` (and their replicas' table when some have replicas), line by line."""
    reps = any(r.n_replicas for r in rows)
    lines = []
    lines.append(f"{'size_mm':>8} {'tau_s':>6} {'res_dem_s':>9} {'res_model_s':>11} {'rel_err':>8} "
          f"{'tss_dem_s':>9} {'tss_model_s':>11} {'abs_err_s':>9} {'rec_dem_s':>9} {'rec_model_s':>11} "
          f"{'rec_err_s':>9} {'model_5-95%_s':>13}")
    for r in rows:
        sc = f"{r.scatter[0]:.2f}-{r.scatter[1]:.2f}" if np.isfinite(r.scatter[0]) else "-"
        mark = "" if r.today else " (recorded criterion: no DEM series here)"
        lines.append(f"{r.size_mm:8.3g} {r.tau_s:6.3f} {r.res_dem_s:9.3f} {r.res_model_s:11.3f} {r.res_err:+8.3f} "
              f"{_fmt(r.tss_dem_s, 9)} {_fmt(r.tss_model_s, 11)} {_fmt(r.tss_err, 9, '+')} "
              f"{_fmt(r.tss_dem_rec_s, 9)} {_fmt(r.tss_model_rec_s, 11)} {_fmt(r.tss_err_rec, 9, '+')} "
              f"{sc:>13}{mark}")
    for r in rows:
        if np.isfinite(r.scatter_ensemble_s) or np.isfinite(r.scatter_median_s):
            lines.append(f"{r.size_mm:g} mm, independent rocks (--scatter): median single onset "
                  f"{_fmt(r.scatter_median_s, 4)} s, ensemble-mean onset {_fmt(r.scatter_ensemble_s, 4)} s, "
                  f"mean-field march {_fmt(r.tss_model_today_s, 4)} s")
    if reps:
        lines.append(f"\nagainst the replicas (today's criterion on every series; DEM residence = the runs' mean, "
              f"t_ss = onset of the ensemble-mean series, se its bootstrap standard error; median and 5-95 % of the "
              f"single runs' onsets):\n"
              f"{'size_mm':>8} {'n_rep':>5} {'res_dem_s':>9} {'res_model_s':>11} {'rel_err':>8} "
              f"{'tss_dem_s':>9} {'se_s':>5} {'median_s':>8} {'range_s':>11} {'tss_model_s':>11} {'abs_err_s':>9}")
        for r in rows:
            if not r.n_replicas:
                continue
            rng = f"{r.dem_range[0]:.2f}-{r.dem_range[1]:.2f}" if np.isfinite(r.dem_range[0]) else "-"
            lines.append(f"{r.size_mm:8.3g} {r.n_replicas:5d} {r.res_dem_rep_s:9.3f} {r.res_model_s:11.3f} "
                  f"{r.res_err_rep:+8.3f} {_fmt(r.tss_dem_rep_s, 9)} {_fmt(r.tss_dem_rep_se_s, 5)} "
                  f"{_fmt(r.tss_dem_median_s, 8)} {rng:>11} "
                  f"{_fmt(r.tss_model_today_s, 11)} "
                  f"{_fmt(r.tss_err_rep, 9, '+')}")
    return lines


def summary(rows: list[Row], prefix: str = "") -> str:
    """The ``key=value`` summary of ``rows`` (keys prefixed with ``prefix``)."""
    reps = any(r.n_replicas for r in rows)
    rel = [abs(r.res_err_rep) for r in rows if np.isfinite(r.res_err_rep)]
    err = [abs(r.tss_err_rep) for r in rows if np.isfinite(r.tss_err_rep)]
    single = [abs(r.tss_err) for r in rows if np.isfinite(r.tss_err)]
    rec = [abs(r.tss_err_rec) for r in rows if np.isfinite(r.tss_err_rec)]
    no_ss = sum(not np.isfinite(r.tss_dem_s) for r in rows)

    def mx(v: list[float], spec: str) -> str:
        return f"{max(v):{spec}}" if v else "nan"

    p = prefix
    out = (f"{p}runs={len(rows)} {p}residence_rel_err_max={mx(rel, '.3f')} {p}tss_abs_err_max_s={mx(err, '.2f')} "
           f"{p}runs_without_dem_steady_state={no_ss} {p}tss_from_dem_series={sum(r.today for r in rows)} "
           f"{p}tss_abs_err_max_recorded_s={mx(rec, '.2f')}")
    if reps:
        n_rep = sum(r.n_replicas for r in rows)
        with_rep = sum(bool(r.n_replicas) for r in rows)
        width = [r.dem_range[1] - r.dem_range[0] for r in rows if np.isfinite(r.dem_range[0])]
        out += (f" {p}tss_abs_err_max_single_s={mx(single, '.2f')} {p}points_with_replicas={with_rep}"
                f" {p}replicas={n_rep} {p}dem_onset_range_max_s={mx(width, '.2f')}")
    if p and err:
        out += f" {p}tss_abs_err_median_s={float(np.median(err)):.2f}"
    return out
