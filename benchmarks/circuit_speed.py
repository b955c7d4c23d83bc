"""CPU time of a closed circuit: its steady state, its 64-sample band and the mill's fresh-point steady state.

Run::

    NUMBA_NUM_THREADS=1 python benchmarks/circuit_speed.py [--repeats 5]

On ``examples/ug2_closed_circuit.toml`` (the default 5-stage mill with the shipped
surrogate, a Whiten screen at 6 mm, 20 t/h fresh feed), CPU seconds
(``time.process_time``), medians of ``--repeats``:

* ``circuit_steady_cpu_s``: :meth:`Circuit.solve` from empty streams, every repeat at
  another fresh-feed rate (19-21 t/h) with the mill's operator cache cleared, so
  nothing is reused between repeats (within one solve the prepared mill is reused
  between tear passes: operators are rebuilt only when the mill's feed rate moves);
* ``circuit_band_cpu_s``: :meth:`Circuit.band` with 64 posterior samples after that solve;
* ``mill_fresh_point_cpu_s``: ``Mill.run`` of the circuit's mill at fresh operating
  points (feed rate 40-60 t/h, no time march, no held-below re-solve, no band): stage
  parameters from the surrogate, operators assembled, one sparse solve;
  ``mill_fresh_point_table_cpu_s`` the same with the packaged stage table (the provider
  ``benchmarks/model_speed.py`` times).

The last line is ``... circuit_steady_cpu_s=<a> circuit_band_cpu_s=<b> mill_fresh_point_cpu_s=<c>``.
"""

from __future__ import annotations

import argparse
import statistics
import time
import warnings
from pathlib import Path

import numpy as np

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "ug2_closed_circuit.toml"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    warnings.simplefilter("ignore")
    from msmill.model import Mill
    from msmill.model.circuit import CircuitFile
    from msmill.psd import PSD

    cf = CircuitFile.from_toml(EXAMPLE)
    c = cf.circuit
    unit = c.units["mill"]
    fresh = c.units["fresh"]
    cf.solve()  # warm: imports, numba, first assembly

    steady, band, rebuilds, passes = [], [], [], []
    res = None
    for rate in np.linspace(19.0, 21.0, args.repeats):
        fresh.rate_tph = float(rate)
        fresh.bind(c.grid)
        unit.bind(c.grid)
        unit.mill._cache.clear()
        t = time.process_time()
        res = c.solve()
        steady.append(time.process_time() - t)
        rebuilds.append(unit.rebuilds)
        passes.append(res.iterations)
        t = time.process_time()
        b = c.band(res, 64)
        band.append(time.process_time() - t)
    print(f"circuit: {res.iterations} passes, {unit.rebuilds} operator builds, circulating load "
          f"{res.circulating_load_pct:.4g} % (5-95 % {b.circulating_load_band_pct[0]:.4g}-"
          f"{b.circulating_load_band_pct[1]:.4g}), product P80 {res.product_p80_mm:.3g} mm")
    print("steady CPU s:", " ".join(f"{v:.3f}" for v in steady), "| builds:", rebuilds, "| passes:", passes)
    print("band CPU s:", " ".join(f"{v:.3f}" for v in band))

    feed_q = res.unit_feeds_tph["mill"]
    feed = PSD(c.grid, feed_q / feed_q.sum(), validate=False)

    def fresh_points(mill) -> list[float]:
        mill.run(feed, unit.operating_point(50.5), timeseries=False, held_below=False)  # warm
        out = []
        for r in np.linspace(40.0, 60.0, max(args.repeats, 5)):
            mill._cache.clear()
            t = time.process_time()
            mill.run(feed, unit.operating_point(float(r)), timeseries=False, held_below=False)
            out.append(time.process_time() - t)
        return out

    m = unit.mill
    m.band_samples = 0
    surrogate = fresh_points(m)
    table = fresh_points(Mill(m.ore, "table", grid=c.grid, transport=m.transport, impacts=m.impacts,
                              breakage=m.breakage, damage=m.damage, band_samples=0))
    print("mill fresh point CPU s (surrogate):", " ".join(f"{v:.3f}" for v in surrogate))
    print("mill fresh point CPU s (table):", " ".join(f"{v:.3f}" for v in table))
    print(f"mill_fresh_point_table_cpu_s={statistics.median(table):.4f} "
          f"circuit_steady_cpu_s={statistics.median(steady):.3f} circuit_band_cpu_s={statistics.median(band):.3f} "
          f"mill_fresh_point_cpu_s={statistics.median(surrogate):.4f}")


if __name__ == "__main__":
    main()
