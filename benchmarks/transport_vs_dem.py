"""Transport of the mill model against the DEM runs it was built from (non-breaking rock).

Run::

    python benchmarks/transport_vs_dem.py [--table PATH] [--transport dem_matrix]

For every run of the stage-parameter table (default: the packaged
``msmill/data/stage_parameters/default.json``) the mill model is run with
rock that never breaks (``breakage="none"``, ``damage="none"``), one size
class around the run's rock size, at the run's operating point, with that
run's statistics only (``RunProvider``). Compared with the run's own figures:

* **mean residence time**: model = steady-state hold-up (inlet zone included)
  / feed rate; DEM = mean mass in the mill / mass out rate over the
  measurement window (Little's law, ``RunStatistics.residence_time_s``);
* **time to steady state**: the DEM's own criterion,
  :func:`msmill.dem.mill.stats.detect_steady_state` (the same function the DEM
  run used on its particle count, not a copy), applied to the model's hold-up
  series from an empty mill; DEM = ``RunStatistics.steady_state_time_s``.
  A run whose DEM never met its criterion has no time to compare (``n/a``,
  left out of the maximum and counted in ``runs_without_dem_steady_state``).

Nothing is fitted here: the model reads the run's measured transport
(destinations one characteristic time later) and nothing else. The last line is
``runs=<n> residence_rel_err_max=<x> tss_abs_err_max_s=<y> ...``.
"""

from __future__ import annotations

import argparse
import math
import warnings
from pathlib import Path

import numpy as np

from msmill.dem.mill.stats import detect_steady_state
from msmill.machine import OperatingPoint
from msmill.model import Mill
from msmill.model.providers import RunProvider, default_table_path
from msmill.model.submodels import BreakageParameters
from msmill.psd import PSD, SizeGrid
from msmill.stageparams import RunStatistics, StageParameterTable

#: Ore parameters are irrelevant with breakage="none"; any valid set.
_ORE = BreakageParameters("unbreakable", A_pct=50.0, b_t_kwh=1.0, l_ref_mm=29.0)


def model_transport(run: RunStatistics, transport: str) -> dict[str, float]:
    """Residence time (s) and time to steady state (s, DEM criterion) of the model at one run."""
    size = run.design.size_mm
    grid = SizeGrid(np.array([size / 1.1, size * 1.1]))
    feed = PSD(grid, np.array([1.0]))
    op = OperatingPoint(feed_tph=run.design.feed_tph, stage_speeds_rpm=run.design.stage_speeds_rpm,
                        gate_deg=run.design.gate_deg)
    mill = Mill(_ORE, RunProvider(run, source=f"{size:g} mm run"), transport=transport, breakage="none",
                damage="none", grid=grid, damage_classes=1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = mill.run(feed, op)
        _, _, _, lm, _ = mill.prepare(grid, op)
    tps = run.design.feed_tph * run.characteristic_time_s / 3600.0
    x = lm.steady_state(lm.feed_vector(np.array([1.0]), tps))
    ts = res.timeseries
    found = detect_steady_state(ts["time_s"].to_numpy(), ts["holdup_t"].to_numpy())
    return {"residence_s": float(x.sum()) / (run.design.feed_tph / 3600.0),
            "tss_s": found[0] if found else math.nan,
            "tss_product_1pct_s": res.time_to_steady_state_s}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--table", type=Path, default=None, help="stage-parameter table (default: the packaged one)")
    ap.add_argument("--transport", default="dem_matrix", help="transport sub-model (default dem_matrix)")
    args = ap.parse_args()
    path = args.table or default_table_path()
    table = StageParameterTable.from_json(path)
    print(f"table: {path}; transport: {args.transport}; rock: unbreakable")
    n_dest = sum(r.inlet_destinations is not None and all(st.destinations is not None for st in r.stages)
                 for r in table.runs)
    if args.transport == "dem_matrix" and n_dest < len(table.runs):
        print(f"note: {len(table.runs) - n_dest} of {len(table.runs)} runs have no one-lag destinations: "
              "dem_matrix falls back to their three streams there")
    print(f"{'size_mm':>8} {'tau_s':>6} {'res_dem_s':>9} {'res_model_s':>11} {'rel_err':>8} "
          f"{'tss_dem_s':>9} {'tss_model_s':>11} {'abs_err_s':>9} {'tss_1pct_s':>10}")
    rel, err, no_ss = [], [], 0
    for run in table.runs:
        m = model_transport(run, args.transport)
        r_dem = run.residence_time_s
        e_rel = (m["residence_s"] - r_dem) / r_dem if r_dem else math.nan
        t_dem = run.steady_state_time_s
        e_abs = m["tss_s"] - t_dem if t_dem is not None else math.nan
        no_ss += t_dem is None
        rel.append(abs(e_rel))
        if t_dem is not None:
            err.append(abs(e_abs))
        t_dem_txt = f"{t_dem:9.2f}" if t_dem is not None else f"{'n/a':>9}"
        print(f"{run.design.size_mm:8.3g} {run.characteristic_time_s:6.3f} {r_dem:9.3f} {m['residence_s']:11.3f} "
              f"{e_rel:+8.3f} {t_dem_txt} {m['tss_s']:11.2f} {e_abs:+9.2f} {m['tss_product_1pct_s']:10.2f}")
    print(f"runs={len(table.runs)} residence_rel_err_max={max(rel):.3f} "
          f"tss_abs_err_max_s={max(err) if err else math.nan:.2f} runs_without_dem_steady_state={no_ss} "
          f"runs_with_destinations={n_dest}")


if __name__ == "__main__":
    main()
