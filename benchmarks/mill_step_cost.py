"""Benchmark: cost of the DEM step in the default mill slice, per rock and step.

Builds the default slice (default 10 mm rock, 30 t/h, 1500 rpm, gates 40 deg; ``--size-mm`` etc.
for another point, ``--table-start`` to fill it first with the stage table's steady hold-up as
campaign runs start), runs it to ``--warm-s`` of mill time, then times ``--window-s`` windows with
the serial and the threaded step kernels (``--threads`` numba threads) alternately, or, with
``--skin-radii 0.5 1``, the neighbour lists' Verlet skins (multiples of the smallest radius). Prints, per window, the
wall time and the step-kernel time per rock-step (ns) and the steps per
neighbour rebuild; the last line is
``serial_ns_per_rock_step=<wall> kernel=<kernel>`` (best serial window;
below 1000 particles the engine runs serial, above it the faster kind).

Run: ``python benchmarks/mill_step_cost.py [--warm-s 0.6] [--window-s 0.02]``; a fine-rock run's
gain from a second core: ``python benchmarks/mill_step_cost.py --size-mm 3 --feed-tph 10
--table-start --warm-s 0.02 --window-s 0.005 --threads 2`` (on otherwise idle cores).
"""

from __future__ import annotations

import argparse
import time
import warnings

import numba

import msmill.dem  # noqa: F401  (chooses numba's threading layer first)
from msmill.dem.mill.scene import build_scene
from msmill.dem.mill.warmstart import place_table_start
from msmill.machine import Machine, OperatingPoint


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--warm-s", type=float, default=0.6, help="mill time before timing (s)")
    ap.add_argument("--window-s", type=float, default=0.02, help="mill time per timed window (s)")
    ap.add_argument("--windows", type=int, default=3, help="timed windows per kernel kind")
    ap.add_argument("--size-mm", type=float, default=10.0)
    ap.add_argument("--feed-tph", type=float, default=30.0)
    ap.add_argument("--speed-rpm", type=float, default=1500.0)
    ap.add_argument("--gate-deg", type=float, default=40.0)
    ap.add_argument("--table-start", action="store_true", help="fill with the stage table's hold-up first")
    ap.add_argument("--threads", type=int, default=None, help="numba threads of the threaded kind")
    ap.add_argument("--skin-radii", type=float, nargs="+", default=None,
                    help="compare these Verlet skins (multiples of the smallest radius; default 0.5) instead")
    args = ap.parse_args()
    if args.threads:
        numba.set_num_threads(args.threads)
    warnings.simplefilter("ignore")  # the transient's overlap warnings are not the point here
    sc = build_scene(Machine.default(), OperatingPoint(feed_tph=args.feed_tph, speed_rpm=args.speed_rpm,
                                                       gate_deg=args.gate_deg), size_mm=args.size_mm)
    if args.table_start:
        place_table_start(sc)
    sim = sc.sim
    kw = {"max_relative_speed_m_s": sc.max_impact_speed_m_s, "progress": False}
    t0 = time.perf_counter()
    sim.run(args.warm_s, **kw)
    print(f"warm-up to {args.warm_s} s: {time.perf_counter() - t0:.1f} s wall (compilation included), "
          f"{sim.n_particles} rocks, dt {sim.dt_s:.3g} s")
    if args.skin_radii:
        compare_skins(sim, kw, args)
        return
    best = {False: (float("inf"), float("inf")), True: (float("inf"), float("inf"))}
    for _ in range(args.windows):
        for threaded in (False, True):
            sim._par_mode = threaded
            sim._par_min = 1  # allow threads at any size (the default considers them from 1000)
            w, k, per = time_window(sim, kw, args.window_s)
            best[threaded] = min(best[threaded], (w, k))
            print(f"{'threaded' if threaded else 'serial  '}: {w:.0f} ns/rock-step wall, kernel {k:.0f}, "
                  f"{per:.1f} steps/rebuild, {sim.n_particles} rocks")
    print(f"threaded best: {best[True][0]:.0f} ns/rock-step wall, kernel {best[True][1]:.0f} "
          f"({numba.get_num_threads()} threads)")
    w, k = best[False]
    print(f"serial_ns_per_rock_step={w:.0f} kernel={k:.0f} threaded_ns_per_rock_step={best[True][0]:.0f} "
          f"serial_over_threaded={w / best[True][0]:.2f}")


def time_window(sim, kw: dict, window_s: float) -> tuple[float, float, float]:
    """Wall and step-kernel ns per rock-step of ``window_s`` more mill time, and steps per rebuild."""
    s0, r0, k0 = sim.stats["steps"], sim.stats["rebuilds"], sim.stats["loop_time_s"]
    t0 = time.perf_counter()
    sim.run(window_s, **kw)
    wall = time.perf_counter() - t0
    steps = sim.stats["steps"] - s0
    rock_steps = steps * sim.n_particles
    return (wall / rock_steps * 1e9, (sim.stats["loop_time_s"] - k0) / rock_steps * 1e9,
            steps / max(1, sim.stats["rebuilds"] - r0))


def compare_skins(sim, kw: dict, args) -> None:
    """Windows at each Verlet skin of ``--skin-radii`` (multiples of the smallest radius), taking turns."""
    r_min = float(sim.particle_arrays()["rad"].min())
    best = {f: float("inf") for f in args.skin_radii}
    for _ in range(args.windows):
        for f in args.skin_radii:
            sim.neighbor_skin_m = f * r_min
            w, k, per = time_window(sim, kw, args.window_s)
            best[f] = min(best[f], w)
            print(f"skin {f:g} r_min: {w:.1f} ns/rock-step wall, kernel {k:.1f}, {per:.1f} steps/rebuild, "
                  f"{sim.n_particles} rocks")
    print(" ".join(f"skin_{f:g}_ns_per_rock_step={best[f]:.1f}" for f in args.skin_radii))


if __name__ == "__main__":
    main()
