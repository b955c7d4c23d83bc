"""Judge stop rules of the adaptive window over several feed seeds: their cost and their calibration (issue 12).

Three subcommands.

``run``: a new-protocol run (campaign defaults: table start, window from the onset) but with a
*fixed* long window (``--measure-s``), saved raw, plus a trace of wall and CPU time against mill
time (``trace.csv``, one row per engine chunk). Up to the stop, an adaptive run follows the same
trajectory, so one long run stands for every stop rule::

    python benchmarks/stop_study.py run --size-mm 6 --seed 3 --measure-s 2.4 --out RUNS/6mm_seed3

``replay``: for each saved run and each stop rule (``--batches``: the batch count of the check's
errors; ``--settle-s``: where the window starts), the checks of :func:`msmill.dem.mill.run.run_mill` are replayed at the times
the adaptive loop would make them (from ``min_measure_s``, then every ``max(check_every_s, a
quarter of the window so far)``); the first check whose errors meet the targets of
:class:`msmill.dem.mill.run.RunSettings` is the stop. Its cost is the trace's CPU time at the stop
plus the replayed checks' own CPU time. Over the seeds: the median cost, and for the statistics at
the stop the between-seed standard deviation over the errors the runs report (a ratio below 1:
the errors overstate the real scatter, so the window is longer than its targets need)::

    python benchmarks/stop_study.py replay RUNS/6mm_seed* --batches 5 10 --settle-s 0.6 1.0

``coherence``: the part of the runs' product-rate and hold-up fluctuations that every seed shares
(:func:`coherence`)::

    python benchmarks/stop_study.py coherence RUNS/6mm_seed* --from-s 0.9

Last line per rule: ``rule=<name> runs=<k> cpu_s_median=<s> window_end_s_median=<s>
ratio_median=<between-seed sd / reported error, median over the statistics>
streams_ratio=<the same for the streams, from the variance ratio pooled over stages and streams>``.
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
import time
import warnings
from dataclasses import asdict, dataclass
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from msmill._version import __version__
from msmill.dem.mill.run import (
    RunSettings,
    check_stats_settings,
    git_commit,
    load_raw,
    missed_targets,
    run_mill,
    sampling_errors_reached,
    save_run,
    stats_from_raw,
)
from msmill.dem.mill.stats import StatsSettings
from msmill.machine import Machine, OperatingPoint
from msmill.pipeline.campaign import CAMPAIGN_RUN_DEFAULTS
from msmill.sampling import seed_error_ratios

#: the training-run benchmark's design point (benchmarks/training_run_cost.py)
POINT = OperatingPoint(feed_tph=30.0, speed_rpm=1500.0, gate_deg=40.0)


def run_one(size_mm: float, seed: int, measure_s: float, out: Path, start: str = "table") -> None:
    """A fixed-window new-protocol run saved raw to ``out``, with its wall/CPU trace.

    ``start = "empty"``: the same from an empty mill (whether what the window sees comes from the start).
    """
    settings = RunSettings(seed=seed, **{**CAMPAIGN_RUN_DEFAULTS, "adaptive": False, "start": start},
                           measure_s=measure_s)
    rows: list[tuple[float, float, float, str]] = []
    wall0, cpu0 = time.perf_counter(), time.process_time()

    def trace(t_s: float, _n: int, phase: str) -> None:
        rows.append((t_s, time.perf_counter() - wall0, time.process_time() - cpu0, phase))

    run = run_mill(Machine.default(), POINT, size_mm=size_mm, settings=settings, progress=trace)
    save_run(run, out)
    with open(out / "trace.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["time_s", "wall_s", "cpu_s", "phase"])
        w.writerows((f"{t:.6f}", f"{a:.3f}", f"{c:.3f}", p) for t, a, c, p in rows)
    prov = {"command": " ".join([Path(sys.argv[0]).name, *sys.argv[1:]]), "msmill_version": __version__,
            "git_commit": git_commit(), "date_utc": datetime.now(UTC).isoformat(timespec="seconds"),
            "size_mm": size_mm, "seed": seed, "point": {"feed_tph": POINT.feed_tph, "speed_rpm": POINT.upper_speed_rpm,
                                                         "gate_deg": POINT.gate_deg},
            "run_settings": asdict(settings), "window_s": list(run.window_s), "wall_s": run.wall_s,
            "onset_s": run.steady_state_time_s, "outcome": run.outcome}
    (out / "study.json").write_text(json.dumps(prov, indent=1))
    print(f"{size_mm:g} mm seed {seed}: {run.outcome}, onset {run.steady_state_time_s}, window "
          f"{run.window_s[0]:.2f}-{run.window_s[1]:.2f} s, wall {run.wall_s:.0f} s", flush=True)


@dataclass
class Stop:
    """Where a stop rule ends one saved run."""

    window_end_s: float
    cpu_s: float  # the trace's CPU time at the stop plus the replayed checks' own
    wall_s: float  # the same in wall time
    checks: int
    censored: bool  # the record ended before the targets were met (the stop is the record's end)
    stats: object  # msmill.stageparams.RunStatistics of the window to the stop


def read_trace(run_dir: Path) -> np.ndarray:
    """``(time_s, wall_s, cpu_s)`` rows of a run's ``trace.csv``."""
    with open(run_dir / "trace.csv") as f:
        rows = list(csv.DictReader(f))
    return np.array([[float(r["time_s"]), float(r["wall_s"]), float(r["cpu_s"])] for r in rows])


def replay_stop(raw: dict, trace: np.ndarray, n_batches: int, rs: RunSettings, settle_s: float | None = None) -> Stop:
    """The adaptive loop of :func:`msmill.dem.mill.run.run_mill` replayed on a fixed-window record.

    The record's chunks after steady-state detection are the times the loop could check; a check is
    made where the loop would make it, with errors from ``n_batches`` batch means, and the first one
    meeting every target stops the window. ``settle_s``: start the window there instead of where
    the run started it (a window from the onset starts at ``max(onset, settle_s)``).
    """
    res = raw["settings"]["result"]
    start_s, detected_s, end_s = (float(res[k]) for k in ("window_start_s", "steady_state_detected_s",
                                                            "window_end_s"))
    if settle_s is not None:
        start_s = max(float(res["steady_state_time_s"]), settle_s)
    quick = check_stats_settings(StatsSettings(n_batches=n_batches))
    times = trace[trace[:, 0] >= detected_s - 1e-9]
    t_check = start_s + rs.min_measure_s
    spent_cpu = spent_wall = 0.0
    n = 0
    for t, wall, cpu in times:
        if not rs.check_due(t_check, t) and t < end_s - 1e-9:
            continue
        t_check = rs.next_check_s(start_s, t)
        c0, w0 = time.process_time(), time.perf_counter()
        ms = stats_from_raw(raw, quick, window_s=(start_s, t))
        missed = missed_targets(sampling_errors_reached(ms), rs.targets())
        spent_cpu += time.process_time() - c0
        spent_wall += time.perf_counter() - w0
        n += 1
        if not missed or t >= end_s - 1e-9:
            return Stop(float(t), float(cpu) + spent_cpu, float(wall) + spent_wall, n, bool(missed), ms.run)
    raise ValueError("trace ends before the record")


def replay(dirs: list[Path], batches: list[int], settles: list[float | None]) -> None:
    """Print every run's stop per rule (batch count, window start) and the summary line per rule."""
    rs = RunSettings()
    rules = [(b, st) for st in settles for b in batches]
    stops: dict[tuple[int, float | None], list[Stop]] = {r: [] for r in rules}
    for d in dirs:
        raw, trace = load_raw(d), read_trace(d)
        for b, st in rules:
            s = replay_stop(raw, trace, b, rs, st)
            stops[b, st].append(s)
            print(f"{d.name} {_name(b, st)}: stop at {s.window_end_s:.2f} s{' (censored)' if s.censored else ''} "
                  f"after {s.checks} checks, CPU {s.cpu_s:.0f} s, wall {s.wall_s:.0f} s", flush=True)
    for (b, st), ss in stops.items():
        per_family, ratio_median, pooled = seed_error_ratios([s.stats for s in ss])
        for fam, r in per_family.items():
            print(f"{_name(b, st)} {fam}: between-seed sd / reported error, median {np.median(r):.2f} over "
                  f"{len(r)} stages ({min(r):.2f}-{max(r):.2f})")
        print(f"rule={_name(b, st)} runs={len(ss)} censored={sum(s.censored for s in ss)} "
              f"cpu_s_median={np.median([s.cpu_s for s in ss]):.1f} "
              f"window_end_s_median={np.median([s.window_end_s for s in ss]):.2f} "
              f"ratio_median={ratio_median:.2f} streams_ratio={pooled:.2f}", flush=True)


def coherence(dirs: list[Path], from_s: float, bin_s: float = 0.02) -> None:
    """How much of the runs' product-rate and hold-up fluctuation is common to every seed.

    Each run's product rate (``bin_s`` bins) and hold-up from ``from_s`` to its end, mean removed,
    are Fourier transformed; per frequency, the power of the seeds' mean over the mean power of the
    seeds is 1 for a fluctuation every seed shares (the same phase: a start or a deterministic
    driver), ``1/k`` for independent ones. Batch means see the shared part; the scatter between
    seeds does not, so there the between-seed errors understate a run's real error.
    """
    import pandas as pd

    series = []
    for d in dirs:
        ts = pd.read_parquet(d / "timeseries.parquet")
        t, out, hold = (ts[c].to_numpy() for c in ("time_s", "mass_out_kg", "mass_kg"))
        grid = np.arange(from_s, t[-1] - bin_s, bin_s)
        series.append((np.diff(np.interp(grid, t, out)) / bin_s, np.interp(grid, t, hold)[1:]))
    n = min(len(r) for r, _h in series)
    k = len(dirs)
    freq = np.fft.rfftfreq(n, bin_s)
    for name, x in (("product rate", np.array([r[:n] for r, _h in series])),
                    ("hold-up", np.array([h[:n] for _r, h in series]))):
        x = x - x.mean(axis=1, keepdims=True)
        own = np.abs(np.fft.rfft(x, axis=1)) ** 2
        band = (freq > 0.3) & (freq < 10.0)
        peaks = [f"{freq[band][np.argmax(o[band])]:.2f} Hz x{o[band].max() / np.median(o[band]):.0f}" for o in own]
        print(f"{name}: each run's strongest frequency in 0.3-10 Hz (power over the band's median): "
              + ", ".join(peaks))
        p_each = np.mean(own, axis=0)[1:]
        p_mean = (np.abs(np.fft.rfft(x.mean(axis=0))) ** 2)[1:]
        top = np.argsort(p_mean)[::-1][:3]
        print(f"{name}: strongest shared frequencies "
              + ", ".join(f"{freq[i + 1]:.2f} Hz (shared {p_mean[i] / p_each[i]:.2f})" for i in top)
              + f"; shared fraction of all power {p_mean.sum() / p_each.sum():.2f} (independent seeds: "
              f"{1 / k:.2f})")
    print(f"runs={k} from_s={from_s:g} shared_fraction_independent={1 / k:.2f}")


def _name(n_batches: int, settle_s: float | None) -> str:
    return f"batches{n_batches}" + ("" if settle_s is None else f"_settle{settle_s:g}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run", help="a fixed long window, saved raw with its time trace")
    r.add_argument("--size-mm", type=float, required=True)
    r.add_argument("--seed", type=int, required=True)
    r.add_argument("--measure-s", type=float, required=True)
    r.add_argument("--out", type=Path, required=True)
    r.add_argument("--start", choices=("table", "empty"), default="table")
    p = sub.add_parser("replay", help="stop rules replayed on saved runs")
    p.add_argument("run_dirs", type=Path, nargs="+")
    p.add_argument("--batches", type=int, nargs="+", default=[5, 10])
    p.add_argument("--settle-s", type=float, nargs="+", default=None,
                   help="window starts to try (s; a window from the onset starts at max(onset, this)); "
                        "default the runs' own")
    c = sub.add_parser("coherence", help="fluctuations shared by every seed (product rate, hold-up)")
    c.add_argument("run_dirs", type=Path, nargs="+")
    c.add_argument("--from-s", type=float, default=0.9)
    args = ap.parse_args()
    warnings.simplefilter("ignore")
    if args.cmd == "run":
        run_one(args.size_mm, args.seed, args.measure_s, args.out, args.start)
    elif args.cmd == "replay":
        replay(args.run_dirs, args.batches, args.settle_s or [None])
    else:
        coherence(args.run_dirs, args.from_s)


if __name__ == "__main__":
    main()
