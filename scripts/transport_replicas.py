"""Replica DEM runs of the default stage table's points: the DEM's own scatter of the filling dynamics.

Each run of the shipped stage table (``msmill/data/stage_parameters/default.json``)
is one realisation: its time to steady state is one draw of a random quantity
(the feed source's seed sets where every rock enters, and coarse rock pulses
through the mill in bursts). This script re-runs each table point (the default
machine, the table's operating point and rock size) with other feed seeds and
today's run settings, and records per replica what
``benchmarks/transport_vs_dem.py --replicas`` compares the model with:

* the onset of steady state by today's criterion
  (:meth:`msmill.dem.mill.run.RunSettings.criterion`, ``run_mill``'s own test),
  and the outcome;
* the mean residence time over the measurement window (Little's law,
  ``RunStatistics.residence_time_s``) and the characteristic time;
* the filling curve (``filling_transport``) and, since 2026-12-03, the tags it
  is made from (``filling_tags``: fine fill bins at the table run's lag), which
  ``scripts/add_filling_transport.py --pool tags`` sums over the replicas;
* the hold-up and cumulative product mass every ``--every-s`` up to ``--end-s``
  (the run goes on past its window without snapshots), a small series, so the
  criterion can be re-applied, to each run and to the replicas' ensemble mean,
  without raw files.

Nothing is written to the raw event files: only one JSON line per replica in
``OUT/replicas.jsonl`` (resumable: a (size, seed) already there is skipped),
and ``--export FILE`` gathers them with provenance (command, version, commit,
date, settings) into the file the benchmark reads.

Run (one core per process; cheapest sizes first)::

    NUMBA_NUM_THREADS=1 python scripts/transport_replicas.py --out /work/demruns/replicas \
        --sizes-mm 30 20 14 --seeds 1 2 3 4 5 6
    python scripts/transport_replicas.py --out /work/demruns/replicas \
        --export benchmarks/data/transport_replicas.json

A later session adds seeds in new folders and keeps the shipped replicas with
``--previous benchmarks/data/transport_replicas.json`` (their provenance nested).
"""

from __future__ import annotations

import argparse
import json
import platform
import shlex
import sys
import time
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def done_keys(path: Path) -> set[tuple[float, int]]:
    """``(size_mm, seed)`` of the replicas already in ``path``."""
    if not path.is_file():
        return set()
    rows = [json.loads(s) for s in path.read_text(encoding="utf-8").splitlines() if s.strip()]
    return {(round(float(r["size_mm"]), 6), int(r["seed"])) for r in rows}


def run_replica(size_mm: float, seed: int, measure_s: float, every_s: float, end_s: float) -> dict:
    """One replica of the table point at ``size_mm`` with feed seed ``seed``: its figures and short series.

    The run goes on (without snapshots) to ``end_s`` after its measurement
    window, so every replica's series covers the same times and the criterion
    can be applied to their ensemble mean.
    """
    from msmill.dem.mill.run import RunSettings, run_mill
    from msmill.machine import Machine
    from msmill.model.providers import default_table_path
    from msmill.stageparams import StageParameterTable

    table = StageParameterTable.from_json(default_table_path())
    run0 = min(table.runs, key=lambda r: abs(r.design.size_mm - size_mm))
    d = run0.design
    op = _operating_point(d)
    rs = RunSettings(measure_s=measure_s, seed=seed)
    t0 = time.perf_counter()
    run = run_mill(Machine.default(), op, size_mm=float(d.size_mm), mode="slice", settings=rs)
    sim = run.scene.sim
    if end_s > sim.time_s:
        sim.run(end_s - sim.time_s, dt_s=sim.dt_s, max_relative_speed_m_s=run.scene.max_impact_speed_m_s,
                safety=rs.safety, progress=False, timeseries_every_s=every_s / 2)
    ts = sim.timeseries()
    tags = filling_tags_at(run, run0.characteristic_time_s)
    grid = np.arange(0.0, float(ts["time_s"].iloc[-1]) + 1e-9, every_s)
    idx = np.unique(np.clip(np.searchsorted(ts["time_s"].to_numpy(), grid - 1e-9), 0, len(ts) - 1))
    st = run.stats.run
    return {
        "size_mm": round(float(d.size_mm), 6), "seed": int(seed), "outcome": run.outcome,
        "steady_state_time_s": run.steady_state_time_s, "residence_time_s": st.residence_time_s,
        "characteristic_time_s": st.characteristic_time_s, "mass_out_rate_kg_s": st.mass_out_rate_kg_s,
        "feed_kg_s": float(run.scene.feed_kg_s), "wall_s": round(time.perf_counter() - t0, 1),
        "series": {"time_s": np.round(ts["time_s"].to_numpy()[idx], 5).tolist(),
                   "holdup_kg": np.round(ts["mass_kg"].to_numpy()[idx], 5).tolist(),
                   "product_cum_kg": np.round(ts["mass_out_kg"].to_numpy()[idx], 5).tolist()},
        "end_s": float(sim.time_s), "git_commit": run.extra.get("git_commit"),
        # the tags of the filling phase binned by fill (RunStatistics.filling_transport): several seeds
        # of one point pool into a filling curve far less noisy than one run's
        "filling_transport": st.filling_transport.model_dump() if st.filling_transport is not None else None,
        # the same tags in fine fill bins at the table run's lag: replicas pool them before the chain
        # (scripts/add_filling_transport.py --pool tags), which clears the per-bin tag threshold at 30 mm
        "filling_tags": tags.model_dump() if tags is not None else None,
        "run_settings": {"measure_s": measure_s, "seed": seed, **{k: getattr(rs, k) for k in (
            "steady_window_s", "rel_tol", "trend_tol", "balance_tol", "chunk_s")}},
    }


def filling_tags_at(run, lag_s: float):
    """The run's filling tags (:func:`msmill.dem.mill.stats.filling_tags`) at the lag nearest ``lag_s``."""
    from msmill.dem.mill.stats import filling_tags, snapshot_lag

    return filling_tags(run.scene.machine, run.snapshots, run.removed, run.window_s,
                        snapshot_lag(run.snapshots["time_s"].to_numpy(), lag_s), run.scene.rock.density_kg_m3)


def _operating_point(design):
    from msmill.machine import OperatingPoint

    return OperatingPoint(feed_tph=design.feed_tph, stage_speeds_rpm=list(design.stage_speeds_rpm),
                          gate_deg=design.gate_deg)


def export(outs: list[Path], dest: Path, command: str, previous: Path | None = None) -> None:
    """Gather ``replicas.jsonl`` of the folders ``outs`` (e.g. one per core) with provenance into ``dest`` (JSON).

    ``previous``: an earlier export whose replicas are kept (a later session adds seeds without the
    earlier session's folders); its provenance is nested under ``previous``. A (size, seed) in both is
    an error, not a silent duplicate.
    """
    from msmill._version import __version__
    from msmill.dem.mill.run import git_commit

    rows = [json.loads(s) for out in outs
            for s in (out / "replicas.jsonl").read_text(encoding="utf-8").splitlines() if s.strip()]
    earlier = None
    if previous is not None:
        earlier = json.loads(previous.read_text(encoding="utf-8"))
        if earlier.get("kind") != "msmill_transport_replicas":
            raise SystemExit(f"error: --previous {previous}: not a transport-replicas file "
                             f"(kind {earlier.get('kind')!r})")
        new_keys = {(round(float(r["size_mm"]), 6), int(r["seed"])) for r in rows}
        clash = sorted(k for k in ((round(float(r["size_mm"]), 6), int(r["seed"])) for r in earlier["replicas"])
                       if k in new_keys)
        if clash:
            raise SystemExit(f"error: --previous {previous}: (size_mm, seed) {clash[0]} is also in --out; "
                             "each replica must come from one run")
        rows = [*earlier["replicas"], *rows]
    rows.sort(key=lambda r: (r["size_mm"], r["seed"]))
    doc = {"kind": "msmill_transport_replicas", "schema_version": 1,
           "description": "replica DEM slice runs (other feed seeds) of the default stage table's points; "
                          "per replica: onset of steady state by today's criterion, residence time, short series",
           "provenance": {"command": command, "msmill_version": __version__, "git_commit": git_commit(),
                          "date_utc": datetime.now(UTC).isoformat(timespec="seconds"),
                          "inputs": "msmill/data/stage_parameters/default.json (operating point and sizes)",
                          "source": [str(out / "replicas.jsonl") for out in outs], "python": platform.python_version(),
                          "run_commits": sorted({str(r.get("git_commit")) for r in rows}),
                          **({"previous": {"file": str(previous), **earlier["provenance"]}} if earlier else {})},
           "replicas": rows}
    dest.parent.mkdir(parents=True, exist_ok=True)
    dest.write_text(json.dumps(doc, separators=(",", ":")) + "\n", encoding="utf-8")  # compact: series dominate
    print(f"wrote {dest} ({len(rows)} replicas)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, nargs="+", required=True,
                    help="folder of replicas.jsonl (resumable); with --export, one or more folders to gather")
    ap.add_argument("--sizes-mm", type=float, nargs="*", default=[30.0, 20.0, 14.0, 10.0])
    ap.add_argument("--seeds", type=int, nargs="*", default=[1, 2, 3, 4, 5])
    ap.add_argument("--measure-s", type=float, default=0.5, help="measurement window (s), as the table's runs")
    ap.add_argument("--every-s", type=float, default=0.01, help="spacing of the saved series (s)")
    ap.add_argument("--end-s", type=float, default=5.5, help="mill time every replica's series reaches (s)")
    ap.add_argument("--export", type=Path, default=None, help="write the gathered replicas here and stop")
    ap.add_argument("--previous", type=Path, default=None,
                    help="with --export: an earlier export whose replicas are kept beside the folders'")
    args = ap.parse_args()
    command = shlex.join([sys.executable, *sys.argv])
    if args.export is not None:
        export(args.out, args.export, command, args.previous)
        return
    if len(args.out) != 1:
        raise SystemExit(f"error: --out: {len(args.out)} folders given; runs go to exactly one")
    out = args.out[0]
    out.mkdir(parents=True, exist_ok=True)
    path = out / "replicas.jsonl"
    for seed in args.seeds:  # every size at seed 1 before any at seed 2: a partial job covers all sizes
        for size in args.sizes_mm:
            if (round(float(size), 6), int(seed)) in done_keys(path):
                continue
            row = run_replica(size, seed, args.measure_s, args.every_s, args.end_s)
            with path.open("a", encoding="utf-8") as f:
                f.write(json.dumps(row) + "\n")
            print(json.dumps({k: v for k, v in row.items() if k not in ("series", "run_settings")}), flush=True)


if __name__ == "__main__":
    main()
