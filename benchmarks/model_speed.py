"""Speed of the mill model: a 5-stage steady-state prediction on a sqrt(2) grid 0.038-45 mm.

Run::

    python benchmarks/model_speed.py

Reports import time, one-off setup (reading the stage parameters, building
the Mill, appearance and damage tables, first call), then the steady-state
prediction at fresh operating points (stage parameters read at the grid,
every operator re-assembled, one sparse direct solve, all outputs; no time
marching), and the re-solve with cached operators. The last line is
``steady_state_seconds=<median of the fresh-operating-point predictions>``
followed by the surrogate figures: the shipped default surrogate (what
``msmill predict`` uses; a GP fitted to the table's runs when none is
installed), the steady state with it (the surrogate predicts the stage parameters at
every fresh operating point) and the 5-95 % band from 64 posterior samples.

Stage parameters: the packaged DEM-derived table
(``msmill/data/stage_parameters/default.json``) when installed; otherwise a
SYNTHETIC in-memory table made below (benchmark use only, never shipped).
"""

from __future__ import annotations

import statistics
import time
import warnings

T0 = time.perf_counter()
import numpy as np  # noqa: E402

from msmill.machine import OperatingPoint  # noqa: E402
from msmill.model import Mill, TableProvider  # noqa: E402
from msmill.psd import PSD, SizeGrid  # noqa: E402
from msmill.stageparams import StageParameterTable  # noqa: E402

T_IMPORT = time.perf_counter() - T0


def synthetic_table(n_stages: int = 5) -> StageParameterTable:
    """SYNTHETIC stage parameters (benchmark only; plausible magnitudes, not DEM output)."""
    runs = []
    for size in (2.0, 5.0, 10.0, 20.0, 30.0):
        stages = []
        for i in range(1, n_stages + 1):
            kick = 0.0 if i == 1 else 0.08
            refeed = max(0.15, 0.5 - 0.01 * size)
            v = 35.0 * (1.6 if i == n_stages else 1.0)
            stages.append({
                "stage": i, "kickback": kick, "refeed": refeed, "pass_through": 1 - kick - refeed,
                "primary_hit_probability": 0.5,
                "primary_velocity": {"weights": [0.7, 0.3], "means_m_s": [v, 0.5 * v],
                                     "sigmas_m_s": [0.15 * v, 0.2 * v]},
                "secondary_lambda": 2.0 + 0.05 * size,
                "secondary_velocity": {"weights": [0.6, 0.4], "means_m_s": [2.4, 8.0],
                                       "sigmas_m_s": [1.0, 2.4]},
            })
        runs.append({"design": {"size_mm": size, "feed_tph": 30.0, "speed_rpm": 1500.0,
                                "gate_deg": 40.0, "stage_speeds_rpm": [1500.0] * 4 + [3000.0]},
                     "characteristic_time_s": 0.06, "stages": stages})
    return StageParameterTable.model_validate({"runs": runs, "provenance": {"note": "SYNTHETIC"}})


def _poisson_counts(table: StageParameterTable) -> StageParameterTable:
    """The table with each stage's secondary-count distribution replaced by the Poisson of its mean."""
    from msmill.stageparams import CountDistribution

    runs = [r.model_copy(update={"stages": [
        s.model_copy(update={"secondary_count": CountDistribution.poisson(s.secondary_lambda)}) for s in r.stages]})
        for r in table.runs]
    return table.model_copy(update={"runs": runs})


def main() -> None:
    import argparse

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--table", default=None, help="stage-parameter table (default: the packaged one)")
    ap.add_argument("--poisson-counts", action="store_true",
                    help="replace every secondary-count distribution by the Poisson of its mean")
    args = ap.parse_args()
    warnings.simplefilter("ignore")
    t = time.perf_counter()
    from importlib import resources

    default = resources.files("msmill").joinpath("data/stage_parameters/default.json")
    if args.table:
        table = StageParameterTable.from_json(args.table)
        if args.poisson_counts:
            table = _poisson_counts(table)
        provider = TableProvider(table, source=f"{args.table}{' (Poisson counts)' if args.poisson_counts else ''}")
        source = provider.source
    elif default.is_file():
        provider = TableProvider.from_file(str(default))
        source = "packaged DEM-derived table"
    else:
        provider = TableProvider(synthetic_table(), source="SYNTHETIC benchmark table")
        source = "SYNTHETIC table (default.json not installed yet)"
    grid = SizeGrid.geometric(0.038, 45.0)
    feed = PSD.from_passing([4.75, 9.5, 19.0, 26.5, 37.5, 45.0], [3.0, 12.0, 45.0, 70.0, 92.0, 100.0],
                            grid=grid)
    mill = Mill("UG2", provider, grid=grid)
    mill.run(feed, OperatingPoint(feed_tph=30.0, speed_rpm=1450.0, gate_deg=40.0), timeseries=False)
    t_setup = time.perf_counter() - t

    fresh, fresh_cpu = [], []
    for speed in np.linspace(1200.0, 1900.0, 9):
        op = OperatingPoint(feed_tph=30.0, speed_rpm=float(speed), gate_deg=40.0)
        c0, w0 = time.process_time(), time.perf_counter()
        res = mill.run(feed, op, timeseries=False)
        fresh.append(time.perf_counter() - w0)
        fresh_cpu.append(time.process_time() - c0)
    cached = []
    for _ in range(9):
        w0 = time.perf_counter()
        mill.run(feed, op, timeseries=False)
        cached.append(time.perf_counter() - w0)
    w0 = time.perf_counter()
    res_ts = mill.run(feed, op)
    t_march = time.perf_counter() - w0

    print(f"stage parameters: {source}")
    print(f"grid: {grid.n_classes} classes 0.038-45 mm (sqrt 2), 5 stages, "
          f"{mill.damage_classes} damage classes, state size {(5 + 1) * grid.n_classes * mill.damage_classes}")
    print(f"import_seconds={T_IMPORT:.3f}")
    print(f"setup_seconds={t_setup:.3f}  (provider, Mill, appearance/damage tables, first call)")
    print(f"steady_state fresh operating point: median {statistics.median(fresh):.4f} s wall, "
          f"{statistics.median(fresh_cpu):.4f} s cpu (min {min(fresh):.4f}, max {max(fresh):.4f})")
    print(f"steady_state cached operators: median {statistics.median(cached):.4f} s")
    print(f"with time series from empty mill ({len(res_ts.timeseries)} steps, cached operators): "
          f"{t_march:.4f} s")
    print(f"P80 at {op.speed_rpm:g} rpm: {res.p80_mm:.3f} mm; mass-balance error {res.mass_balance_error:.1e}")
    sur = surrogate_timings(feed, grid)
    print(f"surrogate ({sur['source']} {sur['fit_s']:.2f} s wall); steady state with the surrogate "
          f"median {sur['steady_s']:.4f} s wall, {sur['steady_cpu_s']:.4f} s cpu; "
          f"band of {sur['n_samples']} posterior samples median {sur['band_s']:.3f} s wall, "
          f"{sur['band_cpu_s']:.3f} s cpu (P80 {sur['p80_mm']:.3f} mm, band {sur['band'][0]:.3f}-"
          f"{sur['band'][1]:.3f} mm)")
    print(f"steady_state_seconds={statistics.median(fresh):.4f} "
          f"surrogate_steady_state_seconds={sur['steady_s']:.4f} "
          f"surrogate_band_{sur['n_samples']}_seconds={sur['band_s']:.3f} "
          f"surrogate_steady_state_cpu_seconds={sur['steady_cpu_s']:.4f} "
          f"surrogate_band_cpu_seconds={sur['band_cpu_s']:.3f}")


def surrogate_timings(feed, grid, n_samples: int = 64) -> dict:
    """Time predictions with the shipped default surrogate (else one fitted to the packaged table's runs).

    Steady state: fresh operating points (the surrogate predicts at every one),
    no band. Band: the same plus ``n_samples`` posterior samples through the
    expected-value solver. Medians over 3 speeds.
    """
    from importlib import resources

    from msmill.model.providers import default_surrogate_path
    from msmill.surrogate.provider import SurrogateProvider
    from msmill.surrogate.stage_model import StageSurrogate

    w0 = time.perf_counter()
    shipped = default_surrogate_path()
    if shipped is not None:  # what `msmill predict` uses: the GP's cost grows with its training runs
        provider = SurrogateProvider.from_file(shipped)
        source = f"the shipped default surrogate, {provider.surrogate.training_.n_runs} runs; loaded in"
    else:
        default = resources.files("msmill").joinpath("data/stage_parameters/default.json")
        if default.is_file():
            runs, source = StageParameterTable.from_json(str(default)).runs, "fitted to the packaged table's runs"
        else:
            runs, source = synthetic_table().runs, "fitted to the SYNTHETIC benchmark table"
        provider = SurrogateProvider(StageSurrogate(n_restarts=0).fit(runs))
        source += "; fit"
    fit_s = time.perf_counter() - w0
    plain = Mill("UG2", provider, grid=grid, band_samples=0)
    banded = Mill("UG2", provider, grid=grid, band_samples=n_samples)
    plain.run(feed, OperatingPoint(feed_tph=30.0, speed_rpm=1490.0, gate_deg=40.0), timeseries=False)
    steady, steady_cpu, band, band_cpu = [], [], [], []
    for speed in (1450.0, 1500.0, 1550.0):
        op = OperatingPoint(feed_tph=30.0, speed_rpm=speed, gate_deg=40.0)
        c0, w0 = time.process_time(), time.perf_counter()
        plain.run(feed, op, timeseries=False)
        steady.append(time.perf_counter() - w0)
        steady_cpu.append(time.process_time() - c0)
        c0, w0 = time.process_time(), time.perf_counter()
        res = banded.run(feed, op, timeseries=False)
        band.append(time.perf_counter() - w0)
        band_cpu.append(time.process_time() - c0)
    return {"source": source, "fit_s": fit_s, "steady_s": statistics.median(steady),
            "steady_cpu_s": statistics.median(steady_cpu), "band_s": statistics.median(band),
            "band_cpu_s": statistics.median(band_cpu), "n_samples": n_samples, "p80_mm": res.p80_mm,
            "band": res.p80_band_mm}


if __name__ == "__main__":
    main()
