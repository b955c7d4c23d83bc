"""Benchmark: what a campaign run costs at fine rock, from the committed exports (runs no DEM; issue 35).

Reads ``benchmarks/data/fine_rock_cost/<size>mm/cost.json`` (written by ``scripts/fine_rock_cost.py``:
one campaign-protocol slice run per size at 30 t/h, 1500 rpm, gates 40 deg) and prints per size the
wall and CPU time, rocks in the slice, time step, onset, settle and window lengths, the step kernels'
share and the checkpoints' cost. Then the cost model the active-learning planner uses
(:class:`msmill.surrogate.active.CostModel`, fitted to the training campaign's wall times) against the
measured points, and the model refitted with them, and the physical scaling from the coarsest
measured size (rock-steps: rocks in the slice x simulated time / time step).

A size without a protocol run's ``cost.json`` is taken from the training campaign's export where it
has a steady run within 5 % of that size (the cheapest such run: campaigns run fine rock where it costs
least, so at another point than the protocol's; the point is printed and ``point=campaign`` says so).
Its rocks are the window's mean hold-up over one rock's mass.

Last line: ``sizes_mm=<s,...> wall_h=<...> cpu_h=<...> rocks=<...> measured=<1|0,...> point=<protocol|campaign,...>``
(sizes with neither are left out and named on the line above).

Run: ``python benchmarks/fine_rock_cost.py [--data DIR] [--sizes-mm 4 3 2]``
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from msmill.pipeline.export import default_export_dir, read_export, split_runs
from msmill.surrogate.active import CostModel

DATA = Path(__file__).parent / "data" / "fine_rock_cost"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=DATA)
    ap.add_argument("--sizes-mm", type=float, nargs="+", default=[4.0, 3.0, 2.0])
    a = ap.parse_args(argv)
    rows, missing, partial = [], [], []
    train = [x.statistics for x in split_runs(read_export(default_export_dir()))[0]]
    for s in a.sizes_mm:
        f = a.data / f"{s:g}mm" / "cost.json"
        if f.is_file():
            rows.append(json.loads(f.read_text(encoding="utf-8")) | {"point": "protocol"})
            continue
        if (a.data / f"{s:g}mm" / "cost_partial.json").is_file():
            partial.append(json.loads((a.data / f"{s:g}mm" / "cost_partial.json").read_text(encoding="utf-8")))
        row = campaign_cost(train, s)
        if row is not None:
            rows.append(row)
        elif not partial or partial[-1]["size_mm"] != s:
            missing.append(s)
    print("size_mm  wall_h  cpu_h  parts  rocks  dt_us  onset_s  window_s  kernels  checkpoints(s)")
    for r in rows:
        ck = sum(p.get("checkpoint_s", 0.0) for p in r["parts"])
        nck = sum(p.get("checkpoints", 0) for p in r["parts"])
        onset = r["steady_state_time_s"]
        print(f"{r['size_mm']:7g}  {r['wall_s'] / 3600:6.3f}  {r['cpu_s'] / 3600:5.3f}  {len(r['parts']):5d}  "
              f"{r['rocks_in_slice_window_mean']:5.0f}  {r['dt_s'] * 1e6:5.2f}  "
              f"{'-' if onset is None else f'{onset:.2f}':>7}  {r['window_length_s']:8.2f}  "
              f"{r['step_kernels_share_of_wall']:7.2f}  {nck} ({ck:.1f})")
    estimates = []  # (size, cpu_s estimated, rocks) of partial runs
    for p in partial:
        # CPU per simulated second after the first chunk (which holds the scene build and the table start)
        tr = p["trace"]
        if len(tr) >= 3:
            rate = (tr[-1]["cpu_s"] - tr[0]["cpu_s"]) / (tr[-1]["sim_s"] - tr[0]["sim_s"])
            end = rows[0]["window_s"][1] if rows else float("nan")
            print(f"{p['size_mm']:g} mm: partial run to {tr[-1]['sim_s']:.3f} s simulated in {tr[-1]['wall_s'] / 3600:.2f} h "
                  f"wall, {np.mean([x['rocks'] for x in tr]):.0f} rocks: {rate / 3600:.2f} h of CPU per simulated "
                  f"second; a run to {end:.2f} s (the measured runs' end) would take about {rate * end / 3600:.2f} h "
                  "of CPU (estimated, not measured)")
            estimates.append((p["size_mm"], rate * end, float(np.mean([x["rocks"] for x in tr]))))
    if missing:
        print("no export yet for: " + ", ".join(f"{s:g} mm" for s in missing))
    for r in rows:
        if r["point"] == "campaign":
            print(f"{r['size_mm']:g} mm: the training campaign's run at {r['feed_tph']:.3g} t/h, {r['speed_rpm']:.0f} rpm, "
                  f"gate {r['gate_deg']:.3g} deg ({r['run']}), not the protocol point {POINT}")
    if rows:
        X = np.array([[r["size_mm"], r["feed_tph"], r["speed_rpm"], r["gate_deg"]] for r in rows])
        t = np.array([r["wall_s"] for r in rows])
        planner = CostModel.from_runs(train)  # what campaign.active_planner fits
        timed = [x for x in train if x.provenance.get("wall_s") and not any(x is r.get("statistics") for r in rows)]
        X_train = np.array([[x.design.size_mm, x.design.feed_tph, x.design.speed_rpm, x.design.gate_deg]
                            for x in timed])
        refit = CostModel.from_timings(np.vstack([X_train, X]), [x.provenance["wall_s"] for x in timed] + list(t))
        pred, pred2 = planner.predict_s(X), refit.predict_s(X)
        print(f"planner's cost model ({planner.n_timings} training-run timings): wall ~ size^{planner.coef[1]:.2f} "
              f"feed^{planner.coef[2]:.2f}; refitted with these {len(rows)}: size^{refit.coef[1]:.2f} "
              f"feed^{refit.coef[2]:.2f}")
        ref = rows[int(np.argmax(X[:, 0]))]
        for r, p1, p2 in zip(rows, pred, pred2, strict=True):
            # rock-steps from the coarsest measured size: rocks x simulated time / dt
            phys = (ref["wall_s"] * (r["rocks_in_slice_window_mean"] / ref["rocks_in_slice_window_mean"])
                    * (r["window_s"][1] / ref["window_s"][1]) * (ref["dt_s"] / r["dt_s"]))
            print(f"{r['size_mm']:g} mm: measured {r['wall_s'] / 3600:.3f} h wall, {r['cpu_s'] / 3600:.3f} h CPU; planner "
                  f"predicted {p1 / 3600:.3f} h ({p1 / r['cpu_s']:.2f}x CPU); refitted {p2 / 3600:.3f} h "
                  f"({p2 / r['cpu_s']:.2f}x CPU); rocks x steps from {ref['size_mm']:g} mm {phys / 3600:.3f} h "
                  f"({phys / r['wall_s']:.2f}x wall)")
    if rows and estimates:
        for size, cpu, _ in estimates:
            x = np.array([[size, rows[0]["feed_tph"], rows[0]["speed_rpm"], rows[0]["gate_deg"]]])
            print(f"{size:g} mm: estimated {cpu / 3600:.2f} h of CPU; planner predicted {planner.predict_s(x)[0] / 3600:.3f} h "
                  f"({planner.predict_s(x)[0] / cpu:.2f}x)")
    # a partial run's wall time is not given (a whole run was not made); its CPU time is the estimate above
    # and measured=0 says so
    # on the last line an estimate stands in only for a size without a measured run (protocol or campaign)
    estimates = [e for e in estimates if not any(abs(r["size_mm"] / e[0] - 1.0) <= 0.05 for r in rows)]
    print("sizes_mm=" + ",".join([f"{r['size_mm']:g}" for r in rows] + [f"{e[0]:g}" for e in estimates])
          + " wall_h=" + ",".join([f"{r['wall_s'] / 3600:.3f}" for r in rows] + ["nan"] * len(estimates))
          + " cpu_h=" + ",".join([f"{r['cpu_s'] / 3600:.3f}" for r in rows] + [f"{e[1] / 3600:.2f}" for e in estimates])
          + " rocks=" + ",".join([f"{r['rocks_in_slice_window_mean']:.0f}" for r in rows] + [f"{e[2]:.0f}" for e in estimates])
          + " measured=" + ",".join(["1"] * len(rows) + ["0"] * len(estimates))
          + " point=" + ",".join([r["point"] for r in rows] + ["protocol"] * len(estimates)))
    return 0


#: the protocol point of ``scripts/fine_rock_cost.py``
POINT = "30 t/h, 1500 rpm, gate 40 deg"


def campaign_cost(train: list, size_mm: float, rel: float = 0.05) -> dict | None:
    """The cost figures of the cheapest steady training run within ``rel`` of ``size_mm``, as a ``cost.json`` row."""
    near = [x for x in train if abs(x.design.size_mm / size_mm - 1.0) <= rel and x.provenance.get("cpu_s")]
    if not near:
        return None
    x = min(near, key=lambda r: float(r.provenance["cpu_s"]))
    p, d = x.provenance, x.design
    rock_kg = 2700.0 * np.pi / 6.0 * (d.size_mm / 1000.0) ** 3  # single-size feed of the campaign's rock
    hold = (p.get("stats") or {}).get("mean_holdup_kg")
    onset = x.steady_state_time_s
    end = (onset or 0.0) + (x.measurement_window_s or 0.0)
    return {"size_mm": d.size_mm, "feed_tph": d.feed_tph, "speed_rpm": d.speed_rpm, "gate_deg": d.gate_deg,
            "wall_s": float(p["wall_s"]), "cpu_s": float(p["cpu_s"]), "parts": p.get("parts", []),
            "rocks_in_slice_window_mean": float(hold) / rock_kg if hold else float("nan"), "dt_s": float(p["dt_s"]),
            "steady_state_time_s": onset, "window_length_s": x.measurement_window_s or 0.0,
            "window_s": [end - (x.measurement_window_s or 0.0), end], "step_kernels_share_of_wall": float("nan"),
            "point": "campaign", "run": p.get("date_utc", "?"), "statistics": x}


if __name__ == "__main__":
    raise SystemExit(main())
