"""Warm starts: begin a mill run with rock in the mill instead of empty.

Two starts are provided (``docs/mill-dem.md``, Section 3.2):

* :func:`place_table_start` (``RunSettings(start="table")``, the campaign
  default): the steady hold-up the default stage table expects in each
  compartment, rock placed at random free positions. It needs no finished
  run, works at any gate angle, speed, feed rate and size, and is described
  below under *Start from the stage table*.
* :func:`place_warm_start` (``run_mill(..., start=WarmStart...)``): the final
  particles of a finished run at a nearby point with the same gate angle,
  described next.

Start from a finished run
-------------------------

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

Start from the stage table
--------------------------
Design choice (issue 12): a start from the *expected* hold-up rather than
from a source run at another gate angle with the rock in the new gates'
way dropped. Sobol and active-learning designs never repeat a gate angle,
and campaign workers keep no particles of finished runs, so a run-based
start would need raw snapshots shared between workers and would still leave
the first runs of a campaign cold; the table start needs neither.

* **Target per compartment.** The default stage table
  (``src/msmill/data/stage_parameters/default.json``: slice runs at 30 t/h,
  1500/3000 rpm, gates 40 deg, sizes 6-30 mm) gives per run the one-lag
  destinations of the inlet zone (``RunStatistics.inlet_destinations``) and of
  every stage (``StageStatistics.destinations``): a chain ``Q`` over the
  compartments 0 (inlet zone) .. n with the outlet absorbing. Fresh feed
  enters compartment 0, so the steady hold-up is ``h = F tau e0 (I - Q)^-1``
  (kg): the feed ``F`` (kg/s, the scene's, slice-scaled) times ``tau`` times
  the expected number of steps rock fed spends in each compartment. The
  residence per unit feed ``tau e0 (I - Q)^-1`` (s) is interpolated linearly
  in log rock size between the two table runs around the size (the end run
  outside the table). This rescales the hold-up to the point's feed rate and
  rock size; speeds and gate angle are not rescaled (the table has one of
  each), which only moves the start off the steady state the run then finds
  by itself. On the table's own runs the chain's hold-up per unit feed is
  within 24 % per compartment and 19 % in total of the hold-up measured in
  their windows over their feed (larger at 14 and 30 mm; the chain has no
  memory, and those windows put out 85-91 % of the feed).
* **Where rock goes.** Candidate centres are drawn uniformly in each
  compartment's band (:meth:`msmill.machine.Machine.stage_band_m`; the
  inlet zone from the top of stage 1 to below the feed source, i.e. the chute
  under the source) across the casing and kept when they are clear of every
  rotor's swept circle (tip radius + rock radius from the axis, so no
  flinger phase matters), outside the feed source regions, inside the
  casing (above the roof only within the chute; not behind a gate plate,
  where rock would fall straight out), and clear of every primitive of the
  scene (exact test with the engine's contact function, periodic images
  included: :func:`msmill.dem.kernels.geometry_overlap`). Rocks are then
  placed without overlapping one another
  (:func:`msmill.dem.kernels.place_without_overlap`, ``n_tries`` candidates
  each), with a downward velocity (the feed's 2 m/s) and no spin.
* **Mass.** Each compartment gets rocks (drawn from the scene's feed sizes)
  up to its target within half a rock's mass; a rock that finds no free place
  is left out, and the report says how much was placed per compartment.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from msmill.dem import kernels as K
from msmill.dem.mill.checks import START_KINDS, check_start_residence
from msmill.dem.mill.saved import load_raw
from msmill.errors import MsmillInputError
from msmill.machine import Machine, rpm_to_rad_s, size_mm_to_radius_m
from msmill.stageparams import RunStatistics, StageParameterTable, chain_visits, default_stage_table

__all__ = ["START_KINDS", "WarmStart", "place_table_start", "place_warm_start", "table_residence_s"]

#: Values of ``RunSettings.start``: an empty mill, or the stage table's expected hold-up.


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
    return {"kind": "run", "source": start.source, "source_time_s": start.time_s, "n_source": len(rad),
            "n_placed": int(keep.size), "n_dropped_overlap": int((~ok).sum()), "n_turned_back": n_turned,
            "placed_kg": placed, "target_kg": target_kg, "placed_fraction": placed / target_kg if target_kg else 0.0,
            "size_ratio": size_ratio, "speed_ratio": speed_ratio,
            "feed_ratio": sc.feed_kg_s / start.feed_kg_s}


# --------------------------------------------------------------------------- start from the stage table
def _chain_residence_s(run: RunStatistics) -> np.ndarray:
    """``tau e0 (I - Q)^-1``: steady hold-up per unit feed (s) of compartments 0 (inlet zone) .. n of one run."""
    return run.characteristic_time_s * chain_visits(run.destination_matrix())


def table_residence_s(size_mm: float, n_stages: int,
                      table: StageParameterTable | None = None) -> tuple[np.ndarray, dict[str, Any]]:
    """Expected steady hold-up per unit feed of each compartment, from a stage-parameter table.

    Parameters
    ----------
    size_mm : float
        Rock diameter (mm).
    n_stages : int
        Stages of the machine (the table's runs must have as many).
    table : StageParameterTable, optional
        Default: the shipped default table.

    Returns
    -------
    residence_s : ndarray, shape (n_stages + 1,)
        Hold-up / feed rate (s) of the inlet zone and stages 1..n: the chain of
        the one-lag destinations (module docstring), interpolated linearly in
        log size between the two runs around ``size_mm`` (the end run outside).
    source : dict
        ``table_sizes_mm`` and ``table_weights`` of the runs used, and a ``source`` line.
    """
    if table is None:
        table = default_stage_table()
    runs = [r for r in table.runs if r.n_stages == n_stages and r.inlet_destinations is not None
            and all(st.destinations is not None for st in r.stages)]
    if not runs:
        raise MsmillInputError("start", "table", f"a stage table with destinations for {n_stages} stages")
    runs.sort(key=lambda r: r.design.size_mm)
    sizes = np.array([r.design.size_mm for r in runs])
    res = np.array([_chain_residence_s(r) for r in runs])
    x = float(np.clip(np.log(size_mm), np.log(sizes[0]), np.log(sizes[-1])))
    hi = int(np.clip(np.searchsorted(np.log(sizes), x), 1, len(runs) - 1)) if len(runs) > 1 else 0
    lo = max(hi - 1, 0)
    w = 0.0 if hi == lo else (x - np.log(sizes[lo])) / (np.log(sizes[hi]) - np.log(sizes[lo]))
    out = (1 - w) * res[lo] + w * res[hi]
    used = [(float(sizes[lo]), 1 - w), (float(sizes[hi]), w)] if hi != lo else [(float(sizes[lo]), 1.0)]
    used = [(s, float(v)) for s, v in used if v > 0]
    return out, {"table_sizes_mm": [s for s, _ in used], "table_weights": [v for _, v in used],
                 "source": "stage table runs at " + ", ".join(f"{s:.3g} mm (weight {v:.2f})" for s, v in used)}


def _behind_gate(machine: Machine, gate_deg: float, x: np.ndarray, z: np.ndarray) -> np.ndarray:
    """True where ``(x, z)`` lies under a gate plate, between the plate and the liner (rock there falls out)."""
    hw, zh = machine.half_width_m, machine.gate_hinge_z_m
    xt, zt = machine.gate_tip_m(gate_deg, 1)
    reach = hw - xt  # horizontal reach of a gate from its liner (m)
    if reach <= 1e-12:
        return np.zeros(x.shape, dtype=bool)
    ax = np.abs(x)
    z_gate = zh + (zt - zh) * (hw - ax) / reach
    return (ax >= xt) & (z < z_gate)


def _clear_points(sc: Any, pts: np.ndarray, r: float, sources: list[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
    """Mask of candidate centres where a rock of radius ``r`` is clear of the scene and inside the mill."""
    m, sim = sc.machine, sc.sim
    x, z = pts[:, 0], pts[:, 2]
    ok = (np.abs(x) <= m.half_width_m - r) & (z > r)
    ok &= ~((z > m.roof_z_m) & (np.abs(x) > m.chute_width_m / 2 - r))  # above the roof only in the chute
    ok &= ~_behind_gate(m, sc.op.gate_deg, x, z)
    for stage in range(1, m.n_stages + 1):
        z0 = m.stage_axis_z_m(stage)
        for side in (0, 1):
            ok &= np.hypot(x - m.rotor_x_m(side), z - z0) >= m.tip_radius_m + r
    for lo, hi in sources:
        ok &= ~np.all((pts > lo - r) & (pts < hi + r), axis=1)
    idx = np.flatnonzero(ok)
    if idx.size:
        over = K.geometry_overlap(pts[idx], np.full(idx.size, r), sim._gcur, sim._gkind,
                                  np.asarray(sim._hi - sim._lo, dtype=float), np.asarray(sim._periodic))
        ok[idx[over > 0.0]] = False
    return ok


def _draw_radii(rng: np.random.Generator, radii: np.ndarray, weights: np.ndarray, rho: float,
                target_kg: float) -> np.ndarray:
    """Rock radii drawn from the feed sizes up to ``target_kg`` within half the largest rock's mass."""
    mass = rho * 4 / 3 * np.pi * radii**3
    half = 0.5 * float(mass.max())
    n = int(2 * target_kg / float(np.sum(weights * mass))) + 10
    draw = rng.choice(radii, size=n, p=weights)
    while rho * 4 / 3 * np.pi * float(np.sum(draw**3)) <= target_kg + half:
        draw = np.concatenate([draw, rng.choice(radii, size=n, p=weights)])
    cum = np.cumsum(rho * 4 / 3 * np.pi * draw**3)
    return draw[: int(np.searchsorted(cum, target_kg + half, side="right"))]


def place_table_start(scene: Any, table: StageParameterTable | None = None, seed: int = 0,
                      speed_m_s: float = 2.0, n_tries: int = 50, fill: float = 1.0,
                      residence_s: Sequence[float] | None = None) -> dict[str, Any]:
    """Fill a freshly built scene with the stage table's expected steady hold-up; returns a report.

    Parameters
    ----------
    scene : MillScene
        Built, not yet run.
    table : StageParameterTable, optional
        Default: the shipped default table (:func:`table_residence_s`).
    seed : int
        Seed of the positions and sizes.
    speed_m_s : float
        Downward speed of the placed rock (m/s).
    n_tries : int
        Candidate positions per rock.
    fill : float
        Multiplies the target hold-up (1: the table's steady hold-up).
    residence_s : sequence of float, optional
        Residence (hold-up / feed, s) per compartment (inlet zone, stages 1..n) instead of the table's,
        for example the steady one a finished run near this point measured
        (:meth:`msmill.stageparams.RunStatistics.compartment_residence_s`).

    Returns
    -------
    dict
        ``kind = "table"``, ``source``, ``table_sizes_mm``, ``table_weights``,
        per compartment (inlet zone, stages 1..n) ``residence_s`` (s),
        ``compartment_target_kg``, ``compartment_placed_kg``,
        ``compartment_n_placed``, and totals ``target_kg``, ``placed_kg``,
        ``placed_fraction``, ``n_placed``.
    """
    sc, sim, m = scene, scene.sim, scene.machine
    if sim.time_s > 0 or sim.n_particles > 0:
        raise MsmillInputError("start", "scene already run", "a freshly built scene")
    if not (speed_m_s >= 0 and np.isfinite(speed_m_s)):
        raise MsmillInputError("speed_m_s", speed_m_s, "a finite speed >= 0 (m/s)")
    if not (fill >= 0 and np.isfinite(fill)):
        raise MsmillInputError("fill", fill, "a finite factor >= 0")
    if int(n_tries) < 1:
        raise MsmillInputError("n_tries", n_tries, "an integer >= 1")
    if residence_s is None:
        residence, src = table_residence_s(sc.size_mm, m.n_stages, table)
    else:
        check_start_residence(residence_s, m.n_stages, "residence_s")
        residence = np.asarray(residence_s, dtype=float)
        src = {"source": "given residence per compartment (s): " + ", ".join(f"{v:.4g}" for v in residence)}
    target = sc.feed_kg_s * residence * fill
    if sim._dirty:
        sim._pack()  # the geometry at t = 0
    rng = np.random.default_rng(seed)
    rho = sc.rock.density_kg_m3
    radii = size_mm_to_radius_m(sc.sizes_mm)
    weights = np.asarray(sc.mass_fractions, dtype=float) / radii**3
    weights = weights / weights.sum()
    r_max = float(radii.max())
    lo_dom, hi_dom = np.asarray(sim._lo, dtype=float), np.asarray(sim._hi, dtype=float)
    periodic = np.asarray(sim._periodic)
    box = hi_dom - lo_dom
    sources = [(np.asarray(s["lo"], dtype=float), np.asarray(s["hi"], dtype=float)) for s in sim._sources]
    top = min([float(lo[2]) for lo, _ in sources], default=float(hi_dom[2])) - r_max
    bands = [(m.inlet_zone_bottom_z_m, top)] + [m.stage_band_m(s) for s in range(1, m.n_stages + 1)]
    # sampling box: across the casing, along the slice (any y if periodic), within the band
    pad = np.where(periodic.astype(bool), 0.0, r_max)
    all_pos, all_rad = np.zeros((0, 3)), np.zeros(0)
    placed_kg, n_placed = [], []
    for (z_lo, z_hi), tgt in zip(bands, target, strict=True):  # one pass per compartment (n + 1), not per rock
        rad = _draw_radii(rng, radii, weights, rho, float(tgt)) if tgt > 0 else np.zeros(0)
        z_lo, z_hi = max(z_lo, r_max), min(z_hi, hi_dom[2] - r_max)
        if rad.size == 0 or z_hi <= z_lo:
            placed_kg.append(0.0)
            n_placed.append(0)
            continue
        b_lo = np.array([lo_dom[0] + pad[0], lo_dom[1] + pad[1], z_lo])
        b_hi = np.array([hi_dom[0] - pad[0], hi_dom[1] - pad[1], z_hi])
        want = rad.size * int(n_tries)
        pool, n_pool = [], 0
        for _ in range(20):  # batches of candidates until enough are clear
            pts = b_lo + rng.random((min(max(4 * (want - n_pool), 1000), 2_000_000), 3)) * (b_hi - b_lo)
            pts = pts[_clear_points(sc, pts, r_max, sources)]
            pool.append(pts)
            n_pool += len(pts)
            if n_pool >= want:
                break
        free = np.concatenate(pool)
        if len(free) == 0:
            placed_kg.append(0.0)
            n_placed.append(0)
            continue
        pick = rng.permutation(len(free))[:want] if len(free) >= want else rng.integers(len(free), size=want)
        cand = free[pick].reshape(rad.size, int(n_tries), 3)
        near = (all_pos[:, 2] > z_lo - 2 * r_max) & (all_pos[:, 2] < z_hi + 2 * r_max)
        out, ok = K.place_without_overlap(cand, rad, all_pos[near], all_rad[near], box, periodic)
        all_pos = np.concatenate([all_pos, out[ok]])
        all_rad = np.concatenate([all_rad, rad[ok]])
        placed_kg.append(float(rho * 4 / 3 * np.pi * np.sum(rad[ok] ** 3)))
        n_placed.append(int(ok.sum()))
    if all_rad.size:
        vel = np.zeros((all_rad.size, 3))
        vel[:, 2] = -speed_m_s
        sim.add_particles(all_pos, all_rad, vel, material="rock")
    total_target, total_placed = float(target.sum()), float(sum(placed_kg))
    return {"kind": "table", **src, "residence_s": [float(v) for v in residence],
            "compartment_target_kg": [float(v) for v in target], "compartment_placed_kg": placed_kg,
            "compartment_n_placed": n_placed, "target_kg": total_target, "placed_kg": total_placed,
            "placed_fraction": total_placed / total_target if total_target else 0.0,
            "n_placed": int(all_rad.size), "speed_m_s": float(speed_m_s), "fill": float(fill)}
