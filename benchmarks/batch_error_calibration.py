"""How well the batch-means errors of one DEM run predict its real sampling error (issue 12).

Run::

    python benchmarks/batch_error_calibration.py --sizes-mm 10 6 --variant new \
        --results benchmarks/data/training_run_cost/seeds/seed*

Each ``--results`` folder holds runs of ``benchmarks/training_run_cost.py`` made
with another feed seed (``--seed K``; ``<size>mm_<variant>.json``). Over the
seeds at one size, the standard deviation of every stage statistic is the
single run's sampling error measured directly; the script prints its ratio to
the batch-means errors the runs report (the median over the seeds of each
statistic's reported error), per statistic family and over all statistics,
and for the streams the ratio of variances pooled over the stages (the
estimate that uses every seed's scatter at once). A ratio below 1 means the
batch means overstate the error, so an adaptive window stopped by them
measures longer than its targets need; above 1, they understate it.

Last line, per size: ``size_mm=<d> variant=<v> seeds=<k> ratio_median=<all statistics>
streams_ratio=<sqrt of the pooled variance ratio of the streams> window_s_median=<median window>``.
Reads only the result files; needs at least three seeds per size.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from msmill.stageparams import RunStatistics
from training_run_cost import _by_name

FAMILIES = ("kickback", "refeed", "pass_through", "primary_hit_probability", "secondary_lambda",
            "primary_velocity_mean_m_s", "secondary_velocity_mean_m_s")
STREAMS = ("kickback", "refeed", "pass_through")


def calibration(runs: list[RunStatistics]) -> dict[str, list[tuple[float, float]]]:
    """Per statistic family: ``(between-seed variance, median reported error squared)`` of every stage."""
    out: dict[str, list[tuple[float, float]]] = {f: [] for f in FAMILIES}
    for name, (x, e) in _by_name(runs).items():
        fam = name.split(" ", 2)[2]
        if fam in out and np.isfinite(e).sum() >= 3:
            out[fam].append((float(np.var(x, ddof=1)), float(np.nanmedian(e)) ** 2))
    return out


def calibration_ratios(runs: list[RunStatistics]) -> tuple[dict[str, list[float]], float, float]:
    """Between-seed sd over the median reported error: ``(per family, one per stage; median over every
    statistic; the streams' from the variance ratio pooled over stages and streams)`` (nan: none)."""
    cal = calibration(runs)
    per_family = {fam: [float(np.sqrt(v / e2)) for v, e2 in pairs if e2 > 0] for fam, pairs in cal.items()}
    per_family = {fam: r for fam, r in per_family.items() if r}
    every = [x for r in per_family.values() for x in r]
    streams = [p for fam in STREAMS for p in cal[fam] if p[1] > 0]
    pooled = float(np.sqrt(np.mean([v / e2 for v, e2 in streams]))) if streams else float("nan")
    return per_family, float(np.median(every)) if every else float("nan"), pooled


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes-mm", type=float, nargs="+", default=[10.0, 6.0])
    ap.add_argument("--variant", default="new", help="the runs' variant (file name <size>mm_<variant>.json)")
    ap.add_argument("--results", type=Path, nargs="+", required=True, help="--results folders of other seeds")
    args = ap.parse_args()
    for size in args.sizes_mm:
        files = [d / f"{size:g}mm_{args.variant}.json" for d in args.results]
        runs = [RunStatistics.from_json(f) for f in files if f.is_file()]
        if len(runs) < 3:
            print(f"{size:g} mm: {len(runs)} seeds of variant {args.variant!r}, at least 3 needed")
            continue
        per_family, ratio_median, pooled = calibration_ratios(runs)
        for fam, r in per_family.items():
            print(f"{size:g} mm {fam}: between-seed sd / batch-means error, median {np.median(r):.2f} "
                  f"over {len(r)} stages ({min(r):.2f}-{max(r):.2f})")
        windows = [r.measurement_window_s for r in runs]
        print(f"size_mm={size:g} variant={args.variant} seeds={len(runs)} ratio_median={ratio_median:.2f} "
              f"streams_ratio={pooled:.2f} window_s_median={np.median(windows):.2f}")


if __name__ == "__main__":
    main()
