"""Checks of a mill DEM run's inputs, made before any simulation work (``run_mill`` calls them).

Times must be finite and positive; the run must be long enough for rock fed at
the roof to fall through every stage (shorter runs have no rock in the stages
to measure); the rock must fit through the mill's narrowest passages; and the
run must fit the resource limits of :data:`msmill.validate.LIMITS` (time steps
and rocks fed), estimated from the scene before the first step.
"""

from __future__ import annotations

import math
from typing import Any

from msmill.dem.backend import check_backend
from msmill.errors import MsmillInputError
from msmill.machine import Machine, size_mm_to_radius_m
from msmill.validate import LIMITS, integer, number, one_of

G_M_S2 = 9.81
#: Fraction of the smallest rock radius a rock may travel per step (the engine's default
#: ``travel_fraction``): dt <= this x r_min / v_max.
TRAVEL_FRACTION = 0.1


def fall_time_s(machine: Machine) -> float:
    """Free-fall time from the roof to the outlet plane (s): the shortest run that reaches every stage."""
    return math.sqrt(2.0 * machine.roof_z_m / G_M_S2)


def largest_rock_mm(machine: Machine) -> float:
    """Largest rock diameter that fits the chute, the stage gaps and the liner gaps (mm)."""
    gaps = [machine.chute_width_m, machine.liner_clearance_m]
    if machine.n_stages > 1:
        gaps.append(machine.stage_clearance_m)
    return 1000.0 * min(gaps)


#: Fastest feed stream into the chute (m/s): a free fall of about 5 m, far below any flinger tip speed.
MAX_FEED_SPEED_M_S = 10.0


def check_run_inputs(machine: Machine, settings: Any, size_mm: float | None = None,
                     feed_psd: tuple[Any, Any] | None = None) -> None:
    """Raise :class:`MsmillInputError` for run settings or rock sizes the DEM cannot use.

    Field names are those of ``msmill dem run`` (``--max-time-s``, ``--size-mm`` ...).
    """
    number(settings.max_time_s, "--max-time-s", unit="s", ge=0)  # 0: scaled with the residence time
    number(settings.measure_s, "--measure-s", unit="s", gt=0)
    if settings.adaptive:
        number(settings.max_measure_s, "--max-measure-s", unit="s", gt=0)
    number(settings.chunk_s, "settings.chunk_s", unit="s", gt=0)
    if settings.dt_s is not None:
        number(settings.dt_s, "settings.dt_s", unit="s", gt=0)
    integer(settings.seed, "--seed", ge=0, le=2**32 - 1)
    # the feed enters the chute downwards, at most as fast as a free fall of about 5 m
    number(getattr(settings, "feed_speed_m_s", 2.0), "--feed-speed-m-s", unit="m/s", gt=0, le=MAX_FEED_SPEED_M_S)
    check_start(getattr(settings, "start", "empty"), "--start")
    check_window_from(getattr(settings, "window_from", "detection"), "--window-from")
    check_start_residence(getattr(settings, "start_residence_s", None), machine.n_stages)
    number(getattr(settings, "settle_s", 0.0), "settings.settle_s", unit="s", ge=0)
    number(getattr(settings, "checkpoint_every_s", 600.0), "--checkpoint-every-s", unit="s", ge=0)
    # the name only: a campaign's runs may execute elsewhere (the engine checks the machine, Simulation)
    check_backend(getattr(settings, "backend", "cpu"), "backend", here=False)
    t_fall = fall_time_s(machine)
    if 0 < settings.max_time_s < t_fall:
        shown = math.ceil(t_fall * 100) / 100  # the figure printed is itself allowed
        raise MsmillInputError("--max-time-s", settings.max_time_s,
                               f"at least {shown:.2f} s (the free-fall time from the roof to the outlet; "
                               "a shorter run has no rock through the stages to measure)")
    sizes = [size_mm] if size_mm is not None else list(feed_psd[0]) if feed_psd is not None else []
    top = largest_rock_mm(machine)
    for s in sizes:
        number(s, "--size-mm", unit="mm", gt=0)
        if s >= top:
            raise MsmillInputError("--size-mm", s, f"a rock diameter < {top:.4g} mm (the narrowest of the "
                                   "feed chute, the gaps between stages and the liner gaps)")


#: kinds of start of a run (``RunSettings.start``; :mod:`msmill.dem.mill.warmstart` places them)
START_KINDS = ("empty", "table")


def check_start(start: Any, field: str = "settings.start") -> None:
    """Raise :class:`MsmillInputError` unless ``start`` is a kind of start (``RunSettings.start``)."""
    one_of(start, field, START_KINDS)


def check_start_residence(residence_s: Any, n_stages: int, field: str = "settings.start_residence_s") -> None:
    """Raise :class:`MsmillInputError` unless ``residence_s`` is None or ``n_stages + 1`` finite times >= 0 (s)."""
    if residence_s is None:
        return
    allowed = f"None or {n_stages + 1} residence times >= 0 (s; inlet zone, stages 1..{n_stages})"
    try:
        values = [float(v) for v in residence_s]
    except (TypeError, ValueError):
        raise MsmillInputError(field, residence_s, allowed) from None
    if len(values) != n_stages + 1 or not all(math.isfinite(v) and v >= 0 for v in values):
        raise MsmillInputError(field, residence_s, allowed)


#: where a run's measurement window starts (``RunSettings.window_from``)
WINDOW_FROM = ("detection", "onset")


def check_window_from(window_from: Any, field: str = "settings.window_from") -> None:
    """Raise :class:`MsmillInputError` unless ``window_from`` is in :data:`WINDOW_FROM`."""
    one_of(window_from, field, WINDOW_FROM)


def estimated_dt_s(scene: Any, settings: Any) -> float:
    """The time step the engine will choose (s): ``safety`` x the Hertz contact time at the
    scene's largest impact speed, capped by the travel limit, or the explicit ``dt_s``."""
    if settings.dt_s is not None:
        return float(settings.dt_s)
    v = float(scene.max_impact_speed_m_s)
    r_min_m = size_mm_to_radius_m(float(min(scene.sizes_mm)))
    return min(settings.safety * contact_time_s(scene.rock_used, r_min_m, v), TRAVEL_FRACTION * r_min_m / v)


def contact_time_s(rock: Any, radius_m: float, v_m_s: float) -> float:
    """Shortest Hertz contact time of a rock of ``radius_m`` on rock or steel at ``v_m_s`` (s).

    Analytic (``msmill.dem.contact.hertz_contact_time``), so the check costs nothing:
    ``Simulation.contact_time_s`` packs the particle store first, ~10 s for fine rock.
    """
    from msmill.dem.contact import hertz_contact_time
    from msmill.dem.mill.scene import STEEL

    def e_star(a: Any, b: Any) -> float:
        return 1.0 / ((1 - a.poisson_ratio**2) / a.youngs_modulus_pa + (1 - b.poisson_ratio**2) / b.youngs_modulus_pa)

    m = rock.density_kg_m3 * 4.0 / 3.0 * math.pi * radius_m**3
    return min(hertz_contact_time(m / 2, radius_m / 2, e_star(rock, rock), v_m_s),
               hertz_contact_time(m, radius_m, e_star(rock, STEEL), v_m_s))


def check_run_budget(scene: Any, settings: Any) -> None:
    """Reject a run whose step count or number of rocks fed exceeds the resource limits.

    Both are estimated from the scene before the first step: steps from
    :func:`estimated_dt_s`, rocks fed from the feed rate and the smallest rock's mass.
    """
    measure = max(settings.measure_s, settings.max_measure_s if settings.adaptive else 0.0)
    duration = settings.time_limit_s(float(min(scene.sizes_mm))) + measure
    steps = duration / estimated_dt_s(scene, settings)
    r_min_m = size_mm_to_radius_m(float(min(scene.sizes_mm)))
    cap, what = LIMITS["dem_steps"]
    if steps > cap:
        raise MsmillInputError("--max-time-s/--max-measure-s/--size-mm/--speed-rpm", f"~{steps:.3g} steps",
                               f"at most {cap:.3g} {what} (resource limit msmill.validate.LIMITS['dem_steps']); "
                               "shorten the run, coarsen the rock or lower the speed")
    mass_kg = scene.rock.density_kg_m3 * math.pi / 6.0 * (2 * r_min_m) ** 3
    fed = scene.feed_kg_s * duration / mass_kg
    cap, what = LIMITS["dem_particles"]
    if fed > cap:
        raise MsmillInputError("--feed-tph/--size-mm/--max-measure-s", f"~{fed:.3g} rocks fed",
                               f"at most {cap:.3g} rocks fed during the run (resource limit "
                               "msmill.validate.LIMITS['dem_particles']); use --slice, a coarser rock or a shorter run "
                               "(with --adaptive: a shorter --max-measure-s)")
