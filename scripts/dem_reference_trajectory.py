"""Write (or check) the engine's reference trajectories for the bitwise re-layout test.

Two short runs: a dense, frictional, damped periodic gas (1200 spheres, solid
fraction ~0.3, 400 steps, threaded and serial kernels) and the default mill
slice at 30 mm rock (rotating geometry, sources, sinks) for 0.4 s of mill
time. Per run it stores the final particle state ordered by particle id and
the contact events ordered by (owner, partner, onset), and writes their
SHA-256 digests with provenance, so a change of the
engine's memory layout can be checked to leave every bit unchanged
(``tests/dem/test_reference_trajectory.py``). A change that reorders sums
(e.g. a different particle sort) changes the bits; such a change must then
regenerate this file with this script and say so.

Run::

    python scripts/dem_reference_trajectory.py [--out tests/dem/data/trajectory_reference.json]
    python scripts/dem_reference_trajectory.py --check   # compare with the stored digests, run by run
"""

from __future__ import annotations

import argparse
import datetime as _dt
import hashlib
import json
import warnings
from pathlib import Path

import numpy as np

import msmill
import msmill.dem  # chooses numba's threading layer first

OUT = Path(__file__).resolve().parents[1] / "tests" / "dem" / "data" / "trajectory_reference.json"
FIELDS = ("pos", "vel", "omg")
EV_COLS = ("time_s", "x_m", "y_m", "z_m", "vn_m_s", "vt_m_s", "end_time_s", "peak_overlap_m",
           "dissipated_j")



def host_cpu() -> str:
    """The CPU numba compiles for (its code, and so the last bits of a trajectory, depend on it)."""
    import llvmlite.binding as ll

    return str(ll.get_host_cpu_name())


def host_cpu_features() -> str:
    """Short digest of the CPU features numba compiles for.

    Two hosts that both report ``znver4`` gave different gas digests with the
    same numba and numpy (2026-12-04; the mill slice's were the same), so the
    features are part of the key as well. They may still not be all of it.
    """
    import llvmlite.binding as ll

    feats = sorted(f for f in ll.get_host_cpu_features().flatten().split(",") if f.startswith("+"))
    return hashlib.sha256(",".join(feats).encode()).hexdigest()[:16]


def gas_sim(parallel: bool):
    """Dense frictional gas: 1200 spheres of 5 mm radius on a jittered lattice."""
    from msmill.dem import Simulation

    n_side, r, spacing = 11, 0.005, 0.0121
    side = n_side * spacing
    sim = Simulation((0, 0, 0), (side, side, side), periodic=(True, True, True),
                     gravity_m_s2=(0, 0, 0), parallel=parallel, parallel_min_particles=1, sort_every=2)
    sim.add_material("rock", youngs_modulus_pa=2e10, poisson_ratio=0.25, density_kg_m3=2700)
    sim.set_interaction("rock", "rock", restitution=0.5, friction=0.4)
    g = (np.stack(np.meshgrid(*[np.arange(n_side)] * 3, indexing="ij"), -1).reshape(-1, 3)
         + 0.5) * spacing
    rng = np.random.default_rng(7)
    g += rng.uniform(-1, 1, g.shape) * 0.45 * (spacing - 2 * r)
    v = rng.normal(0, 10.0, g.shape)
    v -= v.mean(axis=0)
    w = rng.normal(0, 10.0 / r, g.shape)
    sim.add_particles(g, r, v, material="rock", angular_velocities_rad_s=w)
    return sim


def run_gas(parallel: bool) -> dict[str, np.ndarray]:
    sim = gas_sim(parallel)
    sim.run(400e-6, dt_s=1e-6, progress=False, max_overlap_fraction=0.2)
    return state(sim)


def run_mill() -> dict[str, np.ndarray]:
    from msmill.dem.mill.scene import build_scene
    from msmill.machine import Machine, OperatingPoint

    sc = build_scene(Machine.default(), OperatingPoint(feed_tph=30.0, speed_rpm=1500.0, gate_deg=40.0),
                     size_mm=30.0)
    sc.sim.run(0.4, max_relative_speed_m_s=sc.max_impact_speed_m_s, progress=False)
    return state(sc.sim)


def state(sim) -> dict[str, np.ndarray]:
    """Final state by particle id and the events in a canonical order."""
    p = sim._p
    o = np.argsort(p["pid"])
    out = {k: p[k][o].copy() for k in FIELDS}
    out["pid"] = p["pid"][o].copy()
    ev = sim.events()
    if len(ev):
        ev = ev.sort_values(["particle_id", "partner_kind", "partner_id", "time_s"], kind="stable")
    out["ev_int"] = ev[["particle_id", "partner_kind", "partner_id"]].to_numpy(np.int64) if len(ev) else np.zeros((0, 3), np.int64)
    out["ev_float"] = ev[list(EV_COLS)].to_numpy(np.float64) if len(ev) else np.zeros((0, len(EV_COLS)))
    return out


def digest(a: np.ndarray) -> str:
    """SHA-256 of an array's dtype, shape and bytes (C order)."""
    h = hashlib.sha256(f"{a.dtype.str}{a.shape}".encode())
    h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


def all_runs() -> dict[str, np.ndarray]:
    """Every run's final state and events, keyed ``run/field``."""
    warnings.simplefilter("ignore")
    res = {}
    for name, st in (("gas_par", run_gas(True)), ("gas_ser", run_gas(False)), ("mill", run_mill())):
        for k, v in st.items():
            res[f"{name}/{k}"] = v
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=OUT)
    ap.add_argument("--check", action="store_true", help="compare with --out instead of writing it")
    args = ap.parse_args()
    res = all_runs()
    hashes = {k: digest(v) for k, v in res.items()}
    if args.check:
        ref = json.loads(args.out.read_text())["sha256"]
        for k, h in hashes.items():
            print(f"{k}: {'identical' if ref.get(k) == h else 'DIFFERS'}")
        print(f"identical={all(ref.get(k) == h for k, h in hashes.items())}")
        return
    from msmill.provenance import git_commit

    commit = git_commit() or ""
    prov = {"command": "python scripts/dem_reference_trajectory.py", "commit": commit,
            "msmill_version": msmill.__version__,
            "date_utc": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
            "numba": __import__("numba").__version__, "numpy": np.__version__, "host_cpu": host_cpu(),
            "host_cpu_features": host_cpu_features(),
            "runs": {"gas": "1200 spheres r 5 mm, E 2e10, e 0.5, mu 0.4, 400 steps dt 1e-6 s, seed 7",
                     "mill": "default slice, 30 mm, 30 t/h, 1500 rpm, gates 40 deg, 0.4 s"},
            "events": {k: int(res[f"{k}/ev_int"].shape[0]) for k in ("gas_par", "gas_ser", "mill")},
            "sha256": hashes}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(prov, indent=1) + "\n")
    print(json.dumps(prov, indent=1))


if __name__ == "__main__":
    main()
