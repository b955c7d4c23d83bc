"""Feed-seed replicas of one design point with long fixed windows, for calibrating sampling errors (issue 36).

Each replica is a campaign-protocol slice run (:data:`msmill.pipeline.campaign.CAMPAIGN_RUN_DEFAULTS`:
stage-table start, window from the steady-state onset, at the earliest ``settle_s``) with a *fixed*
window of ``--measure-s`` (not adaptive: every replica measures the same length), the feed seed the only
difference. The statistics record every statistic's per-slice numerator and denominator
(``StatsSettings.series_slices``), so ``benchmarks/error_calibration.py`` can apply every estimator of
:mod:`msmill.sampling` to each replica and compare its errors with the scatter between replicas.

Per replica it writes ``EXPORT/<point>/seed<k>/``: ``statistics.json`` (the run's statistics, errors as
the runs report them today, provenance) and ``series.json`` (the slices, with the point, seed, window
and provenance). Runs are checkpointed in ``WORK`` and a replica whose export exists is skipped, so the
same command continues after a stop.

Run: ``NUMBA_NUM_THREADS=1 python scripts/error_replicas.py --size-mm 20 --feed-tph 30 --seeds 0 1 2 3 4 5
--measure-s 4``
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import asdict
from datetime import UTC, datetime
from pathlib import Path

from msmill._version import __version__
from msmill.dem.mill.run import RunSettings, git_commit, run_mill
from msmill.dem.mill.stats import StatsSettings
from msmill.machine import Machine, OperatingPoint
from msmill.pipeline.campaign import CAMPAIGN_RUN_DEFAULTS

ROOT = Path(__file__).resolve().parents[1]


def point_name(size_mm: float, feed_tph: float, speed_rpm: float, gate_deg: float) -> str:
    """Folder name of a design point."""
    return f"{size_mm:g}mm_{feed_tph:g}tph_{speed_rpm:g}rpm_{gate_deg:g}deg"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size-mm", type=float, required=True)
    ap.add_argument("--feed-tph", type=float, default=30.0)
    ap.add_argument("--speed-rpm", type=float, default=1500.0)
    ap.add_argument("--gate-deg", type=float, default=40.0)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4, 5])
    ap.add_argument("--measure-s", type=float, required=True, help="fixed window length (s)")
    ap.add_argument("--slices", type=int, default=64)
    ap.add_argument("--work", type=Path, default=Path("/work/error_replicas"))
    ap.add_argument("--export", type=Path, default=ROOT / "benchmarks" / "data" / "error_replicas")
    ap.add_argument("--checkpoint-every-s", type=float, default=600.0)
    ap.add_argument("--label", default="", help="appended to the point's folder name (replicas of one point with "
                    "another window are another set), e.g. 'long'")
    a = ap.parse_args(argv)
    point = point_name(a.size_mm, a.feed_tph, a.speed_rpm, a.gate_deg) + (f"_{a.label}" if a.label else "")
    op = OperatingPoint(feed_tph=a.feed_tph, speed_rpm=a.speed_rpm, gate_deg=a.gate_deg)
    stats_settings = StatsSettings(series_slices=a.slices)
    for seed in a.seeds:
        out = a.export / point / f"seed{seed}"
        if (out / "series.json").is_file():
            print(f"{point} seed {seed}: exported already")
            continue
        settings = RunSettings(**{**CAMPAIGN_RUN_DEFAULTS, "adaptive": False}, measure_s=a.measure_s, seed=seed,
                               checkpoint_every_s=a.checkpoint_every_s)
        run = run_mill(Machine.default(), op, size_mm=a.size_mm, mode="slice", settings=settings,
                       stats_settings=stats_settings, checkpoint_dir=a.work / point / f"seed{seed}")
        out.mkdir(parents=True, exist_ok=True)
        run.stats.run.to_json(out / "statistics.json")
        doc = {"kind": "msmill_error_replica", "format_version": 1, "point": point, "size_mm": a.size_mm,
               "feed_tph": a.feed_tph, "speed_rpm": a.speed_rpm, "gate_deg": a.gate_deg, "seed": seed,
               "outcome": run.outcome, "window_s": list(run.window_s), "wall_s": run.wall_s,
               "cpu_s": run.extra.get("cpu_s"), "n_slices": a.slices, "series": run.stats.series,
               "provenance": {"command": " ".join(["python", "scripts/error_replicas.py", *(argv or sys.argv[1:])]),
                              "msmill_version": __version__, "git_commit": git_commit(),
                              "date_utc": datetime.now(UTC).isoformat(timespec="seconds"),
                              "run_settings": asdict(settings), "stats_settings": asdict(stats_settings)}}
        (out / "series.json").write_text(json.dumps(doc, default=float) + "\n", encoding="utf-8")
        print(f"{point} seed {seed}: {run.outcome}, window {run.window_s[0]:.2f}-{run.window_s[1]:.2f} s, "
              f"wall {run.wall_s:.0f} s", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
