"""Benchmark: the DEM's Warp backend (a GPU, or Warp's CPU device) against the numba engine (issue 44).

Three cases, each run with the numba engine (``backend="cpu"``, all numba threads) and with the Warp
kernels (``backend="cuda"``, or ``"warp-cpu"`` with ``--device cpu``), in one process:

* the throughput gas of ``benchmarks/dem_throughput.py`` (its scene builder :func:`bench`: 10 mm
  spheres, periodic cube, 10 m/s, e = 0.5, mu = 0.4, dt = 1e-6 s) at solid fraction 0.05 and 0.30:
  particle-steps per second of wall time;
* the 10 mm mill slice of ``benchmarks/mill_step_cost.py`` (30 t/h, 1500 rpm, gates 40 deg), here from
  the stage table's hold-up (``place_table_start``) instead of a 0.6 s warm-up: wall time per rock and
  step (us) over a window of ``--window-s``;
* a fine-rock slice (``--fine-mm``, default 3 mm, same operating point, table start): wall seconds for
  ``--fine-chunk-s`` of simulated time.

The Warp backend moves the step passes (contacts, history, geometry, integration, events) to the
device; neighbour rebuilds, sources and sinks still run in numba on the host between step calls
(``docs/dem.md``, "GPU backend"), so on a GPU these figures include a host round trip per rebuild.

Run on a GPU machine (installs ``warp-lang``, and msmill from this checkout, if missing)::

    python benchmarks/gpu_dem.py [--n 20000] [--steps 2000]

Here, without a GPU, to see that it works (small sizes, Warp's CPU device)::

    python benchmarks/gpu_dem.py --device cpu

The last line is ``device=<name> gas005_psteps_s=<a> gas030_psteps_s=<b>
slice10_step_us_per_rock=<c> fine_chunk_s=<d>`` for the Warp backend, followed by the numba
engine's figures as ``numba_<same keys>=<value>``.
"""

from __future__ import annotations

import argparse
import importlib.util
import subprocess
import sys
import time
import warnings
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: sizes of a quick run on Warp's CPU device (``--device cpu``): it only shows that the script works
CPU_SIZES = {"n": 1000, "steps": 100, "warm": 10, "window_s": 0.003, "fine_chunk_s": 0.0005}
GPU_SIZES = {"n": 20000, "steps": 2000, "warm": 200, "window_s": 0.02, "fine_chunk_s": 0.01}


def ensure_installed() -> None:
    """Install msmill (this checkout) and warp-lang with pip where they are missing."""
    need = []
    if importlib.util.find_spec("msmill") is None:
        need.append(str(ROOT))
    if importlib.util.find_spec("warp") is None:
        need.append("warp-lang>=1.19")
    if need:
        print(f"installing {' '.join(need)}", flush=True)
        subprocess.run([sys.executable, "-m", "pip", "install", "-q", *need], check=True)


def device_name(device: str) -> str:
    """A short name of the Warp device (GPU model, or ``cpu-<processor>``)."""
    import platform

    import warp as wp

    from msmill.dem.backend import warp_status

    warp_status()  # initialises Warp quietly
    if device == "cpu":
        return "cpu-" + (platform.processor() or platform.machine()).replace(" ", "_")
    return wp.get_device("cuda:0").name.replace(" ", "_")


def gas(backend: str, phi: float, n: int, steps: int, warm: int) -> float:
    """Particle-steps per second of the throughput gas (``dem_throughput.bench``)."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from dem_throughput import bench

    return bench(n, phi, steps, warm, backend=backend)["rate"]


def _slice(backend: str, size_mm: float):
    from msmill.dem.mill.scene import build_scene
    from msmill.dem.mill.warmstart import place_table_start
    from msmill.machine import Machine, OperatingPoint

    sc = build_scene(Machine.default(), OperatingPoint(feed_tph=30.0, speed_rpm=1500.0, gate_deg=40.0),
                     size_mm=size_mm, backend=backend)
    place_table_start(sc, seed=1)
    return sc, {"max_relative_speed_m_s": sc.max_impact_speed_m_s, "progress": False}


def slice_step_us_per_rock(backend: str, window_s: float) -> float:
    """Wall time per rock and step (us) of the 10 mm slice over ``window_s`` of simulated time."""
    sc, kw = _slice(backend, 10.0)
    sc.sim.run(sc.sim.dt_s or 1e-5, **kw)  # first step: compilation or cache load
    s0, n0 = sc.sim.stats["steps"], sc.sim.n_particles
    t0 = time.perf_counter()
    sc.sim.run(window_s, **kw)
    wall = time.perf_counter() - t0
    steps = sc.sim.stats["steps"] - s0
    return wall / (steps * 0.5 * (n0 + sc.sim.n_particles)) * 1e6


def fine_chunk_s(backend: str, size_mm: float, chunk_s: float) -> float:
    """Wall seconds for ``chunk_s`` of simulated time of the fine-rock slice."""
    sc, kw = _slice(backend, size_mm)
    sc.sim.run(sc.sim.dt_s or 1e-6, **kw)
    t0 = time.perf_counter()
    sc.sim.run(chunk_s, **kw)
    return time.perf_counter() - t0


def measure(backend: str, a: argparse.Namespace) -> dict[str, float]:
    """The four figures of one backend."""
    out = {"gas005_psteps_s": gas(backend, 0.05, a.n, a.steps, a.warm),
           "gas030_psteps_s": gas(backend, 0.30, a.n, a.steps, a.warm),
           "slice10_step_us_per_rock": slice_step_us_per_rock(backend, a.window_s),
           "fine_chunk_s": fine_chunk_s(backend, a.fine_mm, a.fine_chunk_s)}
    print(backend + ": " + ", ".join(f"{k} {v:.4g}" for k, v in out.items()), flush=True)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", choices=["cuda", "cpu"], default="cuda",
                    help="Warp device: cuda (backend 'cuda') or cpu (backend 'warp-cpu', small sizes)")
    ap.add_argument("--n", type=int, default=None, help="gas particles")
    ap.add_argument("--steps", type=int, default=None, help="timed gas steps")
    ap.add_argument("--warm", type=int, default=None, help="gas warm-up steps")
    ap.add_argument("--window-s", type=float, default=None, help="timed window of the 10 mm slice (s)")
    ap.add_argument("--fine-mm", type=float, default=3.0, help="fine rock diameter (mm), 2-4")
    ap.add_argument("--fine-chunk-s", type=float, default=None, help="simulated time of the fine chunk (s)")
    ap.add_argument("--no-install", action="store_true", help="do not pip-install what is missing")
    a = ap.parse_args(argv)
    sizes = CPU_SIZES if a.device == "cpu" else GPU_SIZES
    for k, v in sizes.items():
        if getattr(a, k) is None:
            setattr(a, k, v)
    if not a.no_install:
        ensure_installed()
    warnings.simplefilter("ignore")  # overlap / travel warnings of the transients are not the point
    from msmill.dem.backend import check_backend

    backend = check_backend("cuda" if a.device == "cuda" else "warp-cpu")
    name = device_name(a.device)
    print(f"device {name}; gas n={a.n} steps={a.steps}; slice window {a.window_s} s; "
          f"fine {a.fine_mm} mm chunk {a.fine_chunk_s} s", flush=True)
    warp = measure(backend, a)
    numba = measure("cpu", a)
    print(f"device={name} " + " ".join(f"{k}={v:.4g}" for k, v in warp.items()) + " "
          + " ".join(f"numba_{k}={v:.4g}" for k, v in numba.items()), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
