"""Run a seeded space-filling batch of DEM slice runs over the 4-D design space.

The first training batch of the campaign (issue 14) before the campaign runner
existed: a scrambled Sobol design (``scipy.stats.qmc``) over rock size (log
scale), feed rate, upper-stage shaft speed (bottom stage at twice) and gate
angle; every point is one periodic-slice run of the default machine, saved with
:func:`msmill.dem.mill.run.save_run` into ``OUT/pt_NNN`` (raw events, snapshots,
statistics, settings; the folder layout ``msmill db ingest`` reads). Resumable:
a point whose ``statistics.json`` exists is skipped, so the script can be
killed and restarted at any time. Points run cheapest first (large rock, low
feed). One line of JSON per finished point goes to ``OUT/batch.jsonl``.

Run: ``NUMBA_NUM_THREADS=1 python scripts/design_batch.py --out runs/batch0 --n 16 --size-mm 12 30``
(``--feed-tph``, ``--speed-rpm``, ``--gate-deg`` narrow the box, e.g. the capacity batch
``--size-mm 14 30 --feed-tph 30 60 --gate-deg 0 30``).
"""

from __future__ import annotations

import argparse
import json
import math
import shlex
import sys
import time
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
from scipy.stats import qmc

from msmill._version import __version__
from msmill.dem.mill.run import RunSettings, git_commit, run_mill, save_run
from msmill.machine import Machine, OperatingPoint

FEED_TPH = (10.0, 60.0)
SPEED_RPM = (1200.0, 1900.0)
GATE_DEG = (0.0, 80.0)


def design(n: int, size_mm: tuple[float, float], seed: int, feed_tph: tuple[float, float] = FEED_TPH,
           speed_rpm: tuple[float, float] = SPEED_RPM, gate_deg: tuple[float, float] = GATE_DEG) -> np.ndarray:
    """Rows ``(size_mm, feed_tph, speed_rpm, gate_deg)`` of a scrambled Sobol design over a box."""
    u = qmc.Sobol(d=4, scramble=True, seed=seed).random(n)
    lo = np.array([math.log(size_mm[0]), feed_tph[0], speed_rpm[0], gate_deg[0]])
    hi = np.array([math.log(size_mm[1]), feed_tph[1], speed_rpm[1], gate_deg[1]])
    x = qmc.scale(u, lo, hi)
    x[:, 0] = np.exp(x[:, 0])
    return np.round(x, 3)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--n", type=int, default=16)
    ap.add_argument("--size-mm", type=float, nargs=2, default=[12.0, 30.0])
    ap.add_argument("--feed-tph", type=float, nargs=2, default=list(FEED_TPH))
    ap.add_argument("--speed-rpm", type=float, nargs=2, default=list(SPEED_RPM))
    ap.add_argument("--gate-deg", type=float, nargs=2, default=list(GATE_DEG),
                    help="a sub-box, e.g. high feed and narrow gates to find where the mill chokes (issue 20)")
    ap.add_argument("--seed", type=int, default=14)
    ap.add_argument("--max-time-s", type=float, default=9.0)
    ap.add_argument("--measure-s", type=float, default=1.0)
    ap.add_argument("--feed-speed-m-s", type=float, default=2.0,
                    help="downward speed of the fed rock in the chute (m/s); the source delivers more the faster it is")
    ap.add_argument("--adaptive", action="store_true",
                    help="measure until the sampling targets are met (RunSettings defaults) instead of --measure-s")
    args = ap.parse_args()
    box = {"size_mm": tuple(args.size_mm), "feed_tph": tuple(args.feed_tph), "speed_rpm": tuple(args.speed_rpm),
           "gate_deg": tuple(args.gate_deg)}
    pts = design(args.n, box["size_mm"], args.seed, box["feed_tph"], box["speed_rpm"], box["gate_deg"])
    args.out.mkdir(parents=True, exist_ok=True)
    meta = {"command": shlex.join([sys.executable, *sys.argv]), "msmill_version": __version__,
            "git_commit": git_commit(), "date_utc": datetime.now(UTC).isoformat(timespec="seconds"),
            "design": "scrambled Sobol", "seed": args.seed, "adaptive": args.adaptive,
            "bounds": box,
            "points": pts.tolist()}
    (args.out / "design.json").write_text(json.dumps(meta, indent=1), encoding="utf-8")
    machine = Machine.default()
    settings = RunSettings(max_time_s=args.max_time_s, measure_s=args.measure_s, adaptive=args.adaptive,
                           feed_speed_m_s=args.feed_speed_m_s)
    # expected cost ~ feed / size^4: cheapest first so a partial batch covers the most points
    order = np.argsort(pts[:, 1] / pts[:, 0] ** 4)
    for i in order:
        size, feed, speed, gate = (float(v) for v in pts[i])
        d = args.out / f"pt_{i:03d}"
        if (d / "statistics.json").exists():
            continue
        t0 = time.perf_counter()
        op = OperatingPoint(feed_tph=feed, speed_rpm=speed, gate_deg=gate)
        run = run_mill(machine, op, size_mm=size, mode="slice", settings=settings)
        save_run(run, d)
        st = run.stats.run
        line = {"point": int(i), "size_mm": size, "feed_tph": feed, "speed_rpm": speed, "gate_deg": gate,
                "wall_s": round(time.perf_counter() - t0, 1), "steady_state_time_s": run.steady_state_time_s,
                "mass_out_rate_kg_s": st.mass_out_rate_kg_s, "feed_kg_s": run.scene.info.get("feed_kg_s"),
                "particles_end": run.extra["n_particles_end"]}
        with (args.out / "batch.jsonl").open("a", encoding="utf-8") as f:
            f.write(json.dumps(line) + "\n")
        print(json.dumps(line), flush=True)


if __name__ == "__main__":
    main()
