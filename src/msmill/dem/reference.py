"""Reference scenes of the engine and bitwise digests of their trajectories.

Two short runs whose final state and contact events are stored as SHA-256
digests in ``tests/dem/data/trajectory_reference.json`` (written by
``scripts/dem_reference_trajectory.py``, checked by
``tests/dem/test_reference_trajectory.py``): a dense, frictional, damped
periodic gas (:func:`gas_sim`, threaded and serial kernels) and the default
mill slice at 30 mm rock (:func:`run_mill`). A change of the engine's memory
layout must leave every bit unchanged; a change that reorders sums changes the
bits and must regenerate the file. The digests depend on numba's generated
code, so on the toolchain and CPU (:func:`host_cpu`, :func:`host_cpu_features`).
:func:`lattice_gas` is the throughput benchmark's gas (``benchmarks/dem_throughput.py``).
"""

from __future__ import annotations

import hashlib
import warnings

import numpy as np

from msmill.dem.simulation import Simulation

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


def gas_sim(parallel: bool) -> Simulation:
    """The reference gas: 1200 spheres of 5 mm radius on a jittered lattice, dense and frictional."""
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
    """The reference gas after 400 steps of 1 us (:func:`state`)."""
    sim = gas_sim(parallel)
    sim.run(400e-6, dt_s=1e-6, progress=False, max_overlap_fraction=0.2)
    return state(sim)


def run_mill() -> dict[str, np.ndarray]:
    """The default mill slice at 30 mm rock after 0.4 s (:func:`state`)."""
    from msmill.dem.mill.scene import build_scene
    from msmill.machine import Machine, OperatingPoint

    sc = build_scene(Machine.default(), OperatingPoint(feed_tph=30.0, speed_rpm=1500.0, gate_deg=40.0),
                     size_mm=30.0)
    sc.sim.run(0.4, max_relative_speed_m_s=sc.max_impact_speed_m_s, progress=False)
    return state(sc.sim)


def state(sim: Simulation) -> dict[str, np.ndarray]:
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


def lattice_gas(n: int, phi: float, seed: int = 1) -> tuple[np.ndarray, np.ndarray, float, float]:
    """The throughput benchmark's gas: ``n`` spheres of 5 mm radius at solid fraction ``phi``.

    Returns
    -------
    (pos_m, vel_m_s, side_m, radius_m)
        Positions on a jittered cubic lattice in a cube of side ``side_m``
        (periodic), Gaussian velocities of 10 m/s per component (zero mean).
    """
    r = 0.005
    side = (n * 4.0 / 3.0 * np.pi * r**3 / phi) ** (1.0 / 3.0)
    m = int(np.ceil(n ** (1.0 / 3.0)))
    a = side / m
    rng = np.random.default_rng(seed)
    idx = np.stack(np.meshgrid(np.arange(m), np.arange(m), np.arange(m), indexing="ij"), -1)
    idx = idx.reshape(-1, 3)[rng.permutation(m**3)[:n]]
    jitter = (a - 2 * r) * 0.49 * rng.uniform(-1, 1, (n, 3))
    pos = (idx + 0.5) * a + jitter
    vel = rng.normal(0.0, 10.0, (n, 3))
    vel -= vel.mean(axis=0)
    return pos, vel, side, r
