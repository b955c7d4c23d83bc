"""Fit the between-run deviation of the DEM statistics to the feed-seed replicas (issue 36).

Reads ``benchmarks/data/error_replicas/<point>/seed<k>/series.json`` (``scripts/error_replicas.py``),
keeps replica sets of at least ``--min-replicas`` steady replicas, computes every replica's within-run
errors with :data:`msmill.sampling.RUN_ERROR_ESTIMATOR` and fits
:class:`msmill.sampling.BetweenRunVariance` (:func:`msmill.sampling.fit_between_run`) to all of them,
with the two corrections for data without series: the factor per kind from five batch means to the
run estimator (:func:`msmill.sampling.legacy_factors`), and the size law of the velocity-quantile
targets' scatter between replicas over their iid sampling variance
(:func:`msmill.surrogate.targets.quantile_scatter`, :func:`msmill.sampling.fit_variance_law`).
Writes ``src/msmill/data/sampling/between_run.json`` (the packaged fit the runs' errors use, with its
provenance: command, msmill version, git commit, date, the replica sets).

Run: ``python scripts/calibrate_sampling_errors.py``
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import replace
from datetime import UTC, datetime
from pathlib import Path

from msmill._version import __version__
from msmill.provenance import git_commit
from msmill.sampling import (
    RUN_ERROR_ESTIMATOR,
    BatchMeans,
    error_estimator,
    fit_between_run,
    fit_variance_law,
    legacy_factors,
    replica_sets,
)
from msmill.stageparams import RunStatistics
from msmill.surrogate.targets import quantile_scatter

ROOT = Path(__file__).resolve().parents[1]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=ROOT / "benchmarks" / "data" / "error_replicas")
    ap.add_argument("--min-replicas", type=int, default=6)
    ap.add_argument("--out", type=Path, default=ROOT / "src" / "msmill" / "data" / "sampling" / "between_run.json")
    a = ap.parse_args(argv)
    points: dict[str, list[dict]] = {}
    for f in sorted(a.data.glob("*/seed*/series.json")):
        doc = json.loads(f.read_text(encoding="utf-8"))
        if doc.get("outcome") == "steady":
            points.setdefault(doc["point"], []).append(doc)
    points = {p: d for p, d in points.items() if len(d) >= a.min_replicas}
    if not points:
        print(f"error: no replica sets of {a.min_replicas}+ steady replicas under {a.data}")
        return 2
    est = error_estimator(RUN_ERROR_ESTIMATOR)
    sets = [r for docs in points.values() for r in replica_sets(docs, est)]
    prov = {"command": " ".join(["python", "scripts/calibrate_sampling_errors.py", *(argv or sys.argv[1:])]),
            "msmill_version": __version__, "git_commit": git_commit(),
            "date_utc": datetime.now(UTC).isoformat(timespec="seconds"), "within_estimator": RUN_ERROR_ESTIMATOR,
            "replica_sets": {p: {"replicas": len(d), "size_mm": d[0]["size_mm"], "feed_tph": d[0]["feed_tph"],
                                 "window_s": round(d[0]["window_s"][1] - d[0]["window_s"][0], 3)}
                             for p, d in points.items()}}
    fit = fit_between_run(sets, provenance=prov)
    legacy = legacy_factors(sets, [r for docs in points.values() for r in replica_sets(docs, BatchMeans(5))])
    sizes, ratios, weights = [], [], []
    for p in points:
        runs = [RunStatistics.model_validate_json(f.read_text(encoding="utf-8"))
                for f in sorted((a.data / p).glob("seed*/statistics.json"))]
        r2, n = quantile_scatter(runs)
        sizes.append(points[p][0]["size_mm"])
        ratios.append(r2)
        weights.append(n)
        print(f"{p}: velocity-quantile targets scatter {r2:.3f} x their iid variance ({n} z-scores)")
    fit = replace(fit, legacy_factor=legacy, quantile_var_law=fit_variance_law(sizes, ratios, weights))
    a.out.parent.mkdir(parents=True, exist_ok=True)
    tmp = a.out.with_suffix(".tmp")
    tmp.write_text(json.dumps(fit.to_dict(), indent=1) + "\n", encoding="utf-8")
    tmp.replace(a.out)
    for k, (la, b) in fit.params.items():
        print(f"{k:9s} a={math.exp(la):.4g} beta={b:.2f} sets={fit.n_sets[k]}")
    print("legacy factors " + " ".join(f"{k}={v:.3f}" for k, v in legacy.items()))
    print(f"velocity-quantile variance factor c={math.exp(fit.quantile_var_law[0]):.3f} "
          f"beta={fit.quantile_var_law[1]:.2f}")
    print(f"written {a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
