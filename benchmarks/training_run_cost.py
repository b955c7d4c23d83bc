"""Benchmark: cost of a DEM training run, cold fixed-window against warm adaptive (issue 12).

At each rock size (slice, 30 t/h, 1500 rpm upper stages, bottom at twice,
gates 40 deg) two runs of the same point are timed, alternating which goes
first from size to size:

* **old**: today's training run: empty mill, steady state by
  :mod:`msmill.steadystate`, a fixed 0.5 s measurement window;
* **new**: what a campaign run does by default (``--start table``,
  :data:`msmill.pipeline.campaign.CAMPAIGN_RUN_DEFAULTS`): the stage table's
  expected hold-up placed at t = 0 (``RunSettings.start = "table"``,
  :func:`msmill.dem.mill.warmstart.place_table_start`), then the adaptive
  window (``RunSettings.adaptive``) from the steady-state onset
  (``RunSettings.window_from = "onset"``); or (``--start run``) a warm start from the
  finished *seed* run of a nearby point (35 t/h, 1600 rpm, same size and gate;
  cold, 0.3 s window, its cost reported apart).

Both use the same steady-state criterion, so the comparison is of the start
and the window only. For every stage and statistic the surrogate regresses
(streams, hit probability, lambda, mean primary and secondary velocity) the
difference old - new is divided by its sampling error
``sqrt(se_old^2 + se_new^2)`` (batch means, ``StageStatistics.sampling_error``).
With n such comparisons of two samples of one law about ``0.046 n`` exceed 2
sigma by chance; the count beyond 2 sigma is printed beside the maximum.

Run: ``NUMBA_NUM_THREADS=1 python benchmarks/training_run_cost.py [--sizes-mm 20 10]``.
With ``--results DIR`` every finished run's statistics, wall time and summary are kept in DIR and a
run already there is not run again, so a long benchmark (a cold 6 mm run costs about an hour) resumes
after an interruption, and ``--variants old`` / ``new`` can run the two halves as separate jobs (the
summary lines are printed for the sizes with both).
**The old run's code** (``--old-tree DIR``): "today's" run of the issue is the
cold fixed-window run with the engine of the day the issue was filed. With
``--old-tree`` the old run is made by the msmill of another checkout (``git
worktree add DIR d8a5b5f``: the commit before the first of issue 12's changes,
whose engine is that of the filing and whose steady-state criterion is today's)
in a child process (``PYTHONPATH=DIR/src``), timed around its ``run_mill``
alone; its raw record is saved and its statistics recomputed by *this*
checkout's code (:func:`msmill.dem.mill.run.stats_from_dir`), so both runs'
statistics and sampling errors come from one statistics code. The engine's
changes since are bitwise identical, so the old tree's run is step for step
today's cold run (onset and window are checked against a kept current-code
``old`` run when there is one); the ratio then measures all three of the
issue's levers (start, window, step). The current-code ``old`` run, when kept,
gives the protocol-only ratio beside it (``protocol_cpu_ratio_median``).

**Replicas** (``--replicas DIR [DIR ...]``): one pair's deviation divides by the
batch-means errors of one run, which five batches of a 0.5 s window estimate
poorly (their own relative error is about 35 %). Each ``DIR`` is a ``--results``
folder of the same pair made with another feed seed (``--seed K``). Per size
with at least three of them, the between-seed standard deviation of each
statistic is the single run's sampling error measured directly; printed are
its ratio to the batch-means errors, the start dependence proper (the Welch t
of the old and new protocols' means over the seeds, as a normal deviate, with
the family-wise chance of the largest), and the main pair's deviations in units
of the replicas' standard deviations (``sqrt(sd_old^2 + sd_new^2)``).

Last line: ``points=<n> cost_ratio_median=<new/old wall> max_stat_dev_sigma=<x> cpu_ratio_median=<new/old
CPU time>`` (the last where every run has its CPU time); with ``--replicas`` also
``replica_seeds=<k> max_stat_dev_replica_sigma=<the main pairs' largest deviation in units of the
replicas' sd> start_dependence_z_max=<largest normal-equivalent Welch t> start_dependence_p_family=<p>
cost_ratio_median_over_seeds=<median over the sizes of (the median of the new run's wall over the main
seed and the replicas' seeds) / the old run's wall> cpu_ratio_median_over_seeds=<the same in CPU time>``:
the adaptive window's length, so the new run's cost, varies from seed to seed.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
import warnings
from functools import partial
from pathlib import Path

import numpy as np

from msmill.dem.mill.run import RunSettings, run_mill, stats_from_dir
from msmill.dem.mill.warmstart import WarmStart
from msmill.machine import Machine, OperatingPoint
from msmill.pipeline.campaign import CAMPAIGN_RUN_DEFAULTS
from msmill.sampling import paired_deviations, statistics_by_name
from msmill.stageparams import RunStatistics


def replica_pairs(dirs: list[Path], size_mm: float) -> list[tuple[RunStatistics, RunStatistics]]:
    """``(old, new)`` statistics at ``size_mm`` from ``--results`` folders of other feed seeds (both runs kept)."""
    out = []
    for d in dirs:
        o, n = d / f"{size_mm:g}mm_old.json", d / f"{size_mm:g}mm_new.json"
        if o.is_file() and n.is_file():
            out.append((RunStatistics.from_json(o), RunStatistics.from_json(n)))
    return out


def replica_new_costs(dirs: list[Path], size_mm: float) -> list[tuple[float, float | None]]:
    """``(wall, CPU)`` times (s) of the new runs at ``size_mm`` kept in ``--results`` folders of other seeds."""
    metas = [json.loads(m.read_text()) for m in (d / f"{size_mm:g}mm_new.meta.json" for d in dirs) if m.is_file()]
    return [(float(m["wall_s"]), m.get("cpu_s")) for m in metas]


def replica_summary(size_mm: float, reps: list[tuple[RunStatistics, RunStatistics]],
                    pair: tuple[RunStatistics, RunStatistics]) -> tuple[list[float], list[float]]:
    """Print the replicas' figures at one size; return (normal-equivalent Welch t of every statistic's
    old and new means, the main pair's deviations in units of the replicas' sd)."""
    from scipy import stats

    old, new = statistics_by_name([o for o, _ in reps]), statistics_by_name([n for _, n in reps])
    main_old, main_new = statistics_by_name([pair[0]]), statistics_by_name([pair[1]])
    k = len(reps)
    zs, devs, rows = [], [], []
    by_variant: dict[str, list[float]] = {"old": [], "new": []}
    for name, (xo, eo) in old.items():
        xn, en = new[name]
        so, sn = float(np.std(xo, ddof=1)), float(np.std(xn, ddof=1))
        if np.isfinite(eo).any() and np.isfinite(en).any():
            by_variant["old"].append(so / np.nanmedian(eo))
            by_variant["new"].append(sn / np.nanmedian(en))
        se = float(np.hypot(so, sn) / np.sqrt(k))
        if se <= 0:
            continue
        t = abs(float(xo.mean() - xn.mean())) / se
        nu = (so**2 + sn**2) ** 2 / ((so**4 + sn**4) / (k - 1)) if so + sn > 0 else k - 1
        z = float(stats.norm.isf(stats.t.sf(t, nu)))
        d = abs(float(main_old[name][0][0] - main_new[name][0][0])) / float(np.hypot(so, sn))
        zs.append(z)
        devs.append(d)
        rows.append((z, d, name, xo.mean(), so, xn.mean(), sn))
    rows.sort(reverse=True)
    ratios = [r for r in by_variant["old"] + by_variant["new"] if np.isfinite(r)]
    med = {v: float(np.nanmedian(r)) if r else float("nan") for v, r in by_variant.items()}
    print(f"{size_mm:g} mm replicas: {k} seeds; between-seed sd / batch-means error, median "
          f"{np.median(ratios):.2f} (5-95 % {np.percentile(ratios, 5):.2f}-{np.percentile(ratios, 95):.2f}; "
          f"old runs {med['old']:.2f}, new runs {med['new']:.2f}); "
          f"the main pair's largest deviation in units of the replicas' sd {max(devs):.2f} "
          f"({rows[int(np.argmax([r[1] for r in rows]))][2]})")
    for z, _d, name, mo, so, mn, sn in rows[:3]:
        print(f"  start dependence {name}: old {mo:.4g} (sd {so:.3g}), new {mn:.4g} (sd {sn:.3g}) over {k} seeds: "
              f"{z:.2f} sigma (normal equivalent of the Welch t)")
    return zs, devs


def timed(fn):
    """``(fn(), wall seconds)``."""
    t0 = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t0


def measured(fn) -> tuple[RunStatistics, float, float, str]:
    """``(statistics, wall_s, cpu_s, summary line)`` of ``fn()``, a run of this checkout. ``cpu_s`` is the
    process's CPU time over the run (one numba thread: its work, much less sensitive than the wall time
    to other jobs on a shared machine)."""
    cpu0 = time.process_time()
    run, wall = timed(fn)
    cpu = time.process_time() - cpu0
    return run.stats.run, wall, cpu, f"{run.summary(wall)}, cpu {cpu:.1f} s"


def cached_or_run(results: Path | None, tag: str, measure) -> tuple[RunStatistics, float, float | None, str]:
    """``measure()`` (``(statistics, wall_s, cpu_s, summary line)`` of a run), from ``results`` if it holds
    it, else measured and kept there."""
    if results is not None and (results / f"{tag}.meta.json").exists():
        meta = json.loads((results / f"{tag}.meta.json").read_text())
        return (RunStatistics.from_json(results / f"{tag}.json"), float(meta["wall_s"]), meta.get("cpu_s"),
                meta["summary"] + " (kept)")
    stats, wall, cpu, line = measure()
    if results is not None:
        stats.to_json(results / f"{tag}.json")
        meta = {"wall_s": wall, "cpu_s": cpu, "summary": line,
                "finished_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
                "load_average": [round(x, 2) for x in os.getloadavg()]}
        (results / f"{tag}.meta.json").write_text(json.dumps(meta, indent=1))  # written last: marks the run done
    return stats, wall, cpu, line


#: Run by the old tree's Python: the cold fixed-window run, timed around ``run_mill`` alone, saved raw.
_OLD_TREE_RUNNER = """
import json, sys, time, warnings
warnings.simplefilter("ignore")
import msmill
from msmill.dem.mill.run import RunSettings, run_mill, save_run
from msmill.machine import Machine, OperatingPoint
size, seed, feed, rpm, gate, out = float(sys.argv[1]), int(sys.argv[2]), *map(float, sys.argv[3:6]), sys.argv[6]
op = OperatingPoint(feed_tph=feed, speed_rpm=rpm, gate_deg=gate)
c0, t0 = time.process_time(), time.perf_counter()
run = run_mill(Machine.default(), op, size_mm=size, settings=RunSettings(measure_s=0.5, seed=seed))
wall, cpu = time.perf_counter() - t0, time.process_time() - c0
save_run(run, out)
print(json.dumps({"wall_s": wall, "cpu_s": cpu, "onset_s": run.steady_state_time_s, "window_s": list(run.window_s),
                  "outcome": run.outcome, "msmill": msmill.__file__, "git_commit": run.extra.get("git_commit")}))
"""


def old_tree_run(tree: Path, size_mm: float, seed: int, point: OperatingPoint) -> tuple[RunStatistics, float, float, str]:
    """The old protocol run by the msmill of checkout ``tree``; statistics recomputed by this checkout's code.

    Returns ``(statistics, wall_s, cpu_s, summary line)``; wall and CPU time are the child's, around its
    ``run_mill`` only (imports, saving and the recomputation are not counted).
    """
    raw = Path(tempfile.mkdtemp(prefix="msmill-old-tree-"))
    try:
        env = {**os.environ, "PYTHONPATH": str(tree / "src"), "NUMBA_NUM_THREADS": "1"}
        args = [str(size_mm), str(seed), str(point.feed_tph), str(point.speed_rpm), str(point.gate_deg), str(raw)]
        out = subprocess.run([sys.executable, "-c", _OLD_TREE_RUNNER, *args], env=env, check=True,
                             capture_output=True, text=True, cwd=tree)
        meta = json.loads(out.stdout.strip().splitlines()[-1])
        if not str(meta["msmill"]).startswith(str(tree.resolve())):
            raise SystemExit(f"error: --old-tree {tree}: the child imported msmill from {meta['msmill']}")
        stats = stats_from_dir(raw).run
    finally:
        shutil.rmtree(raw, ignore_errors=True)
    line = (f"{meta['outcome']}, onset {meta['onset_s']}, window {meta['window_s'][0]:.2f}-{meta['window_s'][1]:.2f} s, "
            f"wall {meta['wall_s']:.1f} s, cpu {meta['cpu_s']:.1f} s, code {meta['git_commit']}")
    return stats, float(meta["wall_s"]), float(meta["cpu_s"]), line


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes-mm", type=float, nargs="+", default=[20.0, 10.0, 6.0])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--results", type=Path, default=None,
                    help="keep each finished run here (statistics, wall, summary); runs already kept are reused")
    ap.add_argument("--variants", nargs="+", choices=("old", "new", "old_tree"), default=None,
                    help="run only these (with --results: the others may come from an earlier job); default old "
                         "and new, and old_tree with --old-tree")
    ap.add_argument("--start", choices=("table", "run"), default="table",
                    help="the new run's start: the stage table's hold-up (the campaign default) or a seed run's")
    ap.add_argument("--max-measure-s", type=float, default=None,
                    help="cap of the new run's adaptive window (s); default RunSettings'")
    ap.add_argument("--cold-adaptive", action="store_true",
                    help="also run a cold start with the adaptive window and compare it with the warm one")
    ap.add_argument("--replicas", type=Path, nargs="+", default=None,
                    help="--results folders of the same pair with other feed seeds: sampling errors measured "
                         "between seeds, and the start dependence over the seeds")
    ap.add_argument("--old-tree", type=Path, default=None,
                    help="make the old run with the msmill of this checkout (the code of the issue's day, "
                         "e.g. a worktree at d8a5b5f); statistics recomputed by this checkout")
    args = ap.parse_args()
    if args.variants is None:
        args.variants = ["old", "new"] + (["old_tree"] if args.old_tree is not None else [])
    if "old_tree" in args.variants and args.old_tree is None:
        raise SystemExit("error: --variants old_tree needs --old-tree DIR")
    if args.results:
        args.results.mkdir(parents=True, exist_ok=True)
    warnings.simplefilter("ignore")  # transient overlap warnings are not the point here
    m = Machine.default()
    point = OperatingPoint(feed_tph=30.0, speed_rpm=1500.0, gate_deg=40.0)
    near = OperatingPoint(feed_tph=35.0, speed_rpm=1600.0, gate_deg=40.0)
    ratios, cpu_ratios, protocol_cpu, worst, z_all = [], [], [], (0.0, ""), []
    seed_ratios, seed_cpu_ratios = [], []
    n_dev = n_over = 0
    rep_z, rep_dev, rep_seeds = [], [], []
    for i, size in enumerate(args.sizes_mm):
        start = None
        if args.start == "run":
            seed_run, seed_wall = timed(partial(run_mill, m, near, size_mm=size, settings=RunSettings(
                measure_s=0.3, seed=args.seed + 1)))
            start = WarmStart.from_run(seed_run)
            print(f"{size:g} mm seed (35 t/h, 1600 rpm): {seed_run.outcome}, t_ss {seed_run.steady_state_time_s}, "
                  f"end {seed_run.window_s[1]:.2f} s, wall {seed_wall:.1f} s")
            del seed_run

        old = partial(run_mill, m, point, size_mm=size, settings=RunSettings(measure_s=0.5, seed=args.seed))
        cap = {} if args.max_measure_s is None else {"max_measure_s": args.max_measure_s}
        protocol = {**CAMPAIGN_RUN_DEFAULTS, **({} if args.start == "table" else {"start": "empty"}), **cap}
        new = partial(run_mill, m, point, size_mm=size, settings=RunSettings(seed=args.seed, **protocol), start=start)

        old_name = "old" if args.old_tree is None else "old_tree"
        runs = {"old": partial(measured, old), "new": partial(measured, new)}
        if args.old_tree is not None:  # the same cold fixed-window run by the code of the day
            runs["old_tree"] = partial(old_tree_run, args.old_tree, size, args.seed, point)
        order = [old_name, "new"][:: 1 if i % 2 == 0 else -1]
        if args.old_tree is not None:  # today's engine on the old protocol: the protocol-only ratio
            order.append("old")
        if args.cold_adaptive:  # the error targets of "new" from an empty mill, window from detection
            runs["cold_adaptive"] = partial(measured, partial(run_mill, m, point, size_mm=size,
                                                              settings=RunSettings(adaptive=True, seed=args.seed)))
            order.append("cold_adaptive")
        res = {}
        for name in order:
            tag = f"{size:g}mm_{name}"
            kept = args.results is not None and (args.results / f"{tag}.meta.json").exists()
            if name in ("old", "new", "old_tree") and name not in args.variants and not kept:
                continue
            st, wall, cpu, line = cached_or_run(args.results, tag, runs[name])
            res[name] = (st, wall, cpu)
            print(f"{size:g} mm {name}: {line}")
        if old_name != "old" and "old" in res and old_name in res:
            same = res["old"][0].steady_state_time_s == res[old_name][0].steady_state_time_s and all(
                a.pass_through == b.pass_through for a, b in zip(res["old"][0].stages, res[old_name][0].stages,
                                                                 strict=True))
            cpu_p = ""
            if "new" in res and res["new"][2] and res["old"][2]:
                protocol_cpu.append(res["new"][2] / res["old"][2])
                cpu_p = f"CPU time {protocol_cpu[-1]:.3f}"
            print(f"{size:g} mm: old tree's run {'is' if same else 'is NOT'} step for step today's cold run "
                  f"(onset, pass-through); old tree / today's engine CPU time {res[old_name][2] / res['old'][2]:.3f}"
                  f"{'; protocol only, new / today-engine old: ' + cpu_p if cpu_p else ''}")
        if old_name not in res or "new" not in res:
            continue
        res["old"] = res[old_name]
        devs = paired_deviations(res["old"][0], res["new"][0])
        d_max = max(devs)
        n_dev += len(devs)
        n_over += sum(d > 2 for d, _ in devs)
        worst = max(worst, d_max)
        zs = paired_deviations(res["old"][0], res["new"][0], normal_equivalent=True)
        z_all += [z for z, _ in zs]
        if "cold_adaptive" in res:  # the same error targets, empty mill, window from detection
            dc = paired_deviations(res["cold_adaptive"][0], res["new"][0])
            ca = res["cold_adaptive"]
            cpu_ca = f", CPU time {res['new'][2] / ca[2]:.3f}" if res["new"][2] and ca[2] else ""
            print(f"{size:g} mm cold adaptive vs new: cost ratio new / cold adaptive {res['new'][1] / ca[1]:.3f}"
                  f"{cpu_ca}; max {max(dc)[0]:.2f} sigma ({max(dc)[1]}); "
                  f"{sum(d > 2 for d, _ in dc)} of {len(dc)} beyond 2 sigma")
        reps = replica_pairs(args.replicas or [], size)
        if len(reps) >= 3:
            z, d = replica_summary(size, reps, (res["old"][0], res["new"][0]))
            rep_z, rep_dev, rep_seeds = rep_z + z, rep_dev + d, [*rep_seeds, len(reps)]
        seed_costs = [(res["new"][1], res["new"][2]), *replica_new_costs(args.replicas or [], size)]
        if len(seed_costs) > 1:
            # the new run's window, so its cost, varies from seed to seed (the stop on batch-means errors)
            seed_ratios.append(float(np.median([w for w, _c in seed_costs])) / res["old"][1])
            cpus = [c for _w, c in seed_costs if c]
            if len(cpus) == len(seed_costs) and res["old"][2]:
                seed_cpu_ratios.append(float(np.median(cpus)) / res["old"][2])
            print(f"{size:g} mm new run over {len(seed_costs)} feed seeds: wall "
                  + ", ".join(f"{w:.1f}" for w, _c in seed_costs)
                  + f" s, median / old {seed_ratios[-1]:.3f}"
                  + (f" (CPU time {seed_cpu_ratios[-1]:.3f})" if len(cpus) == len(seed_costs) else ""))
        ratio = res["new"][1] / res["old"][1]
        ratios.append(ratio)
        if res["new"][2] and res["old"][2]:
            cpu_ratios.append(res["new"][2] / res["old"][2])
        cpu_txt = f" (CPU time {cpu_ratios[-1]:.3f})" if len(cpu_ratios) == len(ratios) else ""
        print(f"{size:g} mm: cost ratio {ratio:.3f}{cpu_txt}; max deviation {d_max[0]:.2f} sigma ({d_max[1]}); "
              f"{sum(d > 2 for d, _ in devs)} of {len(devs)} beyond 2 sigma")
    print(f"beyond 2 sigma: {n_over} of {n_dev} (about {0.046 * n_dev:.1f} expected by chance with exact errors); "
          f"worst: {worst[1]}")
    if z_all:
        from scipy import stats

        z_max = max(z_all)
        # chance that the largest of n independent normal-equivalent deviations is at least z_max
        p_family = 1.0 - (1.0 - 2.0 * stats.norm.sf(z_max)) ** len(z_all)
        print(f"normal-equivalent deviations (Student t, Welch dof, for the batch-means errors): largest "
              f"{z_max:.2f}, {sum(z > 2 for z in z_all)} of {len(z_all)} beyond 2 ({0.046 * len(z_all):.1f} "
              f"by chance); chance of a largest deviation at least this large among {len(z_all)} with no "
              f"start dependence: {p_family:.2f}; of none beyond 2: {(1 - 0.0455) ** len(z_all):.3f}")
    if not ratios:
        print("points=0 (no size with both runs yet)")
        return
    cpu_txt = (f" cpu_ratio_median={float(np.median(cpu_ratios)):.3f}" if len(cpu_ratios) == len(ratios)
               else "")
    if protocol_cpu:
        cpu_txt += f" protocol_cpu_ratio_median={float(np.median(protocol_cpu)):.3f}"
    if rep_z:
        from scipy import stats

        p_family = 1.0 - (1.0 - 2.0 * stats.norm.sf(max(rep_z))) ** len(rep_z)
        print(f"replicas: start dependence, largest of {len(rep_z)} normal-equivalent Welch t {max(rep_z):.2f} "
              f"({sum(z > 2 for z in rep_z)} beyond 2, {0.046 * len(rep_z):.1f} by chance; family-wise chance of "
              f"a largest this large {p_family:.2f}); main pairs in units of the replicas' sd: largest "
              f"{max(rep_dev):.2f}, {sum(d > 2 for d in rep_dev)} of {len(rep_dev)} beyond 2")
        cpu_txt += (f" replica_seeds={min(rep_seeds)} max_stat_dev_replica_sigma={max(rep_dev):.2f}"
                    f" start_dependence_z_max={max(rep_z):.2f} start_dependence_p_family={p_family:.2f}")
    if len(seed_ratios) == len(ratios):
        cpu_txt += f" cost_ratio_median_over_seeds={float(np.median(seed_ratios)):.3f}"
    if len(seed_cpu_ratios) == len(ratios):
        cpu_txt += f" cpu_ratio_median_over_seeds={float(np.median(seed_cpu_ratios)):.3f}"
    print(f"points={len(ratios)} cost_ratio_median={float(np.median(ratios)):.3f} max_stat_dev_sigma={worst[0]:.2f}"
          f"{cpu_txt}")


if __name__ == "__main__":
    main()
