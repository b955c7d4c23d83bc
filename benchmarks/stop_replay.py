"""Replay the adaptive window's stop on a saved run: the errors a check would read at each window end.

A saved run (``msmill dem run`` folder, e.g. a stage-table run of ``scripts/build_stage_table.py``
with its raw events and snapshots) is measured again for windows from its saved start to each of
``--ends-s``, with ``--batches`` batch means, by the statistics code of the adaptive window's checks
(single Gaussian fits, no filling transport). For each window: the largest stream error and where it
is, and the targets of :class:`msmill.dem.mill.run.RunSettings` missed. So a stop rule can be judged
on one trajectory: a run's window should not depend on where the checks happen to fall, and the
error times the square root of the window length should stay about constant once the window is
longer than the streams' correlation time (issue 12, ``docs/mill-dem.md``).

Run: ``python benchmarks/stop_replay.py RUN_DIR --ends-s 1.3 1.5 1.7 1.9 2.1 2.3 2.5 [--batches 5 10]``.
Last line: ``run=<dir> batches=<b1>,<b2> first_end_meeting_targets_s=<t1>,<t2>`` (``nan``: none does).
"""

from __future__ import annotations

import argparse
import math
import warnings
from pathlib import Path

import numpy as np

from msmill.dem.mill.run import (
    RunSettings,
    check_stats_settings,
    load_raw,
    missed_targets,
    sampling_errors_reached,
    stats_from_raw,
)
from msmill.dem.mill.stats import StatsSettings

STREAMS = ("kickback", "refeed", "pass_through")


def replay(run_dir: Path, ends_s: list[float], n_batches: int, settings: RunSettings) -> float:
    """Print one line per window end; return the first end whose errors meet every target (nan: none)."""
    raw = load_raw(run_dir)  # read once for every window
    start_s = float(raw["settings"]["result"]["window_start_s"])
    quick = check_stats_settings(StatsSettings(n_batches=n_batches))
    first = math.nan
    for end in ends_s:
        ms = stats_from_raw(raw, quick, window_s=(start_s, end), source=str(run_dir))
        se = np.array([[st.sampling_error.get(k, np.nan) for k in STREAMS] for st in ms.run.stages])
        i, j = np.unravel_index(np.nanargmax(se), se.shape)
        missed = missed_targets(sampling_errors_reached(ms), settings.targets())
        print(f"batches {n_batches}, window {start_s:.2f}-{end:.2f} s: largest stream error {se[i, j]:.4f} "
              f"(stage {ms.run.stages[i].stage} {STREAMS[j]}), x sqrt(length) {se[i, j] * math.sqrt(end - start_s):.4f}; "
              f"missed: {', '.join(f'{k} {v:.3f}' for k, v in missed.items() if v is not None) or 'none'}",
              flush=True)
        if not missed and math.isnan(first):
            first = end
    return first


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run_dir", type=Path)
    ap.add_argument("--ends-s", type=float, nargs="+", required=True, help="window ends to check (s)")
    ap.add_argument("--batches", type=int, nargs="+", default=[5], help="batch counts of the errors")
    args = ap.parse_args()
    warnings.simplefilter("ignore")
    firsts = [replay(args.run_dir, args.ends_s, b, RunSettings()) for b in args.batches]
    print(f"run={args.run_dir} batches={','.join(map(str, args.batches))} "
          f"first_end_meeting_targets_s={','.join(f'{t:.2f}' for t in firsts)}")


if __name__ == "__main__":
    main()
