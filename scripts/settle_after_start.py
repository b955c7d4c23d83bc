"""How a saved run settles after its start: streams and hold-up per compartment in time slots.

Reads raw run folders (``save_run``: a campaign's ``--raw-dir``, ``msmill dem run --out``), tags every
rock at every snapshot with its compartment one characteristic time later
(:func:`msmill.dem.mill.stats.slot_streams`) and prints, per slot, each stage's kickback and
pass-through and each compartment's hold-up relative to the run's measurement window (``docs/mill-dem.md``,
Section 3.2: the settle time ``RunSettings.settle_s`` is where these reach the window's values). With
``--csv`` the whole table is written too.

Run: ``python scripts/settle_after_start.py RUN_DIR [RUN_DIR ...] [--slot-s 0.2] [--csv OUT.csv]``
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pandas as pd

from msmill.dem.mill.saved import load_raw
from msmill.dem.mill.stats import slot_streams, snapshot_lag
from msmill.stageparams import RunStatistics


def settle_table(run_dir: Path, slot_s: float) -> tuple[pd.DataFrame, RunStatistics]:
    """The slot table of one saved run, with the hold-up over the window's mean, and the run's statistics."""
    raw = load_raw(run_dir)
    stats = RunStatistics.from_json(run_dir / "statistics.json")
    lag = snapshot_lag(raw["snapshots"]["time_s"].to_numpy(), stats.characteristic_time_s)
    rho = float(raw["settings"]["rock"].get("density_kg_m3", 2700.0))
    tab = slot_streams(raw["machine"], raw["snapshots"], raw["removed"], lag, slot_s, rho)
    window = [stats.inlet_holdup_kg] + [s.mean_holdup_kg for s in stats.stages]
    tab["holdup_over_window"] = tab["holdup_kg"] / np.asarray(window, dtype=float)[tab["stage"].to_numpy()]
    return tab, stats


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", type=Path, nargs="+")
    ap.add_argument("--slot-s", type=float, default=0.2)
    ap.add_argument("--csv", type=Path, default=None)
    a = ap.parse_args(argv)
    tables = []
    for d in a.runs:
        tab, st = settle_table(d, a.slot_s)
        ds = st.design
        start = st.steady_state_time_s or 0.0
        print(f"# {d.name}: {ds.size_mm:.3g} mm, {ds.feed_tph:.3g} t/h, {ds.speed_rpm:.0f} rpm, gate {ds.gate_deg:.3g} "
              f"deg; onset {start:.2f} s, window {st.measurement_window_s or 0.0:.2f} s long; window streams (kickback / pass-through) "
              + ", ".join(f"s{s.stage} {s.kickback:.2f}/{s.pass_through:.2f}" for s in st.stages))
        wide = tab.pivot_table(index="slot_start_s", columns="stage",
                               values=["kickback", "pass_through", "holdup_over_window"])
        for t, row in wide.iterrows():
            kb = " ".join(f"{row[('kickback', s)]:.2f}" for s in range(1, st.n_stages + 1))
            pt = " ".join(f"{row[('pass_through', s)]:.2f}" for s in range(1, st.n_stages + 1))
            ho = " ".join(f"{row[('holdup_over_window', s)]:.2f}" for s in range(st.n_stages + 1))
            print(f"{t:5.2f}-{t + a.slot_s:.2f} s  kickback {kb}  pass-through {pt}  hold-up/window {ho}")
        tables.append(tab.assign(run=d.name))
    if a.csv is not None:
        pd.concat(tables, ignore_index=True).to_csv(a.csv, index=False)
        print(f"wrote {a.csv}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
