"""Check: cold start against the stage-table warm start at one point (issue 12).

Two slice runs of the same point and seed (default: 30 mm, 30 t/h, 1500 rpm upper stages, bottom at
twice, gates 40 deg), one from an empty mill and one with ``RunSettings(start="table")``
(:func:`msmill.dem.mill.warmstart.place_table_start`), same steady-state criterion and window rule.
Prints the steady-state onset and detection, the window, the wall time, and the largest difference of
the stage statistics in units of their sampling error (:func:`msmill.sampling.paired_deviations`; about 4.6 % of the comparisons exceed 2 sigma by chance).

Run: ``NUMBA_NUM_THREADS=1 python benchmarks/table_start_check.py [--size-mm 30] [--adaptive --max-measure-s 3]``.
Last line: ``size_mm=<s> onset_cold=<t> onset_warm=<t> wall_ratio=<warm/cold> max_stat_dev_sigma=<x>``.
"""

from __future__ import annotations

import argparse
import warnings
from pathlib import Path

from msmill.dem.mill.run import RunSettings, run_mill
from msmill.machine import Machine, OperatingPoint
from msmill.sampling import paired_deviations


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size-mm", type=float, default=30.0)
    ap.add_argument("--feed-tph", type=float, default=30.0)
    ap.add_argument("--speed-rpm", type=float, default=1500.0)
    ap.add_argument("--gate-deg", type=float, default=40.0)
    ap.add_argument("--measure-s", type=float, default=0.5, help="fixed window (s)")
    ap.add_argument("--adaptive", action="store_true", help="adaptive window instead of the fixed one")
    ap.add_argument("--max-measure-s", type=float, default=30.0, help="cap of the adaptive window (s)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=None, help="write each run's statistics JSON here")
    args = ap.parse_args()
    warnings.simplefilter("ignore")  # transient overlap warnings are not the point here
    m = Machine.default()
    op = OperatingPoint(feed_tph=args.feed_tph, speed_rpm=args.speed_rpm, gate_deg=args.gate_deg)
    res = {}
    for start in ("empty", "table"):
        rs = RunSettings(measure_s=args.measure_s, adaptive=args.adaptive, max_measure_s=args.max_measure_s,
                         seed=args.seed, start=start)
        run = run_mill(m, op, size_mm=args.size_mm, settings=rs)
        st = run.stats.run
        res[start] = (st, run.wall_s, run.steady_state_time_s)
        if args.out:
            args.out.mkdir(parents=True, exist_ok=True)
            st.to_json(args.out / f"{args.size_mm:g}mm_{start}.json")
        print(f"{start}: {run.summary()}")
    devs = paired_deviations(res["empty"][0], res["table"][0])
    worst = max(devs)
    print(f"max deviation {worst[0]:.2f} sigma ({worst[1]}); {sum(d > 2 for d, _ in devs)} of {len(devs)} "
          f"beyond 2 sigma (about {0.046 * len(devs):.1f} by chance)")
    print(f"size_mm={args.size_mm:g} onset_cold={res['empty'][2]} onset_warm={res['table'][2]} "
          f"wall_ratio={res['table'][1] / res['empty'][1]:.3f} max_stat_dev_sigma={worst[0]:.2f}")


if __name__ == "__main__":
    main()
