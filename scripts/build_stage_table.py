"""Build the default stage-parameter table from our own DEM slice runs.

Runs periodic-slice DEM simulations of the default machine at the default
operating point (upper stages 1500 rpm, bottom stage 3000 rpm, 30 t/h, gates
at 40 deg) for several rock sizes, and writes a
:class:`msmill.stageparams.StageParameterTable` to
``src/msmill/data/stage_parameters/default.json`` with its provenance
(command, msmill version, git commit, date, inputs, wall time) stored inside
the file and beside it (``default.provenance.json``). Each run's raw data and
plots go to ``--runs-dir`` (not shipped).

Run: ``python scripts/build_stage_table.py [--sizes-mm 10 14 20 30] [--measure-s 0.5]``;
``--restat`` recomputes the statistics (e.g. the secondary-impact count
families) from the raw data saved in ``--runs-dir`` without running the DEM.
``--protocol campaign`` runs each point as a campaign run does
(:data:`msmill.pipeline.campaign.CAMPAIGN_RUN_DEFAULTS`: the shipped table's
hold-up placed at t = 0, the adaptive window until the statistics' sampling
errors reach their targets) instead of the cold start and the fixed
``--measure-s`` window: one 0.5 s window measures a coarse-rock point's
transport to 10-20 % (docs/model.md 7.6). Such runs carry no filling curve
(the mill starts full); ``scripts/add_filling_transport.py --curves-from
COLD_TABLE --replicas FILE --reference window`` adds the cold runs' and the
replicas' curves, put on the long windows' reference. ``--min-measure-s``
lengthens the campaign protocol's shortest window (the 30 mm point's hold-up
wanders on a scale of seconds, which five batches of a 15 s window do not
see); ``--into TABLE`` puts the runs into an existing table in place of its
runs at the same sizes (the others and that table's provenance kept).
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

from msmill._version import __version__
from msmill.dem.mill.run import RunSettings, git_commit, run_mill, save_run
from msmill.machine import Machine, OperatingPoint
from msmill.plots.dem import plot_run
from msmill.stageparams import StageParameterTable

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_OUT = ROOT / "src" / "msmill" / "data" / "stage_parameters" / "default.json"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes-mm", type=float, nargs="+", default=[10.0, 14.0, 20.0, 30.0])
    ap.add_argument("--feed-tph", type=float, default=30.0)
    ap.add_argument("--speed-rpm", type=float, default=1500.0)
    ap.add_argument("--gate-deg", type=float, default=40.0)
    ap.add_argument("--measure-s", type=float, default=0.5)
    ap.add_argument("--protocol", choices=("cold", "campaign"), default="cold",
                    help="cold: empty start, fixed --measure-s window; campaign: warm start, adaptive window")
    ap.add_argument("--seed", type=int, default=0, help="feed seed of every run")
    ap.add_argument("--min-measure-s", type=float, default=None,
                    help="campaign protocol: the shortest window (s), e.g. a long one where the hold-up wanders "
                         "more slowly than the error targets see (30 mm)")
    ap.add_argument("--into", type=Path, default=None,
                    help="put the runs into this table, replacing its runs at the same sizes (others kept)")
    ap.add_argument("--max-time-s", type=float, default=None, help="time limit (s); default scales with the residence time")
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT)
    ap.add_argument("--runs-dir", type=Path, default=ROOT / "runs" / "stage_table")
    ap.add_argument("--restat", action="store_true",
                    help="do not run the DEM: recompute the statistics of the runs saved in --runs-dir")
    ap.add_argument("--stats-dir", type=Path, default=None,
                    help="with --restat: write each run's recomputed statistics.json to STATS_DIR/size_<d>mm "
                         "instead of back into its run folder")
    args = ap.parse_args()
    if args.into is not None:  # before any DEM: a bad table fails now, not after the runs
        from msmill.errors import MsmillError

        try:
            StageParameterTable.from_json(args.into)
        except (MsmillError, OSError) as exc:
            raise SystemExit(f"error: --into: {exc}") from None
    if args.restat:
        _restat(args)
        return

    machine, op, settings = _design(args)
    t_all = time.perf_counter()
    runs, per_run = [], []
    # cheapest (largest rocks) first; the table is rewritten after every run so a partial build is usable
    for size in sorted(args.sizes_mm, reverse=True):
        t0 = time.perf_counter()
        run = run_mill(machine, op, size_mm=size, mode="slice", settings=settings)
        save_run(run, args.runs_dir / f"size_{size:g}mm")
        plot_run(run, args.runs_dir / f"size_{size:g}mm")
        wall = time.perf_counter() - t0
        st = run.stats.run
        runs.append(st)
        kls = {f"stage{s.stage}": [s.primary_velocity_kl, s.secondary_lambda_kl, s.secondary_velocity_kl]
               for s in st.stages}
        per_run.append({"size_mm": size, "wall_s": round(wall, 1), "steady_state_time_s": st.steady_state_time_s,
                        "window_s": st.measurement_window_s, "characteristic_time_s": st.characteristic_time_s,
                        "dt_s": run.extra["dt_s"], "particles_end": run.extra["n_particles_end"],
                        "rock_youngs_modulus_used_pa": run.scene.info["rock_youngs_modulus_used_pa"],
                        "kl_primary_v_lambda_secondary_v": kls})
        print(json.dumps(per_run[-1]), flush=True)
        _write(args, machine, op, settings, runs, per_run, t_all)


def _design(args) -> tuple[Machine, OperatingPoint, RunSettings]:
    """The machine, operating point and run settings the table is built at."""
    op = OperatingPoint(feed_tph=args.feed_tph, speed_rpm=args.speed_rpm, gate_deg=args.gate_deg)
    protocol = {}
    if args.protocol == "campaign":
        from msmill.pipeline.campaign import CAMPAIGN_RUN_DEFAULTS

        protocol = dict(CAMPAIGN_RUN_DEFAULTS)
        if args.min_measure_s is not None:
            protocol |= {"min_measure_s": args.min_measure_s,
                         "max_measure_s": max(args.min_measure_s, protocol.get("max_measure_s", 0.0))}
    elif args.min_measure_s is not None:
        raise SystemExit("error: --min-measure-s: only with --protocol campaign (the cold protocol's window is "
                         "--measure-s)")
    return Machine.default(), op, RunSettings(max_time_s=args.max_time_s or 0.0, measure_s=args.measure_s,
                                              seed=args.seed, **protocol)


def _restat(args) -> None:
    """Recompute statistics from saved raw DEM data (events, snapshots) with the current code."""
    import tomllib

    from msmill.dem.mill.run import stats_from_dir

    machine, op, settings = _design(args)
    t_all = time.perf_counter()
    runs, per_run = [], []
    for size in sorted(args.sizes_mm, reverse=True):
        d = args.runs_dir / f"size_{size:g}mm"
        if not (d / "events.parquet").exists():
            print(f"skip {size:g} mm: no saved run in {d}", flush=True)
            continue
        saved = tomllib.loads((d / "run.toml").read_text(encoding="utf-8"))
        old = json.loads((d / "statistics.json").read_text(encoding="utf-8"))
        ms = stats_from_dir(d)
        st = ms.run.model_copy(update={"provenance": {**old.get("provenance", {}),
                                                      "statistics_recomputed_by": ms.run.provenance}})
        out_dir = d if args.stats_dir is None else args.stats_dir / d.name
        out_dir.mkdir(parents=True, exist_ok=True)
        st.to_json(out_dir / "statistics.json")
        runs.append(st)
        res = saved["result"]
        per_run.append({"size_mm": size, "wall_s": round(res["wall_s"], 1),
                        "steady_state_time_s": st.steady_state_time_s, "window_s": st.measurement_window_s,
                        "characteristic_time_s": st.characteristic_time_s, "dt_s": res["dt_s"],
                        "kl_primary_v_lambda_secondary_v": {
                            f"stage{s.stage}": [s.primary_velocity_kl, s.secondary_lambda_kl, s.secondary_velocity_kl]
                            for s in st.stages},
                        "secondary_count_family_kl": {
                            f"stage{s.stage}": [s.secondary_count_selection.chosen, s.secondary_count_selection.kl]
                            for s in st.stages if s.secondary_count_selection is not None}})
        print(json.dumps(per_run[-1]), flush=True)
    _write(args, machine, op, settings, runs, per_run, t_all, dem_wall_s=sum(r["wall_s"] for r in per_run))


def _write(args, machine, op, settings, runs, per_run, t_all, dem_wall_s: float | None = None) -> None:
    provenance = {
        "command": " ".join(shlex.quote(a) for a in [sys.executable, *sys.argv]),
        "script": "scripts/build_stage_table.py",
        "msmill_version": __version__,
        "git_commit": git_commit(),
        "date_utc": datetime.now(UTC).isoformat(timespec="seconds"),
        "host": platform.node(),
        "python": platform.python_version(),
        "inputs": {"machine": machine.model_dump(mode="json"), "mode": "slice", "sizes_mm": sorted(args.sizes_mm),
                   "feed_tph": op.feed_tph, "speed_rpm": op.speed_rpm, "bottom_speed_factor": op.bottom_speed_factor,
                   "stage_speeds_rpm": op.stage_speeds(machine.n_stages), "gate_deg": op.gate_deg,
                   "run_settings": settings.__dict__},
        "sizes_done_mm": sorted(r.design.size_mm for r in runs),
        "runs": per_run,
        "wall_s": round(dem_wall_s if dem_wall_s is not None else time.perf_counter() - t_all, 1),
        "statistics_recomputed_from_saved_runs": bool(args.restat),
        "note": "Produced by our own DEM (msmill.dem) periodic-slice runs; not hand-edited.",
    }
    if args.into is not None:  # the other sizes' runs kept as they are, with the table's provenance
        base = StageParameterTable.from_json(args.into)
        made = {round(r.design.size_mm, 6) for r in runs}
        kept = [r for r in base.runs if round(r.design.size_mm, 6) not in made]
        provenance["kept_runs"] = {"table": str(args.into), "sizes_mm": [r.design.size_mm for r in kept],
                                   "provenance": base.provenance}
        runs = kept + list(runs)
    table = StageParameterTable(runs=sorted(runs, key=lambda r: r.design.size_mm), provenance=provenance)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    table.to_json(args.out)
    args.out.with_suffix(".provenance.json").write_text(json.dumps(provenance, indent=2) + "\n", encoding="utf-8")
    print(f"wrote {args.out} ({len(runs)} runs, {provenance['wall_s']} s)", flush=True)


if __name__ == "__main__":
    main()
