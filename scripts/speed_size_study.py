"""Speed/size study: statistics of slice runs at two shaft speeds and two rock sizes.

For each (upper-stage speed, size) pair (default 1300 and 1800 rpm; 6 and
20 mm; 30 t/h, gates 40 deg, bottom stage at twice the upper speed) a
periodic-slice DEM run goes to steady state plus a measurement window. Prints
a Markdown table with the time to steady state, the characteristic time, the
per-stage streams, hit probabilities, lambda and the KL of every fit, and
writes it (and a JSON of all numbers) to ``--out``.

Run: ``python scripts/speed_size_study.py [--speeds-rpm 1300 1800] [--sizes-mm 6 20] --out runs/study``
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from msmill.dem.mill.run import RunSettings, run_mill, save_run
from msmill.machine import Machine, OperatingPoint


def _f(x: float | None, fmt: str = ".3f") -> str:
    return "-" if x is None else format(x, fmt)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--speeds-rpm", type=float, nargs="+", default=[1300.0, 1800.0])
    ap.add_argument("--sizes-mm", type=float, nargs="+", default=[6.0, 20.0])
    ap.add_argument("--feed-tph", type=float, default=30.0)
    ap.add_argument("--gate-deg", type=float, default=40.0)
    ap.add_argument("--measure-s", type=float, default=0.5)
    ap.add_argument("--max-time-s", type=float, default=None, help="time limit (s); default scales with the residence time")
    ap.add_argument("--out", type=Path, default=Path("runs/speed_size_study"))
    args = ap.parse_args()
    machine = Machine.default()
    settings = RunSettings(max_time_s=args.max_time_s or 0.0, measure_s=args.measure_s)
    rows, lines = [], []
    lines.append("| speed (rpm) | size (mm) | t_ss (s) | tau (s) | stage | kick | refeed | pass | p_hit | "
                 "v_prim (m/s) | KL v_prim | lambda | KL lambda | KL v_sec | n_prim | n_sec |")
    lines.append("|" + "---|" * 16)
    for speed in args.speeds_rpm:
        for size in args.sizes_mm:
            op = OperatingPoint(feed_tph=args.feed_tph, speed_rpm=speed, gate_deg=args.gate_deg)
            t0 = time.perf_counter()
            run = run_mill(machine, op, size_mm=size, mode="slice", settings=settings)
            save_run(run, args.out / f"rpm{speed:g}_size{size:g}mm")
            st = run.stats.run
            wall = time.perf_counter() - t0
            rows.append({"speed_rpm": speed, "size_mm": size, "wall_s": wall, "dt_s": run.extra["dt_s"],
                         "statistics": json.loads(st.model_dump_json())})
            for s in st.stages:
                lines.append(
                    f"| {speed:g} | {size:g} | {_f(st.steady_state_time_s, '.2f')} | "
                    f"{st.characteristic_time_s:.3f} | {s.stage} | {s.kickback:.3f} | {s.refeed:.3f} | "
                    f"{s.pass_through:.3f} | {s.primary_hit_probability:.3f} | {s.primary_velocity.mean():.1f} | "
                    f"{_f(s.primary_velocity_kl, '.4f')} | {s.secondary_lambda:.2f} | "
                    f"{_f(s.secondary_lambda_kl, '.4f')} | {_f(s.secondary_velocity_kl, '.4f')} | "
                    f"{s.n_primary_impacts} | {s.n_secondary_impacts} |")
            print(f"done {speed:g} rpm {size:g} mm: steady {st.steady_state_time_s} s, wall {wall:.0f} s", flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    table = "\n".join(lines)
    (args.out / "study.md").write_text(table + "\n", encoding="utf-8")
    (args.out / "study.json").write_text(json.dumps(rows, indent=1) + "\n", encoding="utf-8")
    print(table)


if __name__ == "__main__":
    main()
