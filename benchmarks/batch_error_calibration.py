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

from msmill.sampling import seed_error_ratios
from msmill.stageparams import RunStatistics


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
        per_family, ratio_median, pooled = seed_error_ratios(runs)
        for fam, r in per_family.items():
            print(f"{size:g} mm {fam}: between-seed sd / batch-means error, median {np.median(r):.2f} "
                  f"over {len(r)} stages ({min(r):.2f}-{max(r):.2f})")
        windows = [r.measurement_window_s for r in runs]
        print(f"size_mm={size:g} variant={args.variant} seeds={len(runs)} ratio_median={ratio_median:.2f} "
              f"streams_ratio={pooled:.2f} window_s_median={np.median(windows):.2f}")


if __name__ == "__main__":
    main()
