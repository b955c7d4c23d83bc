"""Benchmark: periodic-slice DEM of the default mill to steady state plus a measurement window.

Design point: 10 mm rock, 30 t/h (full-mill feed, scaled to the slice), upper
stages 1500 rpm (bottom stage 3000 rpm), gates at 40 deg. Prints the time to
steady state, the statistics summary, and as its last line
``wall_seconds=<number> particles=<number>`` (wall time of the whole run
including numba compilation, and the number of rocks in the mill at the end).

Run: ``python benchmarks/msm_run.py [--out DIR]``
"""

from __future__ import annotations

import argparse
import time

from msmill.dem.mill.run import RunSettings, run_mill, save_run
from msmill.machine import Machine, OperatingPoint
from msmill.plots.dem import plot_run


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=None, help="also save the run (events, statistics, plots) here")
    ap.add_argument("--measure-s", type=float, default=0.5, help="measurement window (s)")
    ap.add_argument("--max-time-s", type=float, default=4.0, help="max time to wait for steady state (s)")
    args = ap.parse_args()
    t0 = time.perf_counter()
    machine = Machine.default()
    op = OperatingPoint(feed_tph=30.0, speed_rpm=1500.0, gate_deg=40.0)
    settings = RunSettings(max_time_s=args.max_time_s, measure_s=args.measure_s)
    run = run_mill(machine, op, size_mm=10.0, mode="slice", settings=settings)
    st = run.stats.run
    ss = run.steady_state_time_s
    print(f"dt_s={run.extra['dt_s']:.3e} rock_E_used_pa={run.scene.info['rock_youngs_modulus_used_pa']:.3e} "
          f"peak_overlap_at_vmax={run.scene.info['peak_overlap_fraction_at_max_speed']:.3f}")
    print(f"steady_state_s={'none' if ss is None else f'{ss:.2f}'} detected_s={run.steady_state_detected_s} "
          f"window_s={run.window_s[0]:.2f}-{run.window_s[1]:.2f} tau_s={st.characteristic_time_s:.4f} "
          f"mass_out_kg_s={st.mass_out_rate_kg_s:.3f} feed_kg_s={run.scene.feed_kg_s:.3f} "
          f"residence_s={st.residence_time_s}")
    for s in st.stages:
        print(f"stage {s.stage}: kick={s.kickback:.3f} refeed={s.refeed:.3f} pass={s.pass_through:.3f} "
              f"p_hit={s.primary_hit_probability:.3f} n_prim={s.n_primary_impacts} "
              f"v_prim={s.primary_velocity.mean():.1f} lambda={s.secondary_lambda:.2f} "
              f"KL(lambda)={s.secondary_lambda_kl} KL(v_sec)={s.secondary_velocity_kl}")
    if args.out:
        save_run(run, args.out)
        plot_run(run, args.out)
    wall = time.perf_counter() - t0
    print(f"wall_seconds={wall:.1f} particles={run.extra['n_particles_end']}")


if __name__ == "__main__":
    main()
