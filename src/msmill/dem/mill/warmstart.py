"""Warm start: begin a mill run from the hold-up of a finished run at a nearby design point.

Filling an empty mill costs 2-5 s of mill time, most of a training run. A
warm start places the final particles of a finished run (the *source*) into
the new scene at ``t = 0``, rescaled to this point (``docs/mill-dem.md``):

* **Phase of the rotors.** At the source's end every rotor had turned by
  ``omega t_end``; the new scene starts with its plates at phase 0. Rock
  within reach of a rotor's swept circle (centre closer than tip radius +
  rock radius to the axis) is turned back about the axis by ``-omega t_end``
  (positions and velocities), so it keeps its place relative to the plates.
* **Rock size.** Radii scale by ``size / source size``; only smaller or
  equal rock is allowed (positions then stay free of the geometry).
* **Feed rate.** The hold-up is taken proportional to the feed rate (the
  residence time barely changes with it): the target mass is the source's
  hold-up times ``feed / source feed``, reached by a random subsample; with
  smaller rock or more feed the source cannot supply it all, and the rest
  comes from the feed as in a cold start (the fraction placed is reported).
* **Speeds.** Velocities and spins scale by the upper-stage speed ratio.
* The gate angle, machine and slice must be the source's (rock at the gates
  would otherwise sit inside the new gate plates).

Particles that overlap after the rotation (at the edge of a swept circle) are
dropped greedily (the engine's overlap-free placement).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from msmill.dem import kernels as K
from msmill.errors import MsmillInputError
from msmill.machine import Machine, rpm_to_rad_s

__all__ = ["WarmStart", "place_warm_start"]


@dataclass(frozen=True)
class WarmStart:
    """Final particle state of a finished run and the design point it came from."""

    particles: pd.DataFrame
    time_s: float
    machine: Machine
    size_mm: float
    feed_kg_s: float
    stage_speeds_rpm: tuple[float, ...]
    gate_deg: float
    slice_length_m: float
    rock_density_kg_m3: float
    source: str = ""

    @classmethod
    def from_run(cls, run: Any) -> WarmStart:
        """From a :class:`msmill.dem.mill.run.MillRun`."""
        sc = run.scene
        return cls(particles=sc.sim.snapshot(), time_s=float(sc.sim.time_s), machine=sc.machine,
                   size_mm=float(sc.size_mm), feed_kg_s=float(sc.feed_kg_s),
                   stage_speeds_rpm=tuple(sc.op.stage_speeds(sc.machine.n_stages)), gate_deg=float(sc.op.gate_deg),
                   slice_length_m=float(sc.length_m), rock_density_kg_m3=float(sc.rock.density_kg_m3),
                   source=f"run at {sc.size_mm:g} mm, {sc.op.feed_tph:g} t/h")

    @classmethod
    def from_dir(cls, run_dir: str | Path) -> WarmStart:
        """From a directory written by ``msmill dem run`` (its last snapshot)."""
        from msmill.dem.mill.run import load_raw

        raw = load_raw(run_dir)
        s = raw["settings"]
        d, res = s["design"], s["result"]
        if "feed_scale" not in res:
            raise MsmillInputError("start", str(run_dir), "a run saved with its feed scale (msmill >= issue 20)")
        snaps = raw["snapshots"]
        t_end = float(snaps["time_s"].max())
        m: Machine = raw["machine"]
        length = m.casing_length_m * float(res["feed_scale"])
        return cls(particles=snaps[snaps["time_s"] == t_end].reset_index(drop=True), time_s=t_end, machine=m,
                   size_mm=float(d["size_mm"]), feed_kg_s=float(d["feed_tph"]) / 3.6 * float(res["feed_scale"]),
                   stage_speeds_rpm=tuple(d["stage_speeds_rpm"]), gate_deg=float(d["gate_deg"]),
                   slice_length_m=length, rock_density_kg_m3=float(s["rock"]["density_kg_m3"]),
                   source=str(run_dir))


def _turn_back(start: WarmStart, pos: np.ndarray, vel: np.ndarray, omg: np.ndarray, rad: np.ndarray) -> int:
    """Rotate rock near each rotor by ``-omega t_end`` about its axis (in place); returns how many turned."""
    m = start.machine
    n_turned = 0
    for stage in range(1, m.n_stages + 1):
        z0 = m.stage_axis_z_m(stage)
        w = rpm_to_rad_s(start.stage_speeds_rpm[stage - 1])
        for side in (0, 1):
            x0 = m.rotor_x_m(side)
            th = -m.omega_sign(stage, side) * w * start.time_s
            px, pz = pos[:, 0] - x0, pos[:, 2] - z0
            near = np.hypot(px, pz) < m.tip_radius_m + rad
            c, s = np.cos(th), np.sin(th)
            # rotation about +y by th (the engine's convention): x' = c x + s z, z' = -s x + c z
            pos[near, 0] = x0 + c * px[near] + s * pz[near]
            pos[near, 2] = z0 - s * px[near] + c * pz[near]
            for v in (vel, omg):
                vx, vz = v[near, 0].copy(), v[near, 2].copy()
                v[near, 0] = c * vx + s * vz
                v[near, 2] = -s * vx + c * vz
            n_turned += int(near.sum())
    return n_turned


def place_warm_start(scene: Any, start: WarmStart, seed: int = 0) -> dict[str, Any]:
    """Add the rescaled hold-up of ``start`` to a freshly built scene (before it runs); returns a report."""
    sc = scene
    if sc.sim.time_s > 0 or sc.sim.n_particles > 0:
        raise MsmillInputError("start", "scene already run", "a freshly built scene")
    if sc.machine != start.machine:
        raise MsmillInputError("start.machine", start.machine.name, f"the run's machine ({sc.machine.name})")
    if abs(sc.length_m - start.slice_length_m) > 1e-9:
        raise MsmillInputError("start.slice_length_m", start.slice_length_m, f"{sc.length_m:g} m (same slice)")
    if abs(sc.op.gate_deg - start.gate_deg) > 1e-9:
        raise MsmillInputError("start.gate_deg", start.gate_deg, f"{sc.op.gate_deg:g} deg (the run's gate angle)")
    size_ratio = sc.size_mm / start.size_mm
    if size_ratio > 1.0 + 1e-9:
        raise MsmillInputError("start.size_mm", start.size_mm, f">= {sc.size_mm:g} mm (rock the same size or coarser)")
    p = start.particles
    pos = p[["x_m", "y_m", "z_m"]].to_numpy(dtype=float).copy()
    vel = p[["vx_m_s", "vy_m_s", "vz_m_s"]].to_numpy(dtype=float).copy()
    omg = p[["wx_rad_s", "wy_rad_s", "wz_rad_s"]].to_numpy(dtype=float).copy()
    rad_src = p["radius_m"].to_numpy(dtype=float)
    n_turned = _turn_back(start, pos, vel, omg, rad_src)
    speed_ratio = sc.op.upper_speed_rpm / start.stage_speeds_rpm[0]
    vel *= speed_ratio
    omg *= speed_ratio / size_ratio  # rolling rock: spin ~ speed / radius
    rad = rad_src * size_ratio
    rho = sc.rock.density_kg_m3
    mass = rho * 4 / 3 * np.pi * rad**3
    target_kg = float((start.rock_density_kg_m3 * 4 / 3 * np.pi * rad_src**3).sum()) * sc.feed_kg_s / start.feed_kg_s
    rng = np.random.default_rng(seed)
    order = rng.permutation(len(rad))
    keep = order[np.cumsum(mass[order]) <= target_kg + 0.5 * float(mass.max(initial=0.0))]
    sim = sc.sim
    periodic = np.asarray(sim._periodic)
    box = np.asarray(sim._hi - sim._lo, dtype=float)
    _, ok = K.place_without_overlap(pos[keep][:, None, :], rad[keep], np.zeros((0, 3)), np.zeros(0), box, periodic)
    keep = keep[ok]
    if keep.size:
        sim.add_particles(pos[keep], rad[keep], vel[keep], material="rock", angular_velocities_rad_s=omg[keep])
    placed = float(mass[keep].sum())
    return {"source": start.source, "source_time_s": start.time_s, "n_source": len(rad),
            "n_placed": int(keep.size), "n_dropped_overlap": int((~ok).sum()), "n_turned_back": n_turned,
            "placed_kg": placed, "target_kg": target_kg, "placed_fraction": placed / target_kg if target_kg else 0.0,
            "size_ratio": size_ratio, "speed_ratio": speed_ratio,
            "feed_ratio": sc.feed_kg_s / start.feed_kg_s}
