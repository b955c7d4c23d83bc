"""How a DEM mill fills from empty, and which transport models reproduce its time to steady state.

Run::

    python scripts/transport_filling.py RUN_DIR [RUN_DIR ...] [--fill-bins 0 0.2 0.4 0.6 0.8]

For each saved slice or full-mill run (``msmill dem run`` folders: snapshots,
removed, timeseries, run.toml, statistics.json) prints, from the DEM alone:

1. the share of the rock fed in each 0.5 s that left within 0.5 s and 1 s
   (rock fed into an empty mill leaves sooner than rock fed later);
2. the time fresh rock takes from the feed to its first stage, by feed time
   (the inlet zone above stage 1 backs up as the mill fills);
3. the hold-up of every compartment (inlet zone, stages) as a share of its
   measurement-window mean, DEM against the one-lag transport;
4. the one-lag destinations measured with tags taken while the mill's hold-up
   was a share ``h`` of its steady value (bins ``--fill-bins``), as the mean
   residence time of the chain they make.

Then the time to steady state by today's criterion
(:meth:`msmill.dem.mill.run.RunSettings.criterion`, on the DEM series by
:func:`msmill.dem.mill.run.saved_run_verdict`) against single-class marches
of four transports, all measured in the same run and nothing fitted:
``one_lag`` (today's ``dem_matrix``: window destinations); ``fill`` (every
compartment's destinations interpolated in the mill's fill ``h`` between the
bins and the window, ``h = 1``); ``inlet_fill`` (only the inlet zone's row,
by the inlet zone's own fill); ``split`` (the inlet zone as two hidden
states: rock not yet in any stage, and rock thrown back up from stage 1).
Reads only; the last line is ``runs=<n> onset_err_max_s_<model>=<x> ...``.
"""

from __future__ import annotations

import argparse
import itertools
import json
import tomllib
from pathlib import Path

import numpy as np
import pandas as pd

from msmill.dem.mill.run import RunSettings, saved_run_feed_kg_s, saved_run_verdict
from msmill.dem.mill.stats import destination_matrix, snapshot_lag, stage_of_z, tagged_moves
from msmill.machine import Machine
from msmill.stageparams import chain_residence_steps, chain_visits
from msmill.steadystate import first_steady

MODELS = ("one_lag", "fill", "inlet_fill", "split")
MARCH_S = 8.0


def load(d: Path) -> dict:
    """Everything the study needs from one run folder."""
    settings = tomllib.loads((d / "run.toml").read_text(encoding="utf-8"))
    m = Machine.from_toml(d / "machine.toml")
    tau = json.loads((d / "statistics.json").read_text(encoding="utf-8"))["characteristic_time_s"]
    snaps = pd.read_parquet(d / "snapshots.parquet", columns=["particle_id", "time_s", "y_m", "z_m", "radius_m"])
    removed = pd.read_parquet(d / "removed.parquet")
    times = np.sort(snaps["time_s"].unique())
    lag = snapshot_lag(times, tau)
    rho = settings["rock"]["density_kg_m3"]
    snaps["c"] = stage_of_z(m, snaps["z_m"].to_numpy())
    snaps["mass_kg"] = rho * 4.0 / 3.0 * np.pi * snaps["radius_m"].to_numpy() ** 3
    res = settings["result"]
    return {"n": m.n_stages, "tau": tau, "snaps": snaps, "removed": removed, "times": times,
            "win": (res["window_start_s"], res["window_end_s"]),
            "moves": tagged_moves(m, snaps, removed, lag, rho), "dir": d}


def compartment_mass(r: dict) -> pd.DataFrame:
    """Mass (kg) per compartment 0..n at every snapshot time."""
    s = r["snaps"]
    s = s[(s["c"] >= 0) & (s["c"] <= r["n"])]
    return s.pivot_table(index="time_s", columns="c", values="mass_kg", aggfunc="sum", fill_value=0.0).reindex(
        index=r["times"], columns=range(r["n"] + 1), fill_value=0.0)


def in_window(r: dict, t: np.ndarray) -> np.ndarray:
    return (t >= r["win"][0] - 1e-9) & (t <= r["win"][1] + 1e-9)


def print_exits_and_chute(r: dict) -> None:
    s = r["snaps"]
    t_in = s.groupby("particle_id")["time_s"].min()
    t_out = r["removed"].set_index("particle_id")["time_s"].reindex(t_in.index)
    t_stage = s[s["c"] >= 1].groupby("particle_id")["time_s"].min().reindex(t_in.index)
    end = float(r["times"][-1])
    print("  fed in      n   left<=0.5s left<=1s  to_stage_1_median_s  mean_s")
    for a in np.arange(0.0, end - 1.5, 0.5):
        g = (t_in >= a) & (t_in < a + 0.5)
        stay = (t_out[g] - t_in[g]).fillna(np.inf)
        chute = (t_stage[g] - t_in[g]).dropna()
        print(f"  {a:3.1f}-{a + 0.5:3.1f} {int(g.sum()):5d} {float((stay <= 0.5).mean()):10.2f} "
              f"{float((stay <= 1.0).mean()):8.2f} {float(chute.median()):20.3f} {float(chute.mean()):7.3f}")


def fill_levels(r: dict, fill: pd.Series, bins: np.ndarray, rows: slice) -> tuple[np.ndarray, np.ndarray]:
    """Destinations measured at fill levels (bins below 1, tags before the window) and the window's at ``h = 1``."""
    mv = r["moves"]
    steady = destination_matrix(mv[in_window(r, mv["time_s"].to_numpy())], r["n"])
    h = mv["time_s"].map(fill).to_numpy()
    pre = mv["time_s"].to_numpy() < r["win"][0]
    hs, mats = [], []
    for a, b in itertools.pairwise([*bins, 1.0]):
        g = mv[pre & (h >= a) & (h < b)]
        if not len(g):
            continue
        p = steady.copy()
        got = destination_matrix(g, r["n"])
        ok = np.isfinite(got).all(axis=1)
        ok[np.setdiff1d(np.arange(r["n"] + 1), np.arange(r["n"] + 1)[rows])] = False
        p[ok] = got[ok]
        hs.append(float(np.average(h[pre & (h >= a) & (h < b)], weights=g["mass_kg"])))
        mats.append(p)
    return np.array([*hs, 1.0]), np.array([*mats, steady])


def march(levels: tuple[np.ndarray, np.ndarray], tau: float, driver: str) -> tuple[np.ndarray, ...]:
    """Single-class march from empty; the matrix is interpolated in the fill of ``driver`` ('mill' or 'inlet')."""
    hs, mats = levels
    q_ss = mats[-1][:, :-1]
    x_ss = chain_visits(mats[-1])
    steps = int(np.ceil(MARCH_S / tau))
    x = np.zeros(q_ss.shape[0])
    held, out = np.zeros(steps + 1), np.zeros(steps + 1)
    for k in range(1, steps + 1):
        h = x.sum() / x_ss.sum() if driver == "mill" else x[0] / x_ss[0]
        j = int(np.clip(np.searchsorted(hs, h) - 1, 0, len(hs) - 2)) if len(hs) > 1 else 0
        u = float(np.clip((h - hs[j]) / (hs[j + 1] - hs[j]), 0.0, 1.0)) if len(hs) > 1 else 1.0
        p = mats[j] * (1 - u) + mats[min(j + 1, len(hs) - 1)] * u
        out[k] = out[k - 1] + x @ p[:, -1]
        x = x @ p[:, :-1]
        x[0] += 1.0
        held[k] = x.sum()
    return np.arange(steps + 1) * tau, held, out


def split_levels(r: dict) -> tuple[np.ndarray, np.ndarray]:
    """Window destinations with the inlet zone split: 0 = not yet in a stage, n + 1 = thrown back up."""
    mv, n = r["moves"], r["n"]
    s = r["snaps"]
    first = mv["particle_id"].map(s[s["c"] >= 1].groupby("particle_id")["time_s"].min()).fillna(np.inf).to_numpy()
    fr = mv["stage_from"].to_numpy().copy()
    fr[(fr == 0) & (mv["time_s"].to_numpy() >= first)] = n + 1
    to = mv["stage_to"].to_numpy().copy()
    to[to == n + 1] = n + 2
    to[(to == 0) & (mv["t_to"].to_numpy() >= first)] = n + 1
    w = in_window(r, mv["time_s"].to_numpy())
    p = np.zeros((n + 2, n + 3))
    np.add.at(p, (fr[w], to[w]), mv["mass_kg"].to_numpy()[w])
    p /= np.where(p.sum(axis=1, keepdims=True) > 0, p.sum(axis=1, keepdims=True), 1.0)
    return np.array([1.0]), p[None]


def study(d: Path, bins: np.ndarray) -> dict[str, float]:
    """Print the study of one run; return the onset error (s) of each model (NaN if either never steady)."""
    r = load(d)
    n, tau = r["n"], r["tau"]
    print(f"{d}: tau {tau:.3f} s, window {r['win'][0]:.2f}-{r['win'][1]:.2f} s")
    print_exits_and_chute(r)
    cm = compartment_mass(r)
    w = in_window(r, cm.index.to_numpy())
    fill_c = cm / cm[w].mean()
    mill_fill = cm.sum(axis=1) / cm.sum(axis=1)[w].mean()
    one = fill_levels(r, mill_fill, np.zeros(0), slice(0, 0))
    t, _, _ = march(one, tau, "mill")
    q = one[1][-1][:, :-1]
    x, model_fill = np.zeros(n + 1), []
    x_ss = chain_visits(one[1][-1])
    for _ in range(1, t.size):
        x = x @ q
        x[0] += 1.0
        model_fill.append(x / x_ss)
    model_fill = np.array(model_fill)
    for ts in (0.5, 1.0, 2.0, 3.0):
        dem = fill_c.iloc[int(np.argmin(np.abs(cm.index.to_numpy() - ts)))].to_numpy()
        print(f"  fill at {ts:.1f} s (inlet, stages): DEM {np.round(dem, 2)} one-lag {np.round(model_fill[int(ts / tau) - 1], 2)}")
    levels = {"one_lag": (one, "mill"), "fill": (fill_levels(r, mill_fill, bins, slice(0, n + 1)), "mill"),
              "inlet_fill": (fill_levels(r, fill_c[0], bins, slice(0, 1)), "inlet"), "split": (split_levels(r), "mill")}
    hs, mats = levels["fill"][0]
    print("  mill fill h and chain residence of its destinations (s): "
          + ", ".join(f"{h:.2f}: {chain_residence_steps(p) * tau:.2f}" for h, p in zip(hs, mats, strict=True)))
    crit = RunSettings().criterion()
    v = saved_run_verdict(d, crit)
    dem_on = v.onset_s if v.onset_s is not None else np.nan
    errs = {}
    line = [f"DEM {dem_on:.2f}"]
    for name, (lv, driver) in levels.items():
        t, held, out = march(lv, tau, driver)
        found = first_steady(t, held, out, 1.0 / tau, crit)
        on = found[0] if found else np.nan
        errs[name] = on - dem_on
        line.append(f"{name} {on:.2f} (res {held[-1] * tau:.2f} s)")
    res_dem = cm.sum(axis=1)[w].mean() / saved_run_feed_kg_s(d)
    print(f"  onset (s): {'; '.join(line)}; DEM hold-up / feed {res_dem:.2f} s\n")
    return errs


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", type=Path, nargs="+")
    ap.add_argument("--fill-bins", type=float, nargs="+", default=[0.0, 0.2, 0.4, 0.6, 0.8])
    args = ap.parse_args()
    errs = [study(d, np.array(args.fill_bins)) for d in args.runs]
    summary = " ".join(f"onset_err_max_s_{m}={np.nanmax([abs(e[m]) for e in errs]):.2f}" for m in MODELS)
    print(f"runs={len(errs)} {summary}")


if __name__ == "__main__":
    main()
