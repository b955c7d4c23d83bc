"""Re-run the campaign's under-sampled DEM runs with a measurement window long enough for their fits.

Issue 14 measured that the surrogate's leave-one-out velocity KL is set by the
stages with few impacts (coarse rock, lower stages, windows capped at 1-1.5 s):
a fit of ``n`` impacts is off the true distribution by about ``p / (2 n)``.
This script finds every steady slice run in the campaign export whose fewest
impacts in any stage (primary or secondary) give an expected sampling KL above
``--target-kl`` and re-runs it at the same design point, seed and run settings,
except for the adaptive window: ``target_velocity_sampling_kl`` (plus the
other targets) with a cap of ``--max-measure-s``. The engine is deterministic,
so the re-run is the same run measured for longer.

Each re-run is saved to ``OUT/<content hash of the run it replaces>`` (the
folder layout ``msmill db ingest`` reads) and a line goes to
``OUT/replaces.jsonl`` naming the folder it replaces, so that
``scripts/rebuild_default_campaign.sh`` ingests the re-run in place of the old
run (two runs at one design point would make the leave-one-out figures
optimistic). Resumable: a folder whose ``statistics.json`` exists is skipped.
``--shard I/N`` runs every N-th run (one process per core). The runs that remove the
most sampling KL per CPU second go first (fewest impacts, cheapest).

Run: ``NUMBA_NUM_THREADS=1 python scripts/rerun_undersampled.py --out runs/rerun1 --shard 0/2``
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
import time
from dataclasses import fields, replace
from datetime import UTC, datetime
from pathlib import Path

from msmill._version import __version__
from msmill.dem.mill.run import VELOCITY_FIT_PARAMETERS, RunSettings, git_commit, run_mill, save_run
from msmill.machine import Machine, OperatingPoint
from msmill.pipeline.export import in_design_space
from msmill.stageparams import DesignPoint

ROOT = Path(__file__).resolve().parents[1]
EXPORT = ROOT / "src/msmill/data/campaigns/default"


def fewest_impacts(doc: dict) -> int:
    """Fewest primary or secondary impacts of any stage of an exported run."""
    st = doc["statistics"]["stages"]
    return int(min(min(s["n_primary_impacts"], s["n_secondary_impacts"]) for s in st))


def undersampled(export: Path, target_kl: float) -> list[dict]:
    """Exported steady slice training runs (in the design space) whose expected sampling KL ``p / (2 n)``
    exceeds ``target_kl``, the most KL removed per CPU second first."""
    n_needed = VELOCITY_FIT_PARAMETERS / (2 * target_kl)
    docs = [json.loads(p.read_text(encoding="utf-8")) for p in sorted(export.glob("run-*.json"))]
    out = [d for d in docs if d["statistics"].get("outcome") == "steady" and d["run"]["mode"] == "slice"
           and in_design_space(DesignPoint(**d["statistics"]["design"])) and fewest_impacts(d) < n_needed]
    # most sampling KL removed per CPU second first: the gain p/2n - p/2N over a cost ~ old wall x N/n
    # is proportional to (1 - n/N) / old wall, so the fewest impacts and the cheapest runs go first
    return sorted(out, key=lambda d: d["run"]["wall_s"] / max(1.0 - fewest_impacts(d) / n_needed, 1e-6))


def settings_for(doc: dict, target_kl: float, max_measure_s: float) -> RunSettings:
    """The old run's settings (fields this version knows) with the long adaptive window."""
    known = {f.name for f in fields(RunSettings)}
    old = {k: v for k, v in doc["run"]["run_settings"].items() if k in known}
    return replace(RunSettings(**old), adaptive=True, max_measure_s=max_measure_s,
                   target_velocity_sampling_kl=target_kl)


def rerun(doc: dict, out: Path, target_kl: float, max_measure_s: float) -> dict:
    """Re-run one exported run into ``out``; the line written to ``replaces.jsonl``."""
    machine = Machine.from_toml(doc["machine_toml"])
    des = doc["statistics"]["design"]
    op = OperatingPoint(feed_tph=des["feed_tph"], stage_speeds_rpm=des["stage_speeds_rpm"], gate_deg=des["gate_deg"])
    settings = settings_for(doc, target_kl, max_measure_s)
    t0 = time.perf_counter()
    run = run_mill(machine, op, size_mm=des["size_mm"], mode="slice", settings=settings)
    folder = out / doc["content_hash"][:16]
    save_run(run, folder)
    return {"folder": str(folder), "replaces": doc["run"]["source_path"], "replaces_content_hash": doc["content_hash"],
            "size_mm": des["size_mm"], "feed_tph": des["feed_tph"], "outcome": run.outcome,
            "fewest_impacts_before": fewest_impacts(doc),
            "window_s": round(run.window_s[1] - run.window_s[0], 3), "wall_s": round(time.perf_counter() - t0, 1),
            "sampling_error_reached": run.stats.run.sampling_error_reached}


def main(argv: list[str] | None = None) -> None:
    """Command line entry point."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--export", type=Path, default=EXPORT)
    ap.add_argument("--target-kl", type=float, default=RunSettings().target_velocity_sampling_kl)
    ap.add_argument("--max-measure-s", type=float, default=RunSettings().max_measure_s)
    ap.add_argument("--shard", default="0/1", help="I/N: run every N-th run starting at I")
    ap.add_argument("--list", action="store_true", help="list the runs to re-run and stop")
    a = ap.parse_args(argv)
    i, n = (int(v) for v in a.shard.split("/"))
    todo = undersampled(a.export, a.target_kl)
    if a.list:
        for d in todo:
            des = d["statistics"]["design"]
            print(f"{d['content_hash'][:16]} size_mm={des['size_mm']:.1f} feed_tph={des['feed_tph']:.1f} "
                  f"fewest_impacts={fewest_impacts(d)} wall_s={d['run']['wall_s']:.0f}")
        print(f"runs={len(todo)}")
        return
    a.out.mkdir(parents=True, exist_ok=True)
    meta = {"command": shlex.join([sys.executable, *sys.argv]), "msmill_version": __version__,
            "git_commit": git_commit(), "date_utc": datetime.now(UTC).isoformat(timespec="seconds"),
            "export": str(a.export), "target_velocity_sampling_kl": a.target_kl, "max_measure_s": a.max_measure_s,
            "runs": [d["content_hash"] for d in todo]}
    (a.out / f"rerun-{i}of{n}.json").write_text(json.dumps(meta, indent=1), encoding="utf-8")
    for doc in todo[i::n]:
        if (a.out / doc["content_hash"][:16] / "statistics.json").exists():
            continue
        line = rerun(doc, a.out, a.target_kl, a.max_measure_s)
        with (a.out / "replaces.jsonl").open("a", encoding="utf-8") as f:
            f.write(json.dumps(line) + "\n")
        print(json.dumps(line), flush=True)


if __name__ == "__main__":
    main()
