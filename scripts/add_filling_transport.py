"""Add the DEM's filling transport to a stage-parameter table, measured from the table's saved runs.

Run::

    python scripts/add_filling_transport.py TABLE [--runs-dir DIR] [--out PATH]

For every run of the table (JSON, :class:`msmill.stageparams.StageParameterTable`)
whose saved DEM folder is found (``--runs-dir/size_<d>mm``, or the run's
provenance ``source_dir``), measures ``RunStatistics.filling_transport``
(:func:`msmill.dem.mill.run.saved_run_filling_transport`: one-lag destinations
of the tags taken before the measurement window, binned by the mill's fill, at
the run's own characteristic time) and writes the table with that field set
(nothing else changes). Each run's provenance gets ``filling_transport_added_by``
(command, version, commit, date, source folder) and the table's provenance a
note. Reads the run folders only; ``--out`` defaults to overwriting ``TABLE``.

``--replicas FILE`` (``scripts/transport_replicas.py --export``, runs of the
table's points with other feed seeds that carry their ``filling_transport``)
pools each run's curve with the replicas' at its size
(:func:`msmill.model.providers.pool_filling_curves`): one run's 0.4 s of tags
per fill bin is noise (docs/model.md 7.4), several seeds' are not. Window
residences are compared in seconds: a curve without a lag (exported before
2026-12-03) is on its replica's ``characteristic_time_s``, an own curve on its
run's. The run's
own curve (from its folder, or kept in its provenance as ``own_curve`` by an
earlier pooling, or the table's) is kept in the provenance, so pooling again
does not count it twice. The last line is ``runs=<n> with_filling=<m>``.

``--pool tags`` (replicas that recorded ``filling_tags``, 2026-12-03 on): at a
size where replicas carry their tags, the curve is made from their tags summed
over the runs (:func:`msmill.stageparams.filling_curve_from_tags`) against the
run's window, instead of averaging per-run curves: a compartment keeps its own
destinations in a fill bin only with enough tags, which one coarse run rarely
has in the emptiest bins (its ratio then falls back towards 1), while the
replicas together do. The run's own curve and untagged replicas are left out
there (the own curve is kept in the provenance).

``--curves-from OTHER`` takes the run's own curve from the run of the same
size in table ``OTHER`` instead (its ``own_curve`` or its curve), with that
run's window references (:meth:`msmill.stageparams.RunStatistics.window_reference`)
attached where the curve lacks them: for a table of warm-started runs, which
measure no filling (their mill starts full). ``--reference window`` puts the
pooled curve on the run's own window reference rather than on the mean of the
curves' short windows: for runs whose long adaptive window measures the steady
hold-up and chain residence better than any cold run's 0.5 s window does
(docs/model.md 7.6).
"""

from __future__ import annotations

import argparse
import json
import sys
from datetime import UTC, datetime
from pathlib import Path

from msmill._version import __version__
from msmill.dem.mill.run import saved_run_filling_transport
from msmill.model.providers import pool_filling_curves
from msmill.provenance import git_commit
from msmill.stageparams import (
    FillingTags,
    FillingTransport,
    RunStatistics,
    StageParameterTable,
    filling_curve_from_tags,
)


def run_dir(run: RunStatistics, runs_dir: Path | None) -> Path | None:
    """The run's saved DEM folder (``runs_dir/size_<d>mm`` first, then its provenance), or None."""
    prov = run.provenance or {}
    cands = [runs_dir / f"size_{run.design.size_mm:g}mm"] if runs_dir else []
    cands += [Path(p) for p in (prov.get("source_dir"), (prov.get("statistics_recomputed_by") or {}).get("source_dir"))
              if isinstance(p, str)]
    for d in cands:
        if all((d / f).is_file() for f in ("snapshots.parquet", "removed.parquet", "run.toml", "machine.toml")):
            return d
    return None


def own_curve(run: RunStatistics) -> FillingTransport | None:
    """The run's own filling curve: kept in its provenance by an earlier pooling, else its curve (None: none)."""
    own = ((run.provenance or {}).get("filling_transport_added_by") or {}).get("own_curve")
    return FillingTransport.model_validate(own) if own else run.filling_transport


def curve_of(table: StageParameterTable, size_mm: float) -> FillingTransport | None:
    """The own filling curve of ``table``'s run at ``size_mm`` with its window references (None: no such run)."""
    r = table.run_at(size_mm)
    ft = own_curve(r) if r is not None else None
    if ft is None:
        return None
    ref = r.window_reference()
    if (ft.window_holdup_kg is None or ft.window_residence_steps is None) and ref is not None:
        ft = ft.model_copy(update={"window_holdup_kg": ref[0], "window_residence_steps": ref[1]})
    return with_lag(ft, r.characteristic_time_s)


def with_lag(ft: FillingTransport, lag_s: float) -> FillingTransport:
    """``ft`` with its lag set to ``lag_s`` (the characteristic time of the run it was measured in) if it has none."""
    return ft if ft.lag_s is not None else ft.model_copy(update={"lag_s": float(lag_s)})


def pooled_tags_curve(run: RunStatistics, replicas: list[dict]) -> FillingTransport:
    """The filling curve of the replicas' tags summed (:func:`msmill.stageparams.filling_curve_from_tags`).

    Against ``run``'s window (mean hold-up and one-lag destinations); every replica's
    tags must be at the run's lag.
    """
    ref, p = run.window_reference(), run.destination_matrix()
    if ref is None or p is None:
        raise SystemExit(f"error: --pool tags: the {run.design.size_mm:g} mm run has no window reference "
                         "(mean hold-up and one-lag destinations)")
    tags = [FillingTags.model_validate(x["filling_tags"]) for x in replicas]
    off = [int(x["seed"]) for x, t in zip(replicas, tags, strict=True)
           if abs(t.lag_s / run.characteristic_time_s - 1.0) > 1e-3]
    if off:
        raise SystemExit(f"error: --pool tags: replicas {off} at {run.design.size_mm:g} mm took their tags at "
                         f"another lag than the run's {run.characteristic_time_s:.4f} s")
    ft = filling_curve_from_tags(tags, (ref[0], p))
    if ft is None:
        raise SystemExit(f"error: --pool tags: no tags below the {run.design.size_mm:g} mm run's steady hold-up")
    return ft


def commit() -> str:
    """The repository's HEAD commit, or 'unknown'."""
    return git_commit() or "unknown"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("table", type=Path)
    ap.add_argument("--runs-dir", type=Path, default=None, help="folder of the runs (size_<d>mm)")
    ap.add_argument("--out", type=Path, default=None, help="output table (default: overwrite TABLE)")
    ap.add_argument("--replicas", type=Path, default=None,
                    help="replica runs with filling curves (scripts/transport_replicas.py --export) to pool in")
    ap.add_argument("--curves-from", type=Path, default=None,
                    help="take each run's own curve from the run of the same size in this table")
    ap.add_argument("--reference", choices=("pooled", "window"), default="pooled",
                    help="the pooled curve's reference: the curves' mean (pooled) or this run's window")
    ap.add_argument("--pool", choices=("curves", "tags"), default="curves",
                    help="tags: at a size where replicas carry their tags, one curve from their tags summed "
                         "against the run's window (the run's own curve and untagged replicas left out)")
    args = ap.parse_args()
    other = StageParameterTable.from_json(args.curves_from) if args.curves_from else None
    replicas = json.loads(args.replicas.read_text(encoding="utf-8"))["replicas"] if args.replicas else []
    table = StageParameterTable.from_json(args.table)
    raw = json.loads(args.table.read_text(encoding="utf-8"))  # edited as JSON: every other byte stays
    stamp = {"command": " ".join([Path(sys.executable).name, *sys.argv]), "script": "scripts/add_filling_transport.py",
             "msmill_version": __version__, "git_commit": commit(), "date_utc": datetime.now(UTC).isoformat()}
    n_fill = 0
    for r, doc in zip(table.runs, raw["runs"], strict=True):
        d = run_dir(r, args.runs_dir)
        ft = saved_run_filling_transport(d, r.characteristic_time_s) if d else None
        earlier = (r.provenance or {}).get("filling_transport_added_by") or {}
        source = str(d) if ft is not None else earlier.get("source_dir")
        if ft is None and other is not None:
            ft = curve_of(other, r.design.size_mm)
            source = f"{args.curves_from} ({r.design.size_mm:g} mm run)" if ft else None
        elif ft is None and args.replicas:  # the run's own curve: kept by an earlier pooling, or the table's
            ft = own_curve(r)
        if ft is None:
            print(f"{r.design.size_mm:g} mm: no saved folder with a record before the window; left as it is")
            continue
        n_fill += 1
        added = {**stamp, "source_dir": source}
        mine = [x for x in replicas if abs(float(x["size_mm"]) - r.design.size_mm) < 1e-6 * r.design.size_mm
                and x.get("filling_transport")]
        reference = r.window_reference() if args.reference == "window" else None
        if args.reference == "window" and reference is None:
            raise SystemExit(f"error: --reference window: the {r.design.size_mm:g} mm run has no window reference "
                             "(mean hold-up and one-lag destinations)")
        tagged = [x for x in mine if x.get("filling_tags")] if args.pool == "tags" else []
        if tagged or mine or reference is not None:  # the own curve is kept (with tags: in the provenance only)
            added |= {"own_curve": ft.model_dump(mode="json"), "replicas": str(args.replicas),
                      "replica_seeds": [int(x["seed"]) for x in tagged or mine],
                      "reference": "window" if tagged else args.reference} | ({"pool": "tags"} if tagged else {})
        if tagged:
            ft = pooled_tags_curve(r, tagged)
        elif mine or reference is not None:
            reps = [with_lag(FillingTransport.model_validate(x["filling_transport"]), x["characteristic_time_s"])
                    for x in mine]
            ft = pool_filling_curves([with_lag(ft, r.characteristic_time_s), *reps], reference=reference,
                                     reference_lag_s=r.characteristic_time_s)
        how = f"the tags of {len(tagged)} replicas summed" if tagged else f"{len(mine)} replicas pooled in"
        print(f"{r.design.size_mm:g} mm ({source}; {how}): fill "
              f"{[round(h, 2) for h in ft.fill]} residence ratio {[round(x, 3) for x in ft.residence_ratio]}")
        doc["filling_transport"] = ft.model_dump(mode="json")
        doc.setdefault("provenance", {})["filling_transport_added_by"] = added
    note = ("RunStatistics.filling_transport measured from the saved runs' snapshots before the measurement window "
            "(issue 15)")
    if args.replicas:
        note += f", pooled with the filling curves of the replica runs in {args.replicas} at each run's size"
    raw.setdefault("provenance", {})["filling_transport"] = {**stamp, "note": note + "; no other field changed"}
    path = args.out or args.table
    text = json.dumps(raw, indent=1) + "\n"
    StageParameterTable.model_validate(raw)  # still a valid table
    path.write_text(text, encoding="utf-8")
    print(f"wrote {path}")
    side = path.with_name(path.stem + ".provenance.json")
    if side.is_file():  # the table's provenance beside it gets the same note
        sp = json.loads(side.read_text(encoding="utf-8"))
        sp["filling_transport"] = raw["provenance"]["filling_transport"]
        side.write_text(json.dumps(sp, indent=1) + "\n", encoding="utf-8")
        print(f"wrote {side}")
    print(f"runs={len(table.runs)} with_filling={n_fill}")


if __name__ == "__main__":
    main()
