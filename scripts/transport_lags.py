"""Is the DEM's transport Markov at the characteristic time? Transitions at several lags of saved runs.

Run::

    python scripts/transport_lags.py RUN_DIR [RUN_DIR ...] [--lags 2 4 8 16]

For each saved mill run (``msmill dem run`` / ``scripts/build_stage_table.py``
folders with ``snapshots.parquet``, ``removed.parquet``, ``run.toml`` and
``statistics.json``) the one-lag transition matrix of every compartment
(inlet zone, stages, out; :func:`msmill.dem.mill.stats.transition_matrix`,
lag = the run's characteristic time) is compared with the matrices measured at
``k`` times that lag, tags in the run's measurement window: a Markov transport
would give ``P(k tau) = P(tau)^k``. Printed per run and lag: the largest
difference in a fraction, and the fraction out of the mill from each
compartment (measured / Markov). Reads only; writes nothing.
"""

from __future__ import annotations

import argparse
import json
import tomllib
from pathlib import Path

import numpy as np
import pandas as pd

from msmill.dem.mill.stats import transition_matrix
from msmill.machine import Machine


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", type=Path, nargs="+")
    ap.add_argument("--lags", type=int, nargs="+", default=[2, 4, 8, 16])
    args = ap.parse_args()
    worst = 0.0
    for d in args.runs:
        m = Machine.from_toml(d / "machine.toml")
        n = m.n_stages
        res = tomllib.loads((d / "run.toml").read_text(encoding="utf-8"))["result"]
        rho = tomllib.loads((d / "run.toml").read_text(encoding="utf-8"))["rock"]["density_kg_m3"]
        tau = json.loads((d / "statistics.json").read_text(encoding="utf-8"))["characteristic_time_s"]
        snaps = pd.read_parquet(d / "snapshots.parquet")
        removed = pd.read_parquet(d / "removed.parquet")
        dt = float(np.median(np.diff(np.sort(snaps["time_s"].unique()))))
        lag = max(1, round(tau / dt))
        win = (res["window_start_s"], res["window_end_s"])
        p1 = transition_matrix(m, snaps, removed, win, lag, rho)
        sq = np.zeros((n + 2, n + 2))
        sq[: n + 1], sq[n + 1, n + 1] = p1, 1.0
        print(f"{d.name}: tau {tau:.3f} s = {lag} snapshots, window {win[0]:.2f}-{win[1]:.2f} s")
        for k in args.lags:
            pk = transition_matrix(m, snaps, removed, win, k * lag, rho)
            markov = np.linalg.matrix_power(sq, k)[: n + 1]
            diff = float(np.nanmax(np.abs(pk - markov)))
            worst = max(worst, diff)
            print(f"  lag {k:2d} tau: max |P_dem - P_markov| = {diff:.3f}; out of the mill from inlet, stages: "
                  f"dem {np.round(pk[:, n + 1], 3).tolist()} markov {np.round(markov[:, n + 1], 3).tolist()}")
    print(f"runs={len(args.runs)} max_abs_diff={worst:.3f}")


if __name__ == "__main__":
    main()
