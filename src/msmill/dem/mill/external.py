"""Import DEM data that msmill did not produce (Rocky, EDEM, LIGGGHTS ...).

An import folder holds plain tables (CSV or Parquet, SI units) and two TOML
files; ``docs/campaign.md`` (External DEM data) documents every column and
the mapping from LIGGGHTS dumps. The tables go through the same statistics
code as our own runs, :func:`msmill.dem.mill.stats.compute_statistics`.

Files
-----
``machine.toml``
    The mill geometry (:class:`msmill.machine.Machine`): stage bands and rotor
    numbering are needed to place contacts and rocks in stages.
``import.toml``
    ``[design]`` size_mm, feed_tph, speed_rpm, gate_deg, stage_speeds_rpm,
    mode ("slice" or "full"); ``[rock]`` density_kg_m3; ``[window]`` start_s,
    end_s (measurement window) and optional steady_state_time_s (None: not
    steady); ``[source]`` engine (free text) and anything else (kept as
    provenance).
``events.csv|parquet`` (required)
    One row per contact at its onset: time_s, particle_id, partner_kind
    (``particle``/``geometry`` or 0/1), partner_id, partner_tag (``flinger``,
    ``liner``, ``gate``, ``hub``, ...; ignored for particles), partner_group
    (rotor index ``2 (stage - 1) + k`` for flingers, else -1), vn_m_s (relative
    normal approach speed, > 0 for an impact), vt_m_s, x_m, y_m, z_m (contact
    point).
``positions.csv|parquet`` (required)
    Rock centres at fixed intervals: time_s, particle_id, x_m, y_m, z_m,
    vx_m_s, vy_m_s, vz_m_s, radius_m.
``removed.csv|parquet`` (optional)
    Rocks that left: particle_id, time_s, tag (``outlet`` = through the gates,
    anything else = lost), radius_m. Without it, rocks that vanish from the
    positions are treated as lost, so pass-through from the bottom stage is
    missing: export it.
``timeseries.csv|parquet`` (optional)
    time_s, n_particles, mass_kg; derived from the positions when absent.
"""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import tomli_w

from msmill._version import __version__
from msmill.dem.mill.stats import MillStatistics, StatsSettings, compute_statistics
from msmill.errors import MsmillInputError
from msmill.machine import Machine
from msmill.stageparams import DesignPoint

__all__ = ["EVENT_COLUMNS", "POSITION_COLUMNS", "import_folder", "import_tables", "read_table", "write_external"]

EVENT_COLUMNS = ("time_s", "particle_id", "partner_kind", "partner_id", "partner_tag", "partner_group",
                 "vn_m_s", "vt_m_s", "x_m", "y_m", "z_m")
POSITION_COLUMNS = ("time_s", "particle_id", "x_m", "y_m", "z_m", "vx_m_s", "vy_m_s", "vz_m_s", "radius_m")
REMOVED_COLUMNS = ("particle_id", "time_s", "tag", "radius_m")
_REQUIRED_EVENTS = ("time_s", "particle_id", "partner_kind", "partner_id", "vn_m_s", "z_m")
_KIND = {"particle": 0, "geometry": 1, "wall": 1, "0": 0, "1": 1}


def read_table(folder: Path, stem: str, required: bool = True) -> pd.DataFrame | None:
    """Read ``stem.parquet`` or ``stem.csv`` from a folder (None if absent and not required)."""
    for ext in (".parquet", ".csv"):
        p = folder / f"{stem}{ext}"
        if p.exists():
            return pd.read_parquet(p) if ext == ".parquet" else pd.read_csv(p)
    if required:
        raise MsmillInputError(f"{folder.name}/{stem}", "missing", f"{stem}.csv or {stem}.parquet")
    return None


def _check_columns(df: pd.DataFrame, needed: tuple[str, ...], name: str) -> None:
    missing = [c for c in needed if c not in df]
    if missing:
        raise MsmillInputError(f"{name} columns", ", ".join(missing), "present (see docs/campaign.md)")


def _events(ev: pd.DataFrame) -> pd.DataFrame:
    _check_columns(ev, _REQUIRED_EVENTS, "events")
    ev = ev.copy()
    kind = ev["partner_kind"].astype(str).str.strip().str.lower().map(_KIND)
    if kind.isna().any():
        bad = ev["partner_kind"][kind.isna()].iloc[0]
        raise MsmillInputError("events.partner_kind", bad, "particle, geometry, 0 or 1")
    ev["partner_kind"] = kind.astype(np.int64)
    ev["particle_id"] = ev["particle_id"].astype(np.int64)
    ev["partner_id"] = ev["partner_id"].astype(np.int64)
    if "partner_tag" not in ev:
        ev["partner_tag"] = ""
    ev["partner_tag"] = ev["partner_tag"].fillna("").astype(str).where(ev["partner_kind"] != 0, "particle")
    if "partner_group" not in ev:
        ev["partner_group"] = -1
    ev["partner_group"] = ev["partner_group"].fillna(-1).astype(np.int64)
    # a particle-particle contact is listed once, owned by the smaller id (as the engine does)
    pp = ev["partner_kind"].to_numpy() == 0
    a, b = ev["particle_id"].to_numpy(), ev["partner_id"].to_numpy()
    ev.loc[pp, "particle_id"], ev.loc[pp, "partner_id"] = np.minimum(a, b)[pp], np.maximum(a, b)[pp]
    return ev.sort_values(["time_s", "particle_id"], kind="stable", ignore_index=True)


def _timeseries(positions: pd.DataFrame, density_kg_m3: float) -> pd.DataFrame:
    m = density_kg_m3 * 4.0 / 3.0 * np.pi * positions["radius_m"].to_numpy() ** 3
    g = positions.assign(mass_kg=m).groupby("time_s")
    return pd.DataFrame({"time_s": g.size().index.to_numpy(), "n_particles": g.size().to_numpy(),
                         "mass_kg": g["mass_kg"].sum().to_numpy()})


def import_tables(
    machine: Machine, meta: dict[str, Any], events: pd.DataFrame, positions: pd.DataFrame,
    removed: pd.DataFrame | None = None, timeseries: pd.DataFrame | None = None,
    settings: StatsSettings | None = None,
) -> MillStatistics:
    """Statistics of external tables (see the module docstring for ``meta`` and the columns)."""
    _check_columns(positions, POSITION_COLUMNS, "positions")
    try:
        d, win = meta["design"], meta["window"]
        density = float(meta.get("rock", {}).get("density_kg_m3", 2700.0))
        design = DesignPoint(size_mm=d["size_mm"], feed_tph=d["feed_tph"], speed_rpm=d["speed_rpm"],
                             gate_deg=d["gate_deg"], stage_speeds_rpm=d["stage_speeds_rpm"])
        window = (float(win["start_s"]), float(win["end_s"]))
    except KeyError as exc:
        raise MsmillInputError("import.toml", f"missing {exc.args[0]}", "[design], [window] (docs/campaign.md)") from None
    if len(design.stage_speeds_rpm) != machine.n_stages:
        raise MsmillInputError("design.stage_speeds_rpm", design.stage_speeds_rpm, f"{machine.n_stages} speeds")
    pos = positions.copy()
    pos["particle_id"] = pos["particle_id"].astype(np.int64)
    if removed is None:
        removed = pd.DataFrame({"particle_id": pd.Series(dtype=np.int64), "time_s": pd.Series(dtype=float),
                                "radius_m": pd.Series(dtype=float), "tag": pd.Series(dtype=str)})
    ts = timeseries if timeseries is not None else _timeseries(pos, density)
    steady = win.get("steady_state_time_s")
    steady = None if steady is None or float(steady) < 0 else float(steady)
    source = dict(meta.get("source", {}))
    prov = {"generator": "msmill.dem.mill.external", "msmill_version": __version__,
            "engine": str(source.get("engine", "external")), "source": source}
    ms = compute_statistics(machine, design, _events(events), removed, ts, pos, window,
                            mode=d.get("mode", "slice"), rock_density_kg_m3=density,
                            steady_state_time_s=steady, settings=settings, provenance=prov)
    from msmill.dem.mill.run import mark_statistics

    # outcome and feed scale if the export recorded them ([run] table), sampling errors reached always
    run_meta = meta.get("run", {})
    return mark_statistics(ms, run_meta.get("outcome"), run_meta.get("feed_scale"))


def import_folder(folder: str | Path, settings: StatsSettings | None = None) -> tuple[MillStatistics, Machine]:
    """Read an import folder (module docstring) and compute its statistics."""
    f = Path(folder)
    if not (f / "import.toml").exists() or not (f / "machine.toml").exists():
        raise MsmillInputError("folder", str(f), "a folder with import.toml, machine.toml and the tables")
    meta = tomllib.loads((f / "import.toml").read_text(encoding="utf-8"))
    machine = Machine.from_toml(f / "machine.toml")
    ms = import_tables(machine, meta, read_table(f, "events"), read_table(f, "positions"),
                       read_table(f, "removed", required=False), read_table(f, "timeseries", required=False),
                       settings=settings)
    ms.run.provenance["source_dir"] = str(f)
    return ms, machine


def write_external(run_dir: str | Path, out_dir: str | Path, fmt: str = "csv", engine: str = "msmill.dem") -> Path:
    """Write a saved msmill run (``save_run`` folder) in the external import schema.

    Used to test the import on our own runs and as an example of the format.
    Only the documented columns are written.
    """
    from msmill.dem.mill.run import load_raw

    if fmt not in ("csv", "parquet"):
        raise MsmillInputError("fmt", fmt, "csv or parquet")
    raw = load_raw(run_dir)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    ev = raw["events"].copy()
    ev["partner_kind"] = np.where(ev["partner_kind"].to_numpy() == 0, "particle", "geometry")
    tables = {"events": ev.loc[:, [c for c in EVENT_COLUMNS if c in ev]],
              "positions": raw["snapshots"].loc[:, list(POSITION_COLUMNS)],
              "removed": raw["removed"].loc[:, list(REMOVED_COLUMNS)],
              "timeseries": raw["timeseries"].loc[:, ["time_s", "n_particles", "mass_kg"]]}
    for name, df in tables.items():
        if fmt == "csv":
            df.to_csv(out / f"{name}.csv", index=False, float_format="%.17g")
        else:
            df.to_parquet(out / f"{name}.parquet", index=False)
    s = raw["settings"]
    res = s["result"]
    meta = {"design": s["design"], "rock": {"density_kg_m3": s["rock"]["density_kg_m3"]},
            "window": {"start_s": res["window_start_s"], "end_s": res["window_end_s"],
                       "steady_state_time_s": res["steady_state_time_s"]},
            "source": {"engine": engine, "converted_from": str(run_dir)},
            "run": {k: res[k] for k in ("outcome", "feed_scale") if k in res}}
    (out / "import.toml").write_text(tomli_w.dumps(meta), encoding="utf-8")
    raw["machine"].to_toml(out / "machine.toml")
    return out
