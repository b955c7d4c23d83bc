"""Record a fixed-duration slice run's time series (no steady-state stop), to study the fill.

Writes ``time_s, n_particles, mass_kg, kinetic_energy_j, mass_out_kg, n_lost,
feed_kg_s`` as Parquet; apply :func:`msmill.steadystate.assess` or
:func:`msmill.steadystate.flow_windows` to it.

Run: ``NUMBA_NUM_THREADS=1 python scripts/steady_state_record.py SIZE_MM FEED_TPH RPM GATE_DEG DURATION_S OUT``
(issue 20: ``20 30 1500 40 8 runs/raw20_default.parquet``).
"""

from __future__ import annotations

import sys
import time

from msmill.dem.mill.scene import build_scene
from msmill.machine import Machine, OperatingPoint


def main() -> None:
    size, feed, rpm, gate, duration = map(float, sys.argv[1:6])
    out = sys.argv[6]
    op = OperatingPoint(feed_tph=feed, speed_rpm=rpm, gate_deg=gate)
    sc = build_scene(Machine.default(), op, size_mm=size, mode="slice", max_overlap_fraction=0.05, seed=0)
    w0 = time.perf_counter()
    sc.sim.run(duration, max_relative_speed_m_s=sc.max_impact_speed_m_s, safety=0.2, snapshot_every_s=0.05,
               progress=False)
    ts = sc.sim.timeseries()
    ts["feed_kg_s"] = sc.feed_kg_s
    ts.to_parquet(out)
    print(f"wall_s={time.perf_counter() - w0:.1f} feed_kg_s={sc.feed_kg_s:.3f} rows={len(ts)}")


if __name__ == "__main__":
    main()
