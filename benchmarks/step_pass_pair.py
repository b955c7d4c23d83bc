"""Benchmark: the engine's step passes against those of another kernels file, side by side.

Builds the granular gas of ``benchmarks/dem_throughput.py``
(:func:`msmill.dem.reference.lattice_gas`: 20,000 spheres, e = 0.5, mu = 0.4,
no gravity) at each solid fraction, runs it 150 steps,
then calls the serial force pass, the serial integration pass and the
neighbour build of this checkout's ``msmill.dem.kernels`` and of ``--other``
(a ``kernels.py`` of another revision, e.g. ``git show REV:src/msmill/dem/kernels.py
> /tmp/kernels_rev.py``) on that same state, taking turns (the order swapped
every round), and prints the median time per particle and the median of the
paired ratios this / other. The integration pass runs with dt = 0, so the
state does not move between calls; the force pass is called at the last
step's time and stamp, so its contacts are those of a step (no new onsets
after the first call). A ratio below 1 means this checkout is faster. ``--mill-mm SIZE`` adds the
default mill slice at that rock size (30 t/h, 1500 rpm, gates 40 deg, run
serial to ``--mill-warm-s`` of mill time from empty; gravity, rotating
geometry), timed the same way.

The two files must agree on the kernels' signatures (a change of the
particle data's layout needs its own harness).

Run::

    python benchmarks/step_pass_pair.py --other /tmp/kernels_rev.py [--phi 0.05 0.30] [--rounds 60]
        [--mill-mm 10 --mill-warm-s 3.0]

The last line is ``cases=<a>,<b> force_ratio=<a>,<b> integrate_ratio=<a>,<b> neighbours_ratio=<a>,<b>``
(cases ``phi0.05``, ``phi0.30``, ``mill10mm``).
"""

from __future__ import annotations

import argparse
import importlib.util
import sys
import time
from pathlib import Path

import numpy as np

import msmill.dem  # noqa: F401  (chooses numba's threading layer first)
from msmill.dem import kernels as this


def load_kernels(path: Path):
    """Import a kernels file under its own module name (numba's cache needs the module importable)."""
    name = "kernels_other"
    spec = importlib.util.spec_from_file_location(name, path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    spec.loader.exec_module(mod)
    return mod


def gas_state(phi: float, n: int):
    """A gas after 150 steps (the benchmark's case), serial kernels."""
    from msmill.dem import Simulation
    from msmill.dem.reference import lattice_gas

    pos, vel, side, r = lattice_gas(n, phi)
    sim = Simulation((0, 0, 0), (side,) * 3, periodic=(True,) * 3, gravity_m_s2=(0, 0, 0), parallel=False)
    sim.add_material("rock", youngs_modulus_pa=2e10, poisson_ratio=0.25, density_kg_m3=2700)
    sim.set_interaction("rock", "rock", restitution=0.5, friction=0.4)
    sim.add_particles(pos, r, vel, material="rock")
    sim.run(150e-6, dt_s=1e-6, progress=False, max_overlap_fraction=0.1)
    return sim


def mill_state(size_mm: float, warm_s: float):
    """The default mill slice run serial from empty to ``warm_s`` of mill time."""
    import warnings

    from msmill.dem.mill.scene import build_scene
    from msmill.machine import Machine, OperatingPoint

    warnings.simplefilter("ignore")  # the fill's overlap warnings are not the point here
    sc = build_scene(Machine.default(), OperatingPoint(feed_tph=30.0, speed_rpm=1500.0, gate_deg=40.0),
                     size_mm=size_mm)
    sc.sim._par_mode = False  # serial kernels throughout
    sc.sim.run(warm_s, max_relative_speed_m_s=sc.max_impact_speed_m_s, progress=False)
    return sc.sim


def pass_calls(sim):
    """Argument builders of the three passes on the simulation's current state."""
    p = sim._p
    own_idx, own_start, act_idx, act_start = sim._work
    nb = sim._nb
    rec = sim._rec
    diag = np.zeros((sim._nch, 6))
    dt = sim.dt_s
    t_last = sim._time - dt

    def force():
        return (t_last, dt, p["pos"], p["vel"], p["omg"], p["rad"], p["mass"], p["invm"], p["invi"], p["mat"],
                p["pid"], p["frc"], p["trq"], sim._kind, own_idx, own_start, nb[0], nb[1], nb[2], nb[4],
                sim._stamp, sim._pair[0], sim._pair[3], sim._pair[1], sim._pair[2], sim._box_len, sim._gc[0],
                sim._gc[1], sim._gcur, sim._grot, sim._gkind, sim._gmat, sim._ptab, sim._gravity,
                p["h_pid"], p["h_st"], p["h_ev"], p["h_pk"], p["h_ds"], p["h_n"], p["h_tch"],
                p["g_gid"], p["g_st"], p["g_ev"], p["g_pk"], p["g_ds"], p["g_n"], p["g_tch"],
                rec.evf, rec.evi, rec.evn, diag)

    def integrate():
        return (sim._time, 0.0, p["pos"], p["vel"], p["omg"], p["frc"], p["trq"], sim._kind, act_idx, act_start,
                p["mass"], sim._gravity, nb[3], sim._stamp, sim._pair[0], sim._pair[3], sim._pair[1],
                sim._pair[2], p["invm"], p["invi"], p["flag"], p["flag_t"], sim._lo, sim._hi, sim._periodic,
                sim._sinkbox, diag)

    _c, start, order, cell = this.bin_cells(p["pos"], sim._lo, sim._cell_len, sim._ncell)

    def neighbours():
        return (p["pid"], p["pos"], p["rad"], sim._skin, cell, start, order, sim._ncell, sim._periodic,
                sim._box_len, False, sim._maxn)

    return {"force": ("force_pass_ser", force), "integrate": ("integrate_ser", integrate),
            "neighbours": ("build_neighbours", neighbours)}


def paired(mods, fname, args, rounds):
    """Median seconds per call of each module's ``fname`` and the median paired ratio mods[0] / mods[1]."""
    for m in mods:
        for _ in range(3):  # compile or load, warm the caches
            getattr(m, fname)(*args())
    ts = ([], [])
    for k in range(rounds):
        for i in ((0, 1) if k % 2 == 0 else (1, 0)):
            a = args()
            t0 = time.perf_counter()
            getattr(mods[i], fname)(*a)
            ts[i].append(time.perf_counter() - t0)
    a, b = np.array(ts[0]), np.array(ts[1])
    return float(np.median(a)), float(np.median(b)), float(np.median(a / b))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--other", type=Path, required=True, help="kernels.py of the revision to compare with")
    ap.add_argument("--phi", type=float, nargs="+", default=[0.05, 0.30])
    ap.add_argument("--n", type=int, default=20000)
    ap.add_argument("--rounds", type=int, default=60)
    ap.add_argument("--mill-mm", type=float, default=None, help="also the mill slice at this rock size (mm)")
    ap.add_argument("--mill-warm-s", type=float, default=3.0, help="mill time before timing (s)")
    args = ap.parse_args()
    if not args.other.is_file():
        raise SystemExit(f"--other: {args.other} is not a file (want a kernels.py, e.g. from git show)")
    mods = (this, load_kernels(args.other))
    out = {k: [] for k in ("force", "integrate", "neighbours")}
    cases = [(f"phi{phi:.2f}", lambda phi=phi: gas_state(phi, args.n)) for phi in args.phi]
    if args.mill_mm:
        cases.append((f"mill{args.mill_mm:g}mm", lambda: mill_state(args.mill_mm, args.mill_warm_s)))
    for case, make in cases:
        sim = make()
        n = sim.n_particles
        for key, (fname, builder) in pass_calls(sim).items():
            a, b, r = paired(mods, fname, builder, args.rounds)
            out[key].append(r)
            print(f"{case} ({n} particles) {key}: this {a / n * 1e9:.2f} ns/particle, other {b / n * 1e9:.2f}, "
                  f"paired this/other median {r:.3f} ({args.rounds} rounds, serial)", flush=True)
    fmt = lambda xs: ",".join(f"{x:.3f}" for x in xs)  # noqa: E731
    print(f"cases={','.join(c for c, _ in cases)} force_ratio={fmt(out['force'])} "
          f"integrate_ratio={fmt(out['integrate'])} neighbours_ratio={fmt(out['neighbours'])}")


if __name__ == "__main__":
    main()
