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
The last line is ``runs=<n> with_filling=<m>``.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from datetime import UTC, datetime
from pathlib import Path

from msmill._version import __version__
from msmill.dem.mill.run import saved_run_filling_transport
from msmill.stageparams import RunStatistics, StageParameterTable


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


def commit() -> str:
    """The repository's HEAD commit, or 'unknown'."""
    try:
        return subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True, check=True,
                              cwd=Path(__file__).resolve().parent).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("table", type=Path)
    ap.add_argument("--runs-dir", type=Path, default=None, help="folder of the runs (size_<d>mm)")
    ap.add_argument("--out", type=Path, default=None, help="output table (default: overwrite TABLE)")
    args = ap.parse_args()
    table = StageParameterTable.from_json(args.table)
    raw = json.loads(args.table.read_text(encoding="utf-8"))  # edited as JSON: every other byte stays
    stamp = {"command": " ".join([Path(sys.executable).name, *sys.argv]), "script": "scripts/add_filling_transport.py",
             "msmill_version": __version__, "git_commit": commit(), "date_utc": datetime.now(UTC).isoformat()}
    n_fill = 0
    for r, doc in zip(table.runs, raw["runs"], strict=True):
        d = run_dir(r, args.runs_dir)
        ft = saved_run_filling_transport(d, r.characteristic_time_s) if d else None
        if ft is None:
            print(f"{r.design.size_mm:g} mm: no saved folder with a record before the window; left as it is")
            continue
        n_fill += 1
        print(f"{r.design.size_mm:g} mm ({d}): fill {[round(h, 2) for h in ft.fill]} "
              f"residence ratio {[round(x, 3) for x in ft.residence_ratio]}")
        doc["filling_transport"] = ft.model_dump(mode="json")
        doc.setdefault("provenance", {})["filling_transport_added_by"] = {**stamp, "source_dir": str(d)}
    raw.setdefault("provenance", {})["filling_transport"] = {
        **stamp, "note": "RunStatistics.filling_transport measured from the saved runs' snapshots before the "
        "measurement window (issue 15); no other field changed"}
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
