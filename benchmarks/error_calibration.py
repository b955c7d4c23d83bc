"""Benchmark: sampling-error estimators against the scatter of feed-seed replicas (issue 36; runs no DEM).

Reads ``benchmarks/data/error_replicas/<point>/seed<k>/series.json`` (``scripts/error_replicas.py``:
campaign-protocol slice runs of one point with long fixed windows, the feed seed the only difference).
Every estimator of :mod:`msmill.sampling` gives each replica's standard error of each statistic from its
per-slice series; :func:`msmill.sampling.replica_z_scores` puts each replica's deviation from the
others' mean in units of those errors. With honest errors the z-scores have rms 1 (a little more for an
estimator of few degrees of freedom). Printed per estimator, kind of statistic and replica set (point):
the rms z of the within-run errors alone, and the mean degrees of freedom.

Then the errors the runs report: the within-run estimator :data:`msmill.sampling.RUN_ERROR_ESTIMATOR`
plus the between-run deviation of :class:`msmill.sampling.BetweenRunVariance`, fitted to every replica
set but the one scored (leave one point out, so no set scores errors fitted to itself).

Kinds: ``streams`` (kickback, refeed, pass-through), ``hit`` (primary hit probability), ``velocity``
(mean primary and secondary impact speed), ``count`` (secondary count mean), ``holdup`` (mean hold-up).

Last line: ``estimator=<name> points=<n> replicas=<m> rms_z_streams=<a> rms_z_hit=<b> rms_z_velocity=<c>
rms_z_count=<d> rms_z_holdup=<e>`` (``points``: replica sets with at least ``--min-replicas``;
``replicas``: the fewest in any of them).

Run: ``python benchmarks/error_calibration.py [--data DIR] [--min-replicas 6]``
"""

from __future__ import annotations

import argparse
import json
from collections import defaultdict
from pathlib import Path

import numpy as np

from msmill.sampling import (
    RUN_ERROR_ESTIMATOR,
    AutocorrelationTime,
    BatchMeans,
    BetweenRunVariance,
    BlockBootstrap,
    ErrorEstimator,
    OverlappingBatchMeans,
    ReplicaSet,
    fit_between_run,
    replica_set_z_scores,
    replica_sets,
    statistic_kind,
)

DATA = Path(__file__).parent / "data" / "error_replicas"
ORDER = ("streams", "hit", "velocity", "count", "holdup")
BAND = (0.8, 1.25)


def estimators() -> dict[str, ErrorEstimator]:
    """The candidates, the old runs' choice (five batch means) first."""
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


def rms(z: list[np.ndarray]) -> float:
    a = np.concatenate(z) if z else np.zeros(0)
    return float(np.sqrt(np.mean(a**2))) if a.size else float("nan")


def table(title: str, cells: dict[str, dict[str, tuple[float, float]]], points: list[str]) -> None:
    print(title)
    print(f"  {'kind':9s} " + " ".join(f"{p[:22]:>22s}" for p in points))
    for kind in ORDER:
        print(f"  {kind:9s} " + " ".join(
            (f"{cells[p][kind][0]:13.2f}/{cells[p][kind][1]:4.0f} dof" if kind in cells[p] else f"{'-':>22s}")
            for p in points))


#: adaptive-window targets replayed on the series (``RunSettings`` defaults), kind -> (target, relative?)
TARGETS = {"streams": (0.02, False), "hit": (0.02, False), "velocity": (0.03, True), "count": (0.08, True)}


def window_needed(doc: dict, est: ErrorEstimator, between: BetweenRunVariance | None) -> float:
    """Shortest prefix of a replica's window (s, in eighths) at which every target is met (inf: never).

    A prefix of the slices is the window the adaptive check would have seen then (up to the tags near
    its end); the errors are ``est``'s, plus ``between`` when given.
    """
    n = int(doc["n_slices"])
    length = doc["window_s"][1] - doc["window_s"][0]
    size = float(doc["size_mm"])
    for k in range(n // 8, n + 1, n // 8):
        ok = True
        for key, sr in doc["series"].items():
            kind = statistic_kind(key)
            if kind not in TARGETS:
                continue
            num, den = np.asarray(sr["num"][:k], dtype=float), np.asarray(sr["den"][:k], dtype=float)
            if not den.sum() > 0:
                ok = False
                break
            e = est.standard_error(num, den)
            r = num.sum() / den.sum()
            se = between.total(kind, size, r, e).se if between else e.se
            target, rel = TARGETS[kind]
            if not se <= target * (abs(r) if rel else 1.0):
                ok = False
                break
        if ok:
            return length * k / n
    return float("inf")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=DATA)
    ap.add_argument("--min-replicas", type=int, default=6, help="replica sets with fewer are left out")
    a = ap.parse_args(argv)
    points = {p: d for p, d in read_points(a.data).items() if len(d) >= a.min_replicas}
    if not points:
        print(f"no replica sets of {a.min_replicas}+ under {a.data} (scripts/error_replicas.py makes them)")
        print("estimator=none points=0 replicas=0")
        return 1
    names = list(points)
    for p, docs in points.items():
        print(f"point {p}: {len(docs)} steady replicas, windows "
              + ", ".join(f"{d['window_s'][1] - d['window_s'][0]:.2f}" for d in docs) + " s")
    for name, est in estimators().items():
        cells: dict[str, dict[str, tuple[float, float]]] = {}
        for p, docs in points.items():
            by: dict[str, list[ReplicaSet]] = defaultdict(list)
            for r in replica_sets(docs, est):
                by[r.kind].append(r)
            cells[p] = {k: (rms([replica_set_z_scores(r) for r in v]), float(np.nanmean([r.dof_within for r in v])))
                        for k, v in by.items()}
        table(f"{name}: rms z of the within-run errors alone", cells, names)
    est = estimators()[RUN_ERROR_ESTIMATOR]
    sets = {p: replica_sets(docs, est) for p, docs in points.items()}
    z_kind: dict[str, list[np.ndarray]] = defaultdict(list)
    cells = {}
    for p in names:
        between = fit_between_run([r for q in names if q != p for r in sets[q]])
        by = defaultdict(list)
        for r in sets[p]:
            by[r.kind].append(replica_set_z_scores(r, between))
        cells[p] = {k: (rms(v), float("nan")) for k, v in by.items()}
        for k, v in by.items():
            z_kind[k].extend(v)
    table(f"{RUN_ERROR_ESTIMATOR} + between-run deviation fitted to the other points: rms z", cells, names)
    full = fit_between_run([r for v in sets.values() for r in v])
    print("between-run deviation fitted to every point: sigma_b = a (size / 20 mm)^beta")
    for k in ORDER:
        if k in full.params:
            la, b = full.params[k]
            c = full.cov[k]
            print(f"  {k:9s} a = {np.exp(la):.4g}{' (relative)' if k in ('velocity', 'count', 'holdup') else ''} "
                  f"(x/ {np.exp(np.sqrt(c[0][0])):.2f}), beta = {b:.2f} +- {np.sqrt(c[1][1]):.2f}, "
                  f"{full.n_sets[k]} sets")
    print("window the adaptive targets need, replayed on each replica's series (median over replicas, s; "
          "'>' the whole window was too short)")
    for p, docs in points.items():
        old = [window_needed(d, BatchMeans(5), None) for d in docs]
        new = [window_needed(d, est, full) for d in docs]
        span = docs[0]["window_s"][1] - docs[0]["window_s"][0]
        old_s, new_s = (f"{np.median(v):.2f}" if np.isfinite(np.median(v)) else f">{span:.2f}" for v in (old, new))
        print(f"  {p:34s} five batch means {old_s:>6s}   {RUN_ERROR_ESTIMATOR} + between-run {new_s:>6s}")
    per_kind = {k: rms(z_kind[k]) for k in ORDER}
    inside = all(BAND[0] <= v <= BAND[1] for v in per_kind.values())
    print(f"every kind {'inside' if inside else 'NOT inside'} {BAND[0]}-{BAND[1]} (leave one point out)")
    m = min(len(d) for d in points.values())
    print(f"estimator={RUN_ERROR_ESTIMATOR}+between_run points={len(points)} replicas={m} "
          + " ".join(f"rms_z_{k}={per_kind[k]:.3f}" for k in ORDER))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
