"""Benchmark: sampling-error estimators against the scatter of feed-seed replicas (issue 36; runs no DEM).

Reads ``benchmarks/data/error_replicas/<point>/seed<k>/series.json`` (``scripts/error_replicas.py``:
campaign-protocol slice runs of one point with long fixed windows, the feed seed the only difference).
Every estimator of :mod:`msmill.sampling` gives each replica's standard error of each statistic from its
per-slice series; :func:`msmill.sampling.replica_z_scores` puts each replica's deviation from the
others' mean in units of those errors. With honest errors the z-scores have rms 1 (a little more for an
estimator of few degrees of freedom). Printed per estimator, kind of statistic and rock size: the rms z
and the mean degrees of freedom.

Kinds: ``streams`` (kickback, refeed, pass-through), ``hit`` (primary hit probability), ``velocity``
(mean primary and secondary impact speed), ``count`` (secondary count mean), ``holdup`` (mean hold-up).

Last line, for the chosen estimator (``--estimator``; default: the first of the list whose rms z lies
in 0.8-1.25 for every kind and size, else the one closest to it):
``estimator=<name> points=<n> replicas=<m> rms_z_streams=<a> rms_z_hit=<b> rms_z_velocity=<c>
rms_z_count=<d> rms_z_holdup=<e>`` (``replicas``: the fewest at any point).

Run: ``python benchmarks/error_calibration.py [--data DIR] [--estimator NAME]``
"""

from __future__ import annotations

import argparse
import json
from collections import defaultdict
from pathlib import Path

import numpy as np

from msmill.sampling import (
    AutocorrelationTime,
    BatchMeans,
    BlockBootstrap,
    ErrorEstimator,
    OverlappingBatchMeans,
    replica_z_scores,
)

DATA = Path(__file__).parent / "data" / "error_replicas"
KINDS = {"kickback": "streams", "refeed": "streams", "pass_through": "streams", "primary_hit_probability": "hit",
         "primary_velocity_mean_m_s": "velocity", "secondary_velocity_mean_m_s": "velocity",
         "secondary_lambda": "count", "holdup": "holdup"}
ORDER = ("streams", "hit", "velocity", "count", "holdup")
BAND = (0.8, 1.25)


def estimators() -> dict[str, ErrorEstimator]:
    """The candidates, today's first."""
    return {"batch_means_5": BatchMeans(5), "batch_means_10": BatchMeans(10), "batch_means_20": BatchMeans(20),
            "overlapping_batch_means": OverlappingBatchMeans(), "autocorrelation_time": AutocorrelationTime(),
            "block_bootstrap": BlockBootstrap(n_boot=200)}


def read_points(data: Path) -> dict[str, list[dict]]:
    """Replica documents per point (only steady replicas)."""
    out: dict[str, list[dict]] = defaultdict(list)
    for f in sorted(data.glob("*/seed*/series.json")):
        doc = json.loads(f.read_text(encoding="utf-8"))
        if doc.get("outcome") == "steady":
            out[doc["point"]].append(doc)
    return dict(out)


def calibrate(points: dict[str, list[dict]], est: ErrorEstimator) -> dict[tuple[str, float], tuple[float, float, int]]:
    """``(kind, size_mm) -> (rms z, mean dof, number of z-scores)`` over every point and statistic."""
    zs: dict[tuple[str, float], list[np.ndarray]] = defaultdict(list)
    dofs: dict[tuple[str, float], list[float]] = defaultdict(list)
    for docs in points.values():
        size = float(docs[0]["size_mm"])
        for key in docs[0]["series"]:
            kind = KINDS.get(key.split(".", 1)[-1])
            if kind is None or not all(key in d["series"] for d in docs):
                continue
            vals, ses = [], []
            for d in docs:
                num, den = (np.asarray(d["series"][key][c], dtype=float) for c in ("num", "den"))
                e = est.standard_error(num, den)
                vals.append(num.sum() / den.sum() if den.sum() > 0 else np.nan)
                ses.append(e.se)
                dofs[(kind, size)].append(e.dof)
            zs[(kind, size)].append(replica_z_scores(np.array(vals), np.array(ses)))
    out = {}
    for k, parts in zs.items():
        z = np.concatenate(parts)
        if z.size:
            out[k] = (float(np.sqrt(np.mean(z**2))), float(np.nanmean(dofs[k])), int(z.size))
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=DATA)
    ap.add_argument("--estimator", default=None, help="report this one on the last line")
    a = ap.parse_args(argv)
    points = read_points(a.data)
    if not points:
        print(f"no replica exports under {a.data} (scripts/error_replicas.py makes them)")
        print("estimator=none points=0 replicas=0")
        return 1
    for p, docs in points.items():
        print(f"point {p}: {len(docs)} steady replicas, windows "
              + ", ".join(f"{d['window_s'][1] - d['window_s'][0]:.2f}" for d in docs) + " s")
    results = {name: calibrate(points, est) for name, est in estimators().items()}
    sizes = sorted({s for r in results.values() for (_k, s) in r})
    print("estimator                 kind      " + "  ".join(f"{s:>9g}mm" for s in sizes) + "   (rms z / dof)")
    worst = {}
    for name, res in results.items():
        for kind in ORDER:
            cells = [res.get((kind, s)) for s in sizes]
            print(f"{name:25s} {kind:9s} " + "  ".join(
                f"{c[0]:5.2f}/{c[1]:4.0f}" if c else f"{'-':>11s}" for c in cells))
        devs = [abs(np.log(v[0])) for v in res.values()]
        inside = all(BAND[0] <= v[0] <= BAND[1] for v in res.values())
        worst[name] = (not inside, max(devs) if devs else np.inf)
    chosen = a.estimator or min(worst, key=lambda n: worst[n])
    res = results[chosen]
    per_kind = {}
    for kind in ORDER:
        z2 = [v[0] ** 2 * v[2] for (k, _s), v in res.items() if k == kind]
        n = [v[2] for (k, _s), v in res.items() if k == kind]
        per_kind[kind] = float(np.sqrt(sum(z2) / sum(n))) if n else float("nan")
    m = min(len(d) for d in points.values())
    print(f"chosen: {chosen} ({'every' if not worst[chosen][0] else 'not every'} kind and size in "
          f"{BAND[0]}-{BAND[1]})")
    print(f"estimator={chosen} points={len(points)} replicas={m} "
          + " ".join(f"rms_z_{k}={per_kind[k]:.3f}" for k in ORDER))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
