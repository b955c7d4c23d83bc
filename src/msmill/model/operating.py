"""Sweeps over operating variables and an optimiser of the operating point.

Variables (``VARIABLES``): ``speed_rpm`` (upper stages; the bottom stage keeps
``bottom_speed_factor``), ``feed_tph``, ``gate_deg`` and ``feed_scale`` (all
feed sizes multiplied by this factor: a coarser or finer feed of the same
shape); and the categorical ``rotation_sense`` (:data:`SENSE`): one mill per
rotation sense (:func:`mills_by_sense`), the numeric variables swept
(:func:`sweep_senses`) or optimised (:func:`optimize_senses`) for each. Every
point is one steady-state expected-value prediction; outputs:
P80, throughput, specific energy (impact power plus the stated no-load term,
per tonne; ``msmill.model.power``), hold-up, % passing at a size, whether the
point is inside the design space, and whether it is feasible.

Feasibility hook: ``feasible(op, result) -> bool`` (default: every point is
feasible). The mill's DEM operating envelope (``Mill(envelope=...)``, by
default the shipped one, :mod:`msmill.surrogate.capacity`) is a constraint on top of it:
every row carries ``capacity_tph`` (at the feed's F80, speed and gate),
``p_steady`` (probability the mill passes the feed) and ``above_capacity``,
and a point above a predicted capacity (an envelope with choked runs) is
infeasible, in sweeps and the optimiser alike. A capacity that is only a
lower bound (no DEM run choked, ``capacity_is_lower_bound``) flags the point
and leaves it feasible: above it the capacity is unknown, not exceeded.
:func:`capacity_feasible` makes the same constraint from another envelope.

Note: with a stage-parameter table measured at one operating point, the
transport and impact statistics do not change with feed rate or gate, so the
product does not either (the model is linear in the feed); sweeps over those
variables become informative with a provider that depends on them (the
surrogate). Off the table's point the provider warns.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import warnings
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd

from msmill.errors import MsmillInputError, OutOfDomainWarning
from msmill.psd import PSD, SizeGrid

__all__ = ["SENSE", "VARIABLES", "OptimumResult", "SenseOptimum", "capacity_feasible", "check_senses",
           "evaluate_point", "mills_by_sense", "optimize", "optimize_senses", "optimize_settings", "pareto_front",
           "stage_parameter_lines", "sweep", "sweep_senses"]

VARIABLES = ("speed_rpm", "feed_tph", "gate_deg", "feed_scale")
#: the categorical variable: the machine's rotation sense (one mill per value, :func:`mills_by_sense`)
SENSE = "rotation_sense"
GOALS = ("max_feed", "min_energy")
Feasible = Callable[[Any, Any], bool]


def _scaled_feed(feed: PSD, factor: float) -> PSD:
    if factor == 1.0:
        return feed
    return PSD(SizeGrid(feed.grid.edges_mm * factor), feed.fractions, validate=False)


def _check_vars(names: Any) -> None:
    bad = [n for n in names if n not in VARIABLES]
    if bad:
        raise MsmillInputError("variable", bad[0], "one of " + ", ".join(VARIABLES))


def capacity_feasible(model: Any) -> Feasible:
    """Feasibility hook: the point's feed rate is within ``model``'s capacity (a :class:`CapacityModel`)."""
    from msmill.surrogate.capacity import check_capacity

    def feasible(op: Any, res: Any) -> bool:
        chk = check_capacity(model, res.f80_mm, op.feed_tph, op.upper_speed_rpm, op.gate_deg)
        return chk is None or not chk.above or chk.lower_bound  # above a lower bound: unknown, not exceeded

    return feasible


def _capacity_columns(res: Any) -> dict[str, Any]:
    cap = getattr(res, "capacity_tph", None)
    if cap is None:
        return {"capacity_tph": float("nan"), "p_steady": float("nan"), "above_capacity": False,
                "capacity_is_lower_bound": False}
    return {"capacity_tph": float(cap), "p_steady": float(res.probability_steady),
            "above_capacity": bool(res.feed_tph > cap),
            "capacity_is_lower_bound": bool(getattr(res, "capacity_is_lower_bound", False))}


def evaluate_point(mill: Any, feed: PSD, base_op: Any, settings: dict[str, float],
                   passing_size_mm: float | None = None, no_load_kw: float = 0.0,
                   feasible: Feasible | None = None) -> dict[str, Any]:
    """Predict at ``base_op`` with ``settings`` applied; one row of outputs (units in the keys)."""
    from msmill.model.power import power_estimate

    _check_vars(settings)
    upd = {k: float(v) for k, v in settings.items() if k in ("speed_rpm", "feed_tph", "gate_deg")}
    if "speed_rpm" in upd and base_op.stage_speeds_rpm is not None:
        raise MsmillInputError("speed_rpm", upd["speed_rpm"], "a base operating point given by speed_rpm")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", OutOfDomainWarning)
        op = base_op.model_validate({**base_op.model_dump(exclude_none=True), **upd})
        f = _scaled_feed(feed, float(settings.get("feed_scale", 1.0)))
        res = mill.run(f, op, timeseries=False, held_below=False)
    pw = power_estimate(res, no_load_kw=no_load_kw)
    row = {**{k: float(v) for k, v in settings.items()},
           "p80_mm": res.p80_mm, "f80_mm": res.f80_mm, "throughput_tph": res.feed_tph,
           "specific_energy_kwh_t": pw.specific_energy_kwh_t, "power_kw": pw.total_kw,
           "holdup_t": float(res.stages["holdup_t"].sum()),
           "inside_design_space": not any("design space" in str(w.message) for w in caught),
           **_capacity_columns(res)}
    choked = row["above_capacity"] and not row["capacity_is_lower_bound"]  # a lower bound flags, never excludes
    row["feasible"] = (bool(feasible(op, res)) if feasible is not None else True) and not choked
    band = getattr(res, "p80_band_mm", None)  # uncertainty band (issue 13), when the result has one
    if band is not None:
        row["p80_low_mm"], row["p80_high_mm"] = float(band[0]), float(band[1])
    if passing_size_mm is not None:
        row[f"passing_{passing_size_mm:g}mm_pct"] = float(res.product_psd.passing_at(passing_size_mm))
    return row


def sweep(mill: Any, feed: PSD, base_op: Any, axes: dict[str, Any], **options: Any) -> pd.DataFrame:
    """Predict on the full grid of one or two variables.

    Parameters
    ----------
    mill : Mill
        Model (give it a ``grid`` covering the coarsest scaled feed to share operators).
    feed : PSD
        Feed (scaled by ``feed_scale`` when swept).
    base_op : OperatingPoint
        The other settings.
    axes : dict
        ``{variable: values}`` for one or two of :data:`VARIABLES`.
    **options
        ``passing_size_mm``, ``no_load_kw``, ``feasible`` of :func:`evaluate_point`.
    """
    if not 1 <= len(axes) <= 2:
        raise MsmillInputError("sweep variables", list(axes), "one or two of " + ", ".join(VARIABLES))
    _check_vars(axes)
    names = list(axes)
    rows = [evaluate_point(mill, feed, base_op, dict(zip(names, vals, strict=True)), **options)
            for vals in itertools.product(*[np.asarray(v, dtype=float) for v in axes.values()])]
    return pd.DataFrame(rows)


def pareto_front(table: pd.DataFrame, x: str = "specific_energy_kwh_t", y: str = "p80_mm") -> pd.DataFrame:
    """Rows not dominated in (lower ``x``, lower ``y``)."""
    t = table.sort_values([x, y]).reset_index(drop=True)
    best = np.minimum.accumulate(t[y].to_numpy())
    keep = np.concatenate([[True], t[y].to_numpy()[1:] < best[:-1]])
    return t[keep]


@dataclass(frozen=True)
class OptimumResult:
    """Result of :func:`optimize_settings`.

    Attributes
    ----------
    settings : dict[str, float] or None
        The best settings (None when no candidate meets the target).
    row : dict or None
        Outputs at the best settings.
    candidates : pandas.DataFrame
        Every evaluated point (grid and refinement) with ``meets_target``.
    front : pandas.DataFrame
        Pareto front of P80 against specific energy among feasible candidates.
    goal : str
    target : str
        Human-readable target.
    bounds : dict
        ``{variable: (low, high)}`` searched.
    closest : dict or None
        When no candidate meets the target: the evaluated point nearest to meeting it (feasible ones first),
        i.e. what the bounds can reach; None otherwise.
    """

    settings: dict[str, float] | None
    row: dict[str, Any] | None
    candidates: pd.DataFrame
    front: pd.DataFrame
    goal: str
    target: str
    bounds: dict[str, tuple[float, float]] = dataclasses.field(default_factory=dict)
    closest: dict[str, Any] | None = None

    def at_bounds(self) -> dict[str, str]:
        """Variables whose best setting sits on a bound of the search: ``{variable: "low" or "high"}``.

        There a wider bound may do better: the optimum is the bound's, not the mill's.
        """
        out = {}
        for k, v in (self.settings or {}).items():
            lo, hi = self.bounds.get(k, (v, v))
            tol = 1e-6 * (hi - lo)
            if hi > lo and v <= lo + tol:
                out[k] = "low"
            elif hi > lo and v >= hi - tol:
                out[k] = "high"
        return out


def optimize_settings(evaluate: Callable[[dict[str, float]], dict[str, Any]],
                      bounds: dict[str, tuple[float, float]], goal: str = "max_feed",
                      target_p80_mm: float | None = None,
                      target_passing: tuple[float, float] | None = None, n_grid: int = 7,
                      refine_tol: float = 1e-3) -> OptimumResult:
    """Best settings within ``bounds`` that reach the target, by grid search plus boundary refinement.

    Parameters
    ----------
    evaluate : callable
        ``settings -> row`` with ``p80_mm``, ``specific_energy_kwh_t``,
        ``throughput_tph``, ``feasible`` (and ``passing_<s>mm_pct`` for a passing target).
    bounds : dict
        ``{variable: (low, high)}``.
    goal : {"max_feed", "min_energy"}
        Highest throughput, or lowest specific energy.
    target_p80_mm : float, optional
        P80 must not exceed this (mm).
    target_passing : (size_mm, pct), optional
        Passing at ``size_mm`` must be at least ``pct`` %.
    n_grid : int
        Grid points per variable.
    refine_tol : float
        Relative tolerance of the refinement.

    Notes
    -----
    After the grid, the variable that drives the goal (``feed_tph`` for
    ``max_feed``; ``speed_rpm`` for ``min_energy`` when swept) is refined by
    bisection between the best feasible grid point and its failing grid
    neighbour, for every combination of the other variables (for
    ``max_feed`` only those that can still beat the best), assuming the target
    is monotone along it between the two grid values.
    """
    if goal not in GOALS:
        raise MsmillInputError("goal", goal, " or ".join(GOALS))
    if (target_p80_mm is None) == (target_passing is None):
        raise MsmillInputError("target", None, "exactly one of a target P80 or a target passing at a size")
    _check_vars(bounds)
    if goal == "max_feed" and "feed_tph" not in bounds:
        raise MsmillInputError("bounds", list(bounds), "feed_tph among the variables for goal max_feed")
    for k, (lo, hi) in bounds.items():
        if not (math.isfinite(lo) and math.isfinite(hi) and lo <= hi):
            raise MsmillInputError(f"bounds.{k}", (lo, hi), "finite low <= high")
    if target_p80_mm is not None:
        target = f"P80 <= {target_p80_mm:g} mm"

        def margin(r: dict) -> float:  # >= 0 meets the target
            return target_p80_mm - r["p80_mm"]
    else:
        size, pct = target_passing
        key = f"passing_{size:g}mm_pct"
        target = f"passing {size:g} mm >= {pct:g} %"

        def margin(r: dict) -> float:
            return r[key] - pct

    names = list(bounds)
    axes = [np.linspace(lo, hi, n_grid) if hi > lo else np.array([lo]) for lo, hi in bounds.values()]
    rows = []
    for vals in itertools.product(*axes):
        s = dict(zip(names, (float(v) for v in vals), strict=True))
        rows.append({**evaluate(s), **s})
    score = _score(goal)
    ok = [r for r in rows if r["feasible"] and margin(r) >= 0]
    best = max(ok, key=score) if ok else None
    drive = "feed_tph" if goal == "max_feed" else ("speed_rpm" if "speed_rpm" in bounds else None)
    if best is not None and drive is not None and bounds[drive][1] > bounds[drive][0]:
        best = _refine_all(evaluate, ok, names, drive, axes[names.index(drive)], margin, rows, refine_tol,
                           score, goal)
    cand = pd.DataFrame(rows)
    cand["meets_target"] = [bool(r["feasible"] and margin(r) >= 0) for r in rows]
    feas = cand[cand["feasible"]]
    front = pareto_front(feas) if len(feas) else feas
    settings = {k: float(best[k]) for k in names} if best is not None else None
    closest = None
    if best is None and rows:  # what the bounds can reach: the nearest miss, feasible points first
        closest = max(rows, key=lambda r: (bool(r["feasible"]), margin(r)))
    return OptimumResult(settings, best, cand, front, goal, target, dict(bounds), closest)


def _score(goal: str) -> Callable[[dict], float]:
    """The goal as a score of a result row (higher is better): throughput, or minus specific energy."""
    if goal == "max_feed":
        return lambda r: r["throughput_tph"]
    return lambda r: -r["specific_energy_kwh_t"]


def _refine_all(evaluate, ok, names, drive, axis, margin, rows, tol, score, goal) -> dict:
    """Refine ``drive`` in every group of the other variables; best refined point.

    For ``max_feed`` a group whose upper limit (its first failing grid value)
    cannot beat the best so far is skipped.
    """
    others = [n for n in names if n != drive]
    groups: dict[tuple, dict] = {}
    for r in ok:  # best feasible grid point per combination of the other variables
        key = tuple(r[n] for n in others)
        if key not in groups or score(r) > score(groups[key]):
            groups[key] = r
    step = axis[1] - axis[0] if axis.size > 1 else 0.0
    direction = 1.0 if drive == "feed_tph" else -1.0  # more feed / less speed is better
    lo, hi = float(axis[0]), float(axis[-1])

    def limit(r: dict) -> float:
        return min(max(r[drive] + direction * step, lo), hi)

    order = sorted(groups.values(), key=lambda r: direction * limit(r), reverse=True)
    best = max(ok, key=score)
    for r in order:
        if goal == "max_feed" and limit(r) <= best[drive]:
            break
        cand = _refine(evaluate, r, names, drive, limit(r), margin, rows, tol, score)
        if score(cand) > score(best):
            best = cand
    return best


def _refine(evaluate, best, names, drive, b, margin, rows, tol, score) -> dict:
    """Bisect ``drive`` between ``best`` (meets the target) and ``b`` (the next grid value)."""
    a = best[drive]
    if b == a:
        return best
    good = best
    for _ in range(40):
        if abs(b - a) <= tol * max(abs(a), 1e-12):
            break
        mid = float(0.5 * (a + b))
        s = {k: best[k] for k in names}
        s[drive] = mid
        r = {**evaluate(s), **s}
        rows.append(r)
        if r["feasible"] and margin(r) >= 0:
            a, good = mid, (r if score(r) >= score(good) else good)
        else:
            b = mid
    return good


def optimize(mill: Any, feed: PSD, base_op: Any, bounds: dict[str, tuple[float, float]],
             goal: str = "max_feed", target_p80_mm: float | None = None,
             target_passing: tuple[float, float] | None = None, n_grid: int = 7, no_load_kw: float = 0.0,
             feasible: Feasible | None = None) -> OptimumResult:
    """:func:`optimize_settings` on the mill model (each evaluation one steady-state prediction)."""
    size = target_passing[0] if target_passing is not None else None

    def evaluate(s: dict[str, float]) -> dict[str, Any]:
        return evaluate_point(mill, feed, base_op, s, passing_size_mm=size, no_load_kw=no_load_kw,
                              feasible=feasible)

    return optimize_settings(evaluate, bounds, goal, target_p80_mm, target_passing, n_grid)


def optimum_sensitivity(make_mill: Callable[[float], Any], l_ref_mm: float, l_ref_se_mm: float,
                        feed: PSD, base_op: Any, bounds: dict[str, tuple[float, float]],
                        **options: Any) -> pd.DataFrame:
    """The optimum at ``L_ref - se``, ``L_ref`` and ``L_ref + se`` (uncertainty of the result).

    ``make_mill(l_ref_mm)`` builds the mill for one reference size; ``options``
    go to :func:`optimize`. Returns one row per case with the best settings and
    outputs (NaN where the target cannot be met).
    """
    if not (l_ref_se_mm > 0 and l_ref_mm - l_ref_se_mm > 0):
        raise MsmillInputError("l_ref_se_mm", l_ref_se_mm, f"a standard error in (0, {l_ref_mm:g}) mm")
    rows = []
    for case, L in (("L_ref - s.e.", l_ref_mm - l_ref_se_mm), ("L_ref", l_ref_mm),
                    ("L_ref + s.e.", l_ref_mm + l_ref_se_mm)):
        res = optimize(make_mill(L), feed, base_op, bounds, **options)
        rows.append({"case": case, "l_ref_mm": L, **(res.row or {})})
    return pd.DataFrame(rows)


# ----------------------------------------------------------------- the rotation sense, a categorical variable
def check_senses(values: Iterable[str], field: str = SENSE) -> list[str]:
    """``values`` as a list of rotation senses (:func:`msmill.machine.rotation_senses`), each once.

    Raises
    ------
    MsmillInputError
        One line naming ``field``, the bad value and the allowed names.
    """
    from msmill.machine import rotation_senses

    allowed = ", ".join(rotation_senses())
    out: list[str] = []
    for v in values:
        if v not in rotation_senses():
            raise MsmillInputError(field, v, allowed)
        if v in out:
            raise MsmillInputError(field, v, "each rotation sense once")
        out.append(v)
    if not out:
        raise MsmillInputError(field, "", f"one or more of {allowed}")
    return out


def mills_by_sense(run_file: Any, senses: Iterable[str], field: str = SENSE) -> dict[str, Any]:
    """One mill per rotation sense: the run file's machine turned each way, stage parameters resolved for it.

    Parameters
    ----------
    run_file : msmill.model.runfile.RunFile
        The run file; each sense's mill is built from
        ``run_file.with_rotation_sense(sense)`` exactly as :meth:`RunFile.build` builds one.
    senses : iterable of str
        Rotation senses (:func:`check_senses`).
    field : str
        Field named by an error about the senses themselves.

    Returns
    -------
    dict
        ``{sense: Mill}`` in the order given.

    Notes
    -----
    Every sense's stage parameters are resolved before any mill is built, so a
    sense without them (``stage_parameters = "default"`` and no shipped
    surrogate of that sense) stops in one line before any work is done.
    """
    specs = {s: run_file.with_rotation_sense(s) for s in check_senses(senses, field)}
    for spec in specs.values():
        spec.stage_parameter_path()
    return {s: spec.build()[0] for s, spec in specs.items()}


def stage_parameter_lines(mills: Mapping[str, Any]) -> list[str]:
    """Where each rotation sense's stage parameters come from (``provider.source``) and whose machine they are.

    One line per sense; then, for senses that share one source, a line saying their rows rest on the
    same DEM data (a table does not record its machine, so :func:`machine_mismatch` cannot say so).
    """
    from msmill.model.providers import machine_mismatch

    lines, by_source = [], {}
    for sense, mill in mills.items():
        source = mill.provider.source
        by_source.setdefault(source, []).append(sense)
        note = machine_mismatch(mill.provider, mill.machine)
        if note is None and getattr(mill.provider, "trained_machine", None) is None:
            note = "they do not record their machine: not checked against this sense"
        lines.append(f"stage parameters of {sense}: {source}" + (f"; {note}" if note else "; this machine's"))
    for source, senses in by_source.items():
        if len(senses) > 1:
            lines.append(f"{', '.join(senses)} rest on the same stage parameters ({source}): their rows are the same "
                         "DEM data, not a comparison of the senses")
    return lines


def sweep_senses(mills: Mapping[str, Any], feed: PSD, base_op: Any, axes: dict[str, Any],
                 **options: Any) -> pd.DataFrame:
    """:func:`sweep` for each rotation sense's mill; the rows tagged ``rotation_sense`` and ``stage_parameters``.

    Parameters
    ----------
    mills : mapping
        ``{sense: Mill}`` (:func:`mills_by_sense`).
    feed, base_op, options
        As for :func:`sweep`.
    axes : dict
        At most one numeric variable (the sense is the other); none: each sense at ``base_op``.
    """
    if len(axes) > 1:
        raise MsmillInputError("sweep variables", [SENSE, *axes], f"{SENSE} and at most one of " + ", ".join(VARIABLES))
    tables = []
    for sense, mill in mills.items():
        t = (sweep(mill, feed, base_op, axes, **options) if axes
             else pd.DataFrame([evaluate_point(mill, feed, base_op, {}, **options)]))
        t.insert(0, SENSE, sense)
        t.insert(1, "stage_parameters", mill.provider.source)
        tables.append(t)
    return pd.concat(tables, ignore_index=True)


@dataclass(frozen=True)
class SenseOptimum:
    """Result of :func:`optimize_senses`: the optimum of every rotation sense and the best of them.

    Attributes
    ----------
    by_sense : dict[str, OptimumResult]
        ``{sense: optimum}`` in the order searched.
    best_sense : str or None
        The sense whose optimum scores best on the goal (None when no sense meets the target).
    sources : dict[str, str]
        ``{sense: provider.source}`` of each sense's stage parameters.
    """

    by_sense: dict[str, OptimumResult]
    best_sense: str | None
    sources: dict[str, str] = dataclasses.field(default_factory=dict)

    @property
    def best(self) -> OptimumResult | None:
        """The best sense's :class:`OptimumResult` (None when no sense meets the target)."""
        return None if self.best_sense is None else self.by_sense[self.best_sense]

    def summary(self) -> pd.DataFrame:
        """One row per sense: ``meets_target``, ``best``, its optimum's settings and outputs (the closest miss
        when it does not meet the target) and ``stage_parameters``."""
        rows = []
        for sense, res in self.by_sense.items():
            row = res.row if res.row is not None else (res.closest or {})
            rows.append({SENSE: sense, "meets_target": res.settings is not None, "best": sense == self.best_sense,
                         **row, "stage_parameters": self.sources.get(sense, "")})
        return pd.DataFrame(rows)

    def candidates(self) -> pd.DataFrame:
        """Every evaluated point of every sense, tagged ``rotation_sense``."""
        tables = []
        for sense, res in self.by_sense.items():
            t = res.candidates.copy()
            t.insert(0, SENSE, sense)
            tables.append(t)
        return pd.concat(tables, ignore_index=True)

    def front(self) -> pd.DataFrame:
        """Pareto front of P80 against specific energy among the feasible candidates of all senses."""
        c = self.candidates()
        feas = c[c["feasible"]]
        return pareto_front(feas) if len(feas) else feas


def optimize_senses(mills: Mapping[str, Any], feed: PSD, base_op: Any, bounds: dict[str, tuple[float, float]],
                    goal: str = "max_feed", **options: Any) -> SenseOptimum:
    """:func:`optimize` within ``bounds`` for each rotation sense's mill; the best sense by ``goal``.

    Parameters
    ----------
    mills : mapping
        ``{sense: Mill}`` (:func:`mills_by_sense`).
    feed, base_op, bounds, goal, options
        As for :func:`optimize` (``bounds`` may be empty: each sense at ``base_op``).
    """
    by_sense = {s: optimize(m, feed, base_op, bounds, goal, **options) for s, m in mills.items()}
    score = _score(goal)
    met = [s for s, r in by_sense.items() if r.row is not None]
    best = max(met, key=lambda s: score(by_sense[s].row)) if met else None
    return SenseOptimum(by_sense, best, {s: m.provider.source for s, m in mills.items()})
