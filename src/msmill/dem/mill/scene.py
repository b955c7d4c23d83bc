"""Build the DEM scene of a multi-shaft mill from a Machine and a design point.

The scene uses the engine API of :mod:`msmill.dem` (``Simulation``,
``Rotation``) and the coordinate frame of :mod:`msmill.machine` (x across the
shafts, y along them, z up, outlet plane at z = 0).

Geometry and tags
-----------------
* ``liner``: the two side liners (planes ``x = +-W/2``), in full mode the two
  end walls (planes ``y = 0`` and ``y = L``), and the roof plates on either
  side of the chute opening.
* ``chute``: the two chute walls (vertical plates ``x = +-w_c/2`` above the
  roof) and the chute lid, under which the feed source sits.
* ``hub``: one rotating cylinder per rotor (group = rotor index).
* ``flinger``: one rotating oriented plate (box) per flinger (group = rotor
  index ``2 (stage - 1) + side``, side 0 = left; the stage is ``group // 2 + 1``).
  A plate spans radially from the hub to the tip radius. Flinger ``k`` of row
  ``j`` of a left rotor starts at angle ``machine.flinger_phase_deg(j, k)``
  (from +x towards +z); right rotors are the mirror image (``180 deg -`` that),
  so a counter-rotating pair stays mirror-symmetric.
* ``gate``: the two outlet gates (plates at the gate angle, groups 0 left, 1 right).
* ``deflector``: deflector plates of the machine (group = stage).
* sink ``outlet``: everything whose centre falls below ``z = 0``.

Modes
-----
``full``: the whole casing length ``L``, closed by end walls. ``slice``: one
flinger row (``row_pitch_m`` long, row 0, periodic along y); the feed is
scaled by ``slice length / casing_length_m``. The slice holds the machine's
own flinger plates of its rows (80 mm wide in a 100 mm row for the default),
so a rock can pass a rotor through the gap between a plate and its periodic
image exactly as in the machine; the engine meets plates across the periodic
boundary through their periodic images. (Earlier builds used one
continuous plate per flinger, 1.25 times the machine's flinger area, because
plate side edges at the periodic boundary blew up: the engine did not image
geometry then.) Liners, hubs, gates and deflectors span the slice and
overhang it, and are taken as continuous along the shafts. The engine needs a periodic
length of at least three neighbour cells (``3 (2 r_max + skin)``; the slice is sized
with a skin of ``SLICE_SKIN_RADII`` = 1.5 radii of the smallest rock, and the
engine's skin is at most what fits, :func:`mill_skin_m`), so for rocks above about
19 mm (default machine) the slice holds the smallest whole number of rows that
satisfies this (2 rows for 20 and 30 mm rock).

Rock stiffness
--------------
The Hertz time step falls with stiffness (``t_c ~ E*^-0.4``), so the rock's
Young's modulus is softened as far as the overlap limit allows (domain-notes
Section 5): for a sphere of density ``rho`` hitting a wall at speed ``v`` the
peak Hertz overlap relative to its radius is ``delta/R = (5 pi rho v^2 /
(4 E*))^(2/5)``, independent of size. Requiring ``delta/R <= f`` at the
highest expected impact speed ``v_max`` (the fastest flinger tip speed plus
``approach_margin_m_s`` for the rock's own speed) gives ``E* >= 5 pi rho
v_max^2 / (4 f^(5/2))``; the rock modulus used is the smaller of the real one
and the one giving that ``E*`` against steel. At mill speeds (tip speeds
30-60 m/s) real rock (E ~ 50 GPa) already overlaps ~5 % at the tip speed, so
with the default ``f = 0.05`` little or no softening is possible; the E used,
``v_max`` and the overlap it gives are reported in :attr:`MillScene.info`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from msmill.errors import MsmillInputError
from msmill.machine import Machine, OperatingPoint, check_size_mm, rpm_to_rad_s, size_mm_to_radius_m

__all__ = ["STEEL", "MillScene", "RockMaterial", "build_scene", "mill_skin_m", "peak_overlap_fraction", "softened_youngs_modulus"]

#: Restitution and friction of the paper (Section 2): rock-rock, rock-steel.
ROCK_ROCK = {"restitution": 0.5, "friction": 0.4}
ROCK_STEEL = {"restitution": 0.2, "friction": 0.3}
#: Verlet skin of mill scenes, in radii of the smallest rock (at most what the slice's periodic
#: length allows, see :func:`mill_skin_m`)
SKIN_RADII = 2.0
#: skin, in radii of the smallest rock, that sizes a periodic slice (:func:`scene_extent`): the
#: slice's rows do not follow the engine's skin
SLICE_SKIN_RADII = 1.5


@dataclass(frozen=True)
class RockMaterial:
    """Elastic properties of rock (or steel).

    Parameters
    ----------
    youngs_modulus_pa : float
        Young's modulus (Pa).
    poisson_ratio : float
    density_kg_m3 : float
    name : str
    """

    youngs_modulus_pa: float = 50e9
    poisson_ratio: float = 0.25
    density_kg_m3: float = 2700.0
    name: str = "generic rock"


STEEL = RockMaterial(youngs_modulus_pa=210e9, poisson_ratio=0.30, density_kg_m3=7850.0, name="steel")


def _estar(a: RockMaterial, b: RockMaterial) -> float:
    return 1.0 / ((1 - a.poisson_ratio**2) / a.youngs_modulus_pa + (1 - b.poisson_ratio**2) / b.youngs_modulus_pa)


def peak_overlap_fraction(rock: RockMaterial, speed_m_s: float, wall: RockMaterial = STEEL) -> float:
    """Peak Hertz overlap / radius of a rock sphere hitting a fixed wall at ``speed_m_s``."""
    return (5 * math.pi * rock.density_kg_m3 * speed_m_s**2 / (4 * _estar(rock, wall))) ** 0.4


def softened_youngs_modulus(
    rock: RockMaterial, max_speed_m_s: float, max_overlap_fraction: float = 0.05, wall: RockMaterial = STEEL
) -> float:
    """Smallest rock modulus (Pa, capped at the real one) keeping the overlap within the limit.

    See the module docstring for the formula.
    """
    estar = 5 * math.pi * rock.density_kg_m3 * max_speed_m_s**2 / (4 * max_overlap_fraction**2.5)
    rest = 1.0 / estar - (1 - wall.poisson_ratio**2) / wall.youngs_modulus_pa
    if rest <= 0:
        return rock.youngs_modulus_pa
    return float(min(rock.youngs_modulus_pa, (1 - rock.poisson_ratio**2) / rest))


@dataclass
class MillScene:
    """A built mill scene: the engine simulation plus what it was built from."""

    sim: Any
    machine: Machine
    op: OperatingPoint
    mode: str
    size_mm: float
    sizes_mm: np.ndarray
    mass_fractions: np.ndarray
    y_range_m: tuple[float, float]
    feed_kg_s: float
    rock: RockMaterial
    rock_used: RockMaterial
    max_impact_speed_m_s: float
    info: dict[str, Any] = field(default_factory=dict)

    @property
    def length_m(self) -> float:
        """Length of the simulated casing along the shafts (m)."""
        return self.y_range_m[1] - self.y_range_m[0]


def _plate_axes(ex: np.ndarray) -> np.ndarray:
    """Rows ex, ey = +y, ez = ex x ey for a plate whose long direction ``ex`` lies in the x-z plane."""
    ex = np.asarray(ex, float) / np.linalg.norm(ex)
    ey = np.array([0.0, 1.0, 0.0])
    return np.vstack([ex, ey, np.cross(ex, ey)])


def _sloped_plate(sim: Any, hinge_xz: tuple[float, float], tip_xz: tuple[float, float], y0: float, y1: float,
                  tag: str, group: int) -> int:
    (hx, hz), (tx, tz) = hinge_xz, tip_xz
    ex = np.array([tx - hx, 0.0, tz - hz])
    length = float(np.linalg.norm(ex))
    centre = ((hx + tx) / 2, (y0 + y1) / 2, (hz + tz) / 2)
    return sim.add_box(centre, (length / 2, (y1 - y0) / 2, 0.0), axes=_plate_axes(ex), material="steel",
                       tag=tag, group=group)


def scene_extent(machine: Machine, sizes_mm: np.ndarray, mode: str) -> tuple[float, float, list[int], float]:
    """Extent of the scene along the rotor axis: ``(y0_m, y1_m, flinger rows, feed scale)``.

    A periodic slice holds as many flinger rows as the engine needs (>= 3
    neighbour cells of ``2 r_max + skin`` along the periodic axis); the feed
    scale is the slice's share of the casing length (1 for the full mill).
    """
    sizes = np.asarray(sizes_mm, dtype=float)
    if mode != "slice":
        return 0.0, machine.casing_length_m, list(range(machine.flinger_rows)), 1.0
    skin = SLICE_SKIN_RADII * size_mm_to_radius_m(float(sizes.min()))
    need = 3 * (2 * size_mm_to_radius_m(float(sizes.max())) + skin) * 1.001
    n_rows = min(machine.flinger_rows, max(1, math.ceil(need / machine.row_pitch_m)))
    y0 = machine.row_y_m(0) - machine.row_pitch_m / 2
    y1 = y0 + n_rows * machine.row_pitch_m
    return y0, y1, list(range(n_rows)), (y1 - y0) / machine.casing_length_m


def mill_skin_m(sizes_mm: np.ndarray, periodic_length_m: float = math.inf) -> float:
    """Verlet skin of a mill scene (m): ``SKIN_RADII`` radii of the smallest rock, at most what fits.

    The lists are rebuilt whenever the fastest rock (~2 tip speeds) may have
    moved half the skin: every ~7 steps at the engine default of half a
    radius. A wider skin means fewer rebuilds but more list entries per step:
    1.5 radii made 10 mm slice runs ~1.5x faster than 0.5; 2.0 radii, with
    the finer neighbour cells of ``CELLS_PER_PARTICLE = 64``, another 1.1-1.3x
    at 6-20 mm (2.5 and 3.0 were slower at 10 and 20 mm; docs/dem.md,
    Performance). A periodic slice (sized by :func:`scene_extent` with
    ``SLICE_SKIN_RADII``) keeps at least three cells of ``2 r_max + skin``.
    """
    sizes = np.asarray(sizes_mm, dtype=float)
    skin = SKIN_RADII * size_mm_to_radius_m(float(sizes.min()))
    fit = periodic_length_m / (3 * 1.001) - 2 * size_mm_to_radius_m(float(sizes.max()))
    return min(skin, fit)


def build_scene(
    machine: Machine,
    op: OperatingPoint,
    size_mm: float | None = None,
    feed_psd: tuple[Any, Any] | None = None,
    mode: str = "slice",
    rock: RockMaterial | None = None,
    ore: str | None = None,
    max_overlap_fraction: float = 0.05,
    approach_margin_m_s: float = 5.0,
    feed_speed_m_s: float = 2.0,
    seed: int = 0,
    backend: str = "cpu",
) -> MillScene:
    """Build the engine scene of the mill at one design point.

    Parameters
    ----------
    machine : Machine
    op : OperatingPoint
        Feed rate (t/h, full-mill value), shaft speeds (rpm), gate angle (deg).
    size_mm : float, optional
        Diameter of mono-size rock (mm). Give this or ``feed_psd``.
    feed_psd : (sizes_mm, mass_fractions), optional
        Discrete feed size distribution: sphere diameters (mm) and their mass
        fractions (converted to number weights for the source).
    mode : {"slice", "full"}
    rock : RockMaterial, optional
        Real rock properties; default from ``ore`` or a generic rock
        (50 GPa, 0.25, 2700 kg/m3).
    ore : str, optional
        Name of an ore in :mod:`msmill.ore` whose density/stiffness to use
        (if that module provides them).
    max_overlap_fraction : float
        Overlap limit used to soften the rock modulus (see module docstring).
    approach_margin_m_s : float
        Added to the fastest tip speed for the highest expected impact speed (m/s).
    feed_speed_m_s : float
        Downward speed of fed rock leaving the source in the chute (m/s).
    seed : int
        Seed of the feed source.
    backend : str
        Step kernels of the engine (:mod:`msmill.dem.backend`; ``RunSettings.backend``).
    """
    from msmill.dem import Simulation

    if mode not in ("slice", "full"):
        raise MsmillInputError("mode", mode, "'slice' or 'full'")
    sizes, mfrac = _feed_sizes(size_mm, feed_psd)
    d50 = float(np.exp(np.sum(mfrac * np.log(sizes))))
    if rock is None:
        rock = _rock_from_ore(ore) if ore else RockMaterial()
    speeds = op.stage_speeds(machine.n_stages)
    v_tip = max(machine.tip_speed_m_s(s) for s in speeds)
    v_max = v_tip + approach_margin_m_s
    e_used = softened_youngs_modulus(rock, v_max, max_overlap_fraction)
    rock_used = RockMaterial(e_used, rock.poisson_ratio, rock.density_kg_m3, rock.name + " (softened)"
                             if e_used < rock.youngs_modulus_pa else rock.name)

    hw = machine.half_width_m
    y0, y1, rows, scale = scene_extent(machine, sizes, mode)
    skin = mill_skin_m(sizes, y1 - y0 if mode == "slice" else math.inf)
    ext = 0.05 if mode == "slice" else 0.0  # liners, hubs, gates overhang a periodic slice
    top = machine.roof_z_m + _CHUTE_HEIGHT_M
    sim = Simulation(
        domain_min_m=(-hw - 0.02, y0, -0.15), domain_max_m=(hw + 0.02, y1, top + 0.02),
        periodic=(False, mode == "slice", False), gravity_m_s2=(0.0, 0.0, -9.81), neighbor_skin_m=skin,
        backend=backend,
    )
    sim.add_material("rock", youngs_modulus_pa=e_used, poisson_ratio=rock.poisson_ratio,
                     density_kg_m3=rock.density_kg_m3)
    sim.add_material("steel", youngs_modulus_pa=STEEL.youngs_modulus_pa, poisson_ratio=STEEL.poisson_ratio,
                     density_kg_m3=STEEL.density_kg_m3)
    sim.set_interaction("rock", "rock", **ROCK_ROCK)
    sim.set_interaction("rock", "steel", **ROCK_STEEL)
    _add_casing(sim, machine, mode, (y0, y1), ext)
    omegas = _add_rotors(sim, machine, speeds, rows, (y0, y1), ext)
    _add_gates_and_deflectors(sim, machine, op.gate_deg, (y0, y1), ext)
    feed_kg_s = op.feed_tph * 1000.0 / 3600.0 * scale
    _add_feed_and_outlet(sim, machine, feed_kg_s, sizes, mfrac, mode, (y0, y1), feed_speed_m_s, seed)

    info = {
        "mode": mode,
        "slice_length_m": y1 - y0,
        "slice_rows": len(rows),
        "feed_scale": scale,
        "feed_kg_s": feed_kg_s,
        "size_mm": d50,
        "stage_speeds_rpm": speeds,
        "rotor_omega_rad_s": [omegas[g] for g in sorted(omegas)],
        "tip_speed_max_m_s": v_tip,
        "max_impact_speed_m_s": v_max,
        "rock_youngs_modulus_real_pa": rock.youngs_modulus_pa,
        "rock_youngs_modulus_used_pa": e_used,
        "rock_poisson_ratio": rock.poisson_ratio,
        "rock_density_kg_m3": rock.density_kg_m3,
        "max_overlap_fraction": max_overlap_fraction,
        "peak_overlap_fraction_at_max_speed": peak_overlap_fraction(rock_used, v_max),
        "rock_name": rock.name,
        "restitution": {"rock_rock": ROCK_ROCK["restitution"], "rock_steel": ROCK_STEEL["restitution"]},
        "friction": {"rock_rock": ROCK_ROCK["friction"], "rock_steel": ROCK_STEEL["friction"]},
        "seed": seed,
    }
    return MillScene(sim=sim, machine=machine, op=op, mode=mode, size_mm=d50, sizes_mm=sizes, mass_fractions=mfrac,
                     y_range_m=(y0, y1), feed_kg_s=feed_kg_s, rock=rock, rock_used=rock_used,
                     max_impact_speed_m_s=v_max, info=info)


#: Height of the feed chute above the roof (m).
_CHUTE_HEIGHT_M = 0.4


def _feed_sizes(size_mm: float | None, feed_psd: tuple[Any, Any] | None) -> tuple[np.ndarray, np.ndarray]:
    """``(sphere diameters mm, mass fractions summing to 1)`` of mono-size rock or a discrete feed."""
    if (size_mm is None) == (feed_psd is None):
        raise MsmillInputError("size_mm/feed_psd", (size_mm, feed_psd), "exactly one of the two")
    if feed_psd is not None:
        sizes = np.asarray(feed_psd[0], dtype=float)
        mfrac = np.asarray(feed_psd[1], dtype=float)
        if sizes.ndim != 1 or sizes.shape != mfrac.shape or np.any(sizes <= 0) or np.any(mfrac < 0) or mfrac.sum() <= 0:
            raise MsmillInputError("feed_psd", feed_psd, "(sizes_mm, mass_fractions) of equal length, sizes > 0")
        mfrac = mfrac / mfrac.sum()
    else:
        if not (size_mm and size_mm > 0):
            raise MsmillInputError("size_mm", size_mm, "a rock diameter > 0 mm")
        sizes, mfrac = np.array([float(size_mm)]), np.array([1.0])
    for s in sizes:
        check_size_mm(s)
    return sizes, mfrac


def _add_casing(sim: Any, machine: Machine, mode: str, y_m: tuple[float, float], ext: float) -> None:
    """Side liners (and the end walls of a full mill), the roof and the feed chute with its lid."""
    y0, y1 = y_m
    hw, roof, chute_h = machine.half_width_m, machine.roof_z_m, _CHUTE_HEIGHT_M
    top = roof + chute_h
    sim.add_plane((-hw, 0, 0), (1, 0, 0), material="steel", tag="liner", group=0)
    sim.add_plane((hw, 0, 0), (-1, 0, 0), material="steel", tag="liner", group=1)
    if mode == "full":
        sim.add_plane((0, 0, 0), (0, 1, 0), material="steel", tag="liner", group=2)
        sim.add_plane((0, y1, 0), (0, -1, 0), material="steel", tag="liner", group=3)
    yc, yh = (y0 + y1) / 2, (y1 - y0) / 2 + ext
    cw = machine.chute_width_m / 2
    roof_half = (hw - cw) / 2
    # roof, chute walls and lid are solid slabs on their outer side (a rock pressed against a plate of
    # zero thickness by a flinger could be pushed through it; a 50 mm slab cannot be crossed)
    slab = 0.05
    for side in (-1, 1):
        sim.add_box((side * (cw + roof_half), yc, roof + slab), (roof_half, yh, slab), material="steel",
                    tag="liner", group=4)
        sim.add_box((side * (cw + slab), yc, roof + chute_h / 2), (slab, yh, chute_h / 2), material="steel",
                    tag="chute", group=0)
    sim.add_box((0.0, yc, top + slab), (cw + 2 * slab, yh, slab), material="steel", tag="chute", group=1)


def _add_rotors(sim: Any, machine: Machine, speeds: list[float], rows: Any, y_m: tuple[float, float],
                ext: float) -> dict[int, float]:
    """Hubs and flinger plates of every rotor, rotating; ``{rotor group: angular velocity rad/s}``."""
    from msmill.dem import Rotation

    y0, y1 = y_m
    r_in, r_out = machine.hub_radius_m, machine.tip_radius_m
    r_mid, half_len = (r_in + r_out) / 2, (r_out - r_in) / 2
    omegas = {}
    for stage in range(1, machine.n_stages + 1):
        z = machine.stage_axis_z_m(stage)
        w = rpm_to_rad_s(speeds[stage - 1])
        for side in (0, 1):
            x = machine.rotor_x_m(side)
            g = machine.rotor_index(stage, side)
            om = machine.omega_sign(stage, side) * w
            omegas[g] = om
            rot = Rotation(axis_point_m=(x, 0.0, z), axis_dir=(0.0, 1.0, 0.0), omega_rad_s=om)
            sim.add_cylinder((x, y0 - ext, z), (x, y1 + ext, z), r_in, material="steel", tag="hub", group=g,
                             rotation=rot, inside=False)
            for j in rows:
                yr, hy = machine.row_y_m(j), machine.flinger_width_m / 2
                for k in range(machine.flingers_per_row):
                    th = math.radians(machine.flinger_phase_deg(j, k))
                    d = np.array([math.cos(th), 0.0, math.sin(th)])
                    if side == 1:
                        d[0] = -d[0]
                    centre = (x + r_mid * d[0], yr, z + r_mid * d[2])
                    sim.add_box(centre, (half_len, hy, machine.flinger_thickness_m / 2),
                                axes=_plate_axes(d), material="steel", tag="flinger", group=g, rotation=rot)
    return omegas


def _add_gates_and_deflectors(sim: Any, machine: Machine, gate_deg: float, y_m: tuple[float, float],
                              ext: float) -> None:
    """The two outlet gates at ``gate_deg`` and the machine's deflectors, as sloped plates."""
    y0, y1 = y_m
    hw, zh = machine.half_width_m, machine.gate_hinge_z_m
    for side in (0, 1):
        hx = -hw if side == 0 else hw
        _sloped_plate(sim, (hx, zh), machine.gate_tip_m(gate_deg, side), y0 - ext, y1 + ext, "gate", side)
    for d in machine.deflectors:
        zd = machine.stage_axis_z_m(d.stage) + d.height_above_axis_m
        for sgn in (-1, 1):
            tip = (sgn * (hw - d.inner_edge_offset_m()), zd - d.drop_m())
            _sloped_plate(sim, (sgn * hw, zd), tip, y0 - ext, y1 + ext, "deflector", d.stage)


def _add_feed_and_outlet(sim: Any, machine: Machine, feed_kg_s: float, sizes: np.ndarray, mfrac: np.ndarray,
                         mode: str, y_m: tuple[float, float], feed_speed_m_s: float, seed: int) -> None:
    """The feed source in the chute (``feed_kg_s`` of the sizes' number mix) and the outlet sink below."""
    y0, y1 = y_m
    hw, cw = machine.half_width_m, machine.chute_width_m / 2
    roof, top = machine.roof_z_m, machine.roof_z_m + _CHUTE_HEIGHT_M
    radii = size_mm_to_radius_m(sizes)
    nweights = mfrac / radii**3
    nweights = nweights / nweights.sum()
    rm = float(radii.max())
    lo = (-cw + 1.2 * rm, y0 + (rm if mode == "full" else 0.0), roof + 0.12)
    hi = (cw - 1.2 * rm, y1 - (rm if mode == "full" else 0.0), top - 1.2 * rm - 0.02)
    radii_arg: Any = (radii, nweights) if radii.size > 1 else radii
    sim.add_source(lo, hi, feed_kg_s, radii_m=radii_arg, velocity_m_s=(0.0, 0.0, -feed_speed_m_s),
                   material="rock", start_s=0.0, stop_s=None, seed=seed)
    sim.add_sink((-hw - 1.0, y0 - 1.0, -10.0), (hw + 1.0, y1 + 1.0, 0.0), tag="outlet")


def _rock_from_ore(ore: str) -> RockMaterial:
    """Rock properties of a named ore from :mod:`msmill.ore`, where it provides them."""
    try:
        from msmill import ore as ore_mod  # type: ignore[attr-defined]
    except ImportError:
        raise MsmillInputError("ore", ore, "an ore known to msmill.ore (module not available)") from None
    get = getattr(ore_mod, "get_ore", None) or getattr(ore_mod, "load_ore", None)
    if get is None:
        raise MsmillInputError("ore", ore, "an ore known to msmill.ore")
    o = get(ore)
    base = RockMaterial()
    return RockMaterial(
        youngs_modulus_pa=float(getattr(o, "youngs_modulus_pa", None) or base.youngs_modulus_pa),
        poisson_ratio=float(getattr(o, "poisson_ratio", None) or base.poisson_ratio),
        density_kg_m3=float(getattr(o, "density_kg_m3", None) or base.density_kg_m3),
        name=str(ore),
    )
