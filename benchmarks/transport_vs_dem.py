"""Transport of the mill model against the DEM runs it was built from (non-breaking rock).

Run::

    python benchmarks/transport_vs_dem.py [--table PATH] [--transport dem_matrix_fill] [--runs-dir DIR]
                                          [--campaign DIR|none] [--scatter N] [--filling table|own]

For every run of the stage-parameter table (default: the packaged
``msmill/data/stage_parameters/default.json``), and for every steady run of
the campaign export (default: the packaged ``msmill/data/campaigns/default``),
the mill model is run with rock that never breaks (``breakage="none"``,
``damage="none"``), one size class around the run's rock size, at the run's
operating point, with that run's statistics only (``RunProvider``). Compared
with the run's own figures:

* **mean residence time**: model = steady-state hold-up (inlet zone included)
  / feed rate; DEM = mean mass in the mill / mass out rate over the
  measurement window (Little's law, ``RunStatistics.residence_time_s``);
* **time to steady state, today's criterion** (the headline): one criterion,
  :func:`msmill.steadystate.first_steady` with the DEM's run settings
  (:meth:`msmill.dem.mill.run.RunSettings.criterion`: two windows of 0.65 s,
  product within 10 % of the feed, hold-up trend below 10 % of the feed,
  window means within 5 %), onset = start of the first passing pair of
  windows, applied to the DEM run's own saved time series (hold-up and product
  mass out, :func:`msmill.dem.mill.run.saved_run_verdict`, the test
  ``run_mill`` applies while it runs) and to the model's march from an empty
  mill (hold-up and cumulative product,
  :func:`msmill.model.result.time_to_steady_state`, the model's own
  ``time_to_steady_state_s``). The DEM series is found through the run's
  provenance (``source_dir``) or ``--runs-dir/size_<d>mm``; a run without it
  falls back to the recorded criterion below;
* **time to steady state, recorded criterion**: the figure stored with the
  run (``RunStatistics.steady_state_time_s``) against the model's series
  judged by the criterion the run recorded in its ``run_settings`` (runs made
  before the mass-balance criterion: the count-only test
  :func:`msmill.steadystate.count_only_onset` with the recorded window
  and tolerances).

**Replicas** (``--replicas FILE``, default ``benchmarks/data/transport_replicas.json``
when present, from ``scripts/transport_replicas.py``): the table's points re-run
with other feed seeds. One DEM run's onset is one draw of a random time (the
seed sets where every rock enters; coarse rock passes in bursts), while the
model's march is the ensemble's expectation. Where replicas exist the headline
compares the model (today's criterion) with the onset of the replicas'
**ensemble-mean** series (hold-up and cumulative product averaged over the
runs, then the same criterion) and the residence time with the runs' mean
(each by Little's law over its steady part, onset to the series' end, 2-4 s
instead of the table run's 0.5 s window); the
median and 5-95 % range of the single runs' onsets are printed beside it, and
the single-run comparison stays in the first table and the key
``tss_abs_err_max_single_s``.

A run whose DEM never met the criterion has no time to compare (``n/a``, left
out of the maximum and counted in ``runs_without_dem_steady_state``).
``--scatter N`` adds the 5-95 % range of the onset over ``N`` simulations of
the model's transport with the DEM run's number of rocks moving independently
(multinomial per compartment and step, at the speed each simulation's own fill
sets when the transport has a filling curve): the scatter a single DEM
realisation has from rock-count noise alone (collective pulsations add to it);
a line per run then gives the marches' median onset and the onset of their
ensemble-mean series beside the mean-field march's (docs/model.md 7.6).

With ``--transport dem_matrix_fill`` (the transport's speed depends on the
mill's fill, docs/model.md section 7.3) every run gets the filling curve
(``RunStatistics.filling_transport``) of ``--filling``: ``table`` (default)
the curve the table provider gives at the run's size (the table runs' curves
interpolated in log size, :func:`msmill.model.providers.filling_curves`; at a
table run's own size its own curve), ``pooled`` the table runs' curves pooled
into one for every size (:func:`msmill.model.providers.pooled_filling`, the
provider's rule before 2026-12-02), ``own`` the run's own; a run without the
field is measured from its saved DEM folder
(:func:`msmill.dem.mill.run.saved_run_filling_transport`).

**Warm-started tables** (the shipped one since 2026-12-03: long adaptive
windows from a filled mill): a warm run's own onset says nothing about filling
from empty, so its time to steady state comes from the replicas where there
are some, else from the cold run of the same point in ``--cold-table``
(default ``benchmarks/data/cold_stage_table.json``, the table shipped until
then; ``none``: n/a); its residence time stays its own.

Nothing is fitted here: the model reads the run's measured transport
(destinations one characteristic time later) and nothing else. The table's
summary is the line ``runs=<n> residence_rel_err_max=<x> tss_abs_err_max_s=<y> ...``,
the campaign's figures follow on the same (last) line with the prefix ``campaign_``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from msmill.dem.mill.run import RunSettings
from msmill.errors import MsmillInputError
from msmill.model import transport_check as tc
from msmill.model.providers import default_table_path
from msmill.model.submodels import DEFAULTS
from msmill.stageparams import StageParameterTable

DEFAULT_REPLICAS = Path(__file__).resolve().parent / "data" / "transport_replicas.json"
#: the stage table of cold 0.5 s-window runs shipped until 2026-12-03 (the onsets from empty of its points)
DEFAULT_COLD_TABLE = Path(__file__).resolve().parent / "data" / "cold_stage_table.json"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--table", type=Path, default=None, help="stage-parameter table (default: the packaged one)")
    ap.add_argument("--transport", default=DEFAULTS["transport"],
                    help=f"transport sub-model (default: the model's, {DEFAULTS['transport']})")
    ap.add_argument("--runs-dir", type=Path, default=None,
                    help="folder of the table's saved DEM runs (size_<d>mm); default: the runs' provenance")
    ap.add_argument("--campaign", default=None,
                    help="campaign export folder (default: the packaged one); 'none' to skip")
    ap.add_argument("--filling", choices=("table", "pooled", "own"), default="table",
                    help="dem_matrix_fill only: the table provider's curve at each run's size (default), the "
                         "table runs' curves pooled into one for every run, or each run's own")
    ap.add_argument("--scatter", type=int, default=0, help="rock-count scatter simulations per table run (0: none)")
    ap.add_argument("--replicas", default=None,
                    help="replica runs of the table's points (scripts/transport_replicas.py --export); "
                         "default benchmarks/data/transport_replicas.json when present; 'none' to skip")
    ap.add_argument("--cold-table", default=None,
                    help="for a table of warm-started runs: a table of cold runs at the same points whose recorded "
                         "onsets stand where there are no replicas (default: benchmarks/data/cold_stage_table.json; "
                         "none: n/a there)")
    ap.add_argument("--plot", type=Path, default=None,
                    help="draw the model's filling against the replicas' (hold-up, product rate) to this PNG")
    args = ap.parse_args()
    try:
        run(args)
    except MsmillInputError as e:
        raise SystemExit(f"error: {e}") from None


def run(args: argparse.Namespace) -> None:
    """The benchmark for parsed ``args``: prints the tables and the summary line."""
    path = args.table or default_table_path()
    table = StageParameterTable.from_json(path)
    print(f"table: {path}; transport: {args.transport}; rock: unbreakable; "
          f"criterion: {RunSettings().criterion()}")
    n_dest = sum(r.inlet_destinations is not None and all(st.destinations is not None for st in r.stages)
                 for r in table.runs)
    if args.transport == "dem_matrix" and n_dest < len(table.runs):
        print(f"note: {len(table.runs) - n_dest} of {len(table.runs)} runs have no one-lag destinations: "
              "dem_matrix falls back to their three streams there")
    curve_for = lambda run: None  # noqa: E731  (None: the run's own)
    if args.transport == "dem_matrix_fill":
        curve_for, lines = tc.filling_rule(table, args.filling, args.runs_dir)
        print("\n".join(lines))
    reps = [] if (args.replicas or "").lower() == "none" else tc.load_replicas(
        Path(args.replicas) if args.replicas else DEFAULT_REPLICAS)
    if reps:
        print(f"replicas: {len(reps)} runs at {sorted({round(float(r['size_mm']), 3) for r in reps})} mm")
    crit = RunSettings().criterion()
    cold = None
    if any(tc.warm_started(r) for r in table.runs) and (args.cold_table or "").lower() != "none":
        cold = StageParameterTable.from_json(Path(args.cold_table) if args.cold_table else DEFAULT_COLD_TABLE)
        print(f"warm-started table runs: onsets from empty from the replicas, else from the cold table's runs "
              f"({args.cold_table or DEFAULT_COLD_TABLE})")
    rows = [tc.attach_replicas(tc.compare(r, args.transport, args.runs_dir, args.scatter, curve_for(r),
                                    cold.run_at(r.design.size_mm) if cold else None), reps, crit)
            for r in table.runs]
    print("\n".join(tc.table_lines(rows)))
    summary = tc.summary(rows) + f" runs_with_destinations={n_dest}"
    if args.plot is not None:
        from msmill.plots.model import png_bytes
        from msmill.plots.validation import approach_plot

        args.plot.write_bytes(png_bytes(approach_plot(rows, reps), dpi=90))
        print(f"wrote {args.plot}")
    if (args.campaign or "").lower() != "none":
        from msmill.pipeline.export import default_export_dir, read_export, split_runs

        folder = Path(args.campaign) if args.campaign else default_export_dir()
        if folder.is_dir():
            slices, full = split_runs(read_export(folder))
            print(f"\ncampaign export: {folder} ({len(slices)} steady slice runs, {len(full)} steady full-mill runs)")
            rows = [tc.compare(e.statistics, args.transport, tc.export_raw_dir(e.path), 0, curve_for(e.statistics))
                    for e in slices + full]
            print("\n".join(tc.table_lines(rows)))
            summary += " " + tc.summary(rows, prefix="campaign_")
    print(summary)


if __name__ == "__main__":
    main()
