"""Fitting breakage parameters to whole product PSDs: single-impact tests and mill surveys.

Single-impact tests (:func:`fit_impact_tests`)
---------------------------------------------
One impact per rock at speed ``v`` (``E = v**2 / 2``) on fresh rock: a feed
class ``j`` of mass ``f_j`` leaves ``f_j (1 - P_b,j)`` unbroken and
``f_j P_b,j`` as the breakage sub-model's fragments. The parameters are fitted
by least squares to the *whole* product PSD: the residuals are the
differences of the cumulative fraction passing at every measured sieve
(``docs/breakage.md`` section 5.1: bounded residuals, so neither an empty
sieve class nor the sieve at which a lab closes its curve at 100 % can
dominate). The mass left in the feed class fixes ``P_b``, the fragments their
fineness (``t10``), which t10 values alone cannot separate. Bounds of the
size- and energy-dependent parameters scale with the tests
(:func:`impact_bounds`); a fit reports the parameters that sit on a bound,
Jacobian standard errors (``cov = s² (JᵀJ)⁻¹``, approximate: cumulative
residuals are correlated) and whether it is identified (multi-start spread).

:func:`compare_submodels` fits each sub-model without some tests (one speed,
or one test, at a time) and predicts them, reporting the held-out K-S;
:func:`impact_report` adds the all-test fits (the ``msmill calibrate`` table).

Mill surveys (:func:`calibrate_surveys`)
----------------------------------------
Fits ``L_ref`` of an ore (optionally ``A``, the Tavares ``gamma``; or ``A``
and ``b`` with ``L_ref`` held: ``b`` and ``L_ref`` enter only as ``b/L_ref``)
to measured products, minimising the mean K-S or the weighted sum of squares
of % passing at the measured sieves. ``L_ref`` alone uses a cubic spline of
every survey's predicted product over ``ln L_ref`` through
``n_nodes`` exact solves per operating point; the optimum is then checked by
one exact solve. Leave-one-survey-out refits give the cross-validated K-S and
the jackknife standard error ``sqrt((n-1)/n sum (theta_i - mean)^2)``.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd

from msmill.errors import MsmillInputError
from msmill.model import submodels as sm
from msmill.model.breakage_swebrec import VogelSwebrecBreakage
from msmill.model.mill import DEFAULT_MIN_SIZE_MM, breakage_parameters
from msmill.model.submodels import specific_energy_kwh_t
from msmill.model.validation import measured_ks
from msmill.psd import PSD, SizeGrid, ks_statistic

__all__ = [
    "FITTABLE",
    "ImpactFit",
    "SurveyCalibration",
    "bootstrap_std_errors",
    "build_breakage",
    "calibrate_surveys",
    "compare_submodels",
    "fit_impact_tests",
    "impact_bounds",
    "impact_report",
    "noise_sigma",
    "single_impact_product",
]

#: Fittable parameters of each breakage sub-model (units in the names); their bounds come from
#: :func:`impact_bounds` (scaled to the tests' sizes and energies, or dimensionless shape ranges).
FITTABLE: dict[str, tuple[str, ...]] = {
    "ab_t10": ("A_pct", "l_ref_mm"),
    "jk_t10": ("A_pct", "l_ref_mm"),
    "energy_t10": ("A_pct", "l_ref_mm", "fineness_ratio"),
    "vogel_swebrec": ("A_pct", "b_t_per_kwh", "e_min_kwh_t", "swebrec_b"),
}
#: Bounds of the dimensionless (shape) parameters, the same for every material.
SHAPE_BOUNDS: dict[str, tuple[float, float]] = {"A_pct": (1.0, 100.0), "swebrec_b": (0.3, 10.0),
                                                 "fineness_ratio": (1e-3, 1e3)}
#: Range of the Eq. 11 exponent ``x = b E L / L_ref`` (``k L E / L_ref`` for ``vogel_swebrec``)
#: that the scaled bounds allow: at one bound even the least energetic test (slowest, smallest
#: rock) breaks with ``P_b = 1 - exp(-X_MAX)``, at the other even the most energetic one breaks
#: with ``P_b = 1 - exp(-X_MIN)`` (about X_MIN): beyond them the tests cannot tell values apart.
X_MIN = 1e-3
X_MAX = 30.0
OBJECTIVES = ("ks", "ssq")


def _test_ranges(tests: Sequence[Any]) -> tuple[float, float, float, float]:
    """``(L_min, L_max, E_min, E_max)``: the tests' feed sizes (mm, the feed's sieves with mass
    between them) and specific impact energies (kWh/t)."""
    lo, hi = [], []
    for t in tests:
        s, p = t.feed_psd.sizes_mm, t.feed_psd.passing_pct
        inside = np.flatnonzero(np.diff(p) > 0)  # intervals that hold feed mass
        lo.append(float(s[inside[0]]) if inside.size else float(s[0]))
        hi.append(float(s[inside[-1] + 1]) if inside.size else float(s[-1]))
    e = specific_energy_kwh_t(np.array([float(t.impact_speed_m_s) for t in tests]))
    return min(lo), max(hi), float(e.min()), float(e.max())


def impact_bounds(submodel: str, tests: Sequence[Any], ore: Any) -> dict[str, tuple[float, float]]:
    """Bounds of ``submodel``'s fittable parameters for these tests (units in the names).

    ``L_ref`` (``ab_t10``, ``jk_t10``; ``b`` held) spans the values at which the
    Eq. 11 exponent ``b E L / L_ref`` lies between :data:`X_MIN` at the most
    energetic test and :data:`X_MAX` at the least energetic one, so the range
    follows the particle size and energy of the tests (0.17 mm particles at
    60-300 m/s get about 0.1-50 mm, 13-32 mm rock at 15-45 m/s about
    0.5-700 mm). ``k`` of ``vogel_swebrec`` spans the same exponent range at
    the ore's ``L_ref``, and the threshold ``E_min`` (at ``L_ref``) from 0 to the
    value at which the coarsest rock at the fastest test is just at threshold.
    ``A``, the Swebrec ``beta`` and the ``energy_t10`` fineness ratio ``c`` are
    dimensionless shape parameters (:data:`SHAPE_BOUNDS`; ``c`` from 1e-3, fragments
    that refine over a thousand times the energy that breaks most rock, to 1e3,
    ``jk_t10``'s fragments).
    """
    if submodel not in FITTABLE:
        raise MsmillInputError("breakage", submodel, sm.did_you_mean(submodel, list(FITTABLE)))
    bp = breakage_parameters(ore)
    l_min, l_max, e_min, e_max = _test_ranges(tests)
    if e_min <= 0:
        raise MsmillInputError("impact_speed_m_s", 0.0, "speeds > 0 m/s in every single-impact test")
    out = dict(SHAPE_BOUNDS)
    if submodel == "vogel_swebrec":
        lr = bp.l_ref_mm
        out["b_t_per_kwh"] = (X_MIN * lr / (e_max * l_max), X_MAX * lr / (e_min * l_min))
        out["e_min_kwh_t"] = (0.0, e_max * l_max / lr)
    else:
        b = bp.b_t_per_kwh
        out["l_ref_mm"] = (b * e_max * l_max / X_MAX, b * e_min * l_min / X_MIN)
    return {k: out[k] for k in FITTABLE[submodel]}


def build_breakage(name: str, ore: sm.BreakageParameters, values: dict[str, float]) -> Any:
    """The breakage sub-model ``name`` for ``ore`` with some parameters replaced by ``values``."""
    if name == "ab_t10":
        return sm.AbT10Breakage(dataclasses.replace(ore, **values))
    if name == "jk_t10":
        return sm.JkT10Breakage(dataclasses.replace(ore, **values))
    if name == "energy_t10":
        return sm.EnergyT10Breakage(dataclasses.replace(ore, **values))
    if name == "vogel_swebrec":
        base = VogelSwebrecBreakage.from_ore(ore)
        return VogelSwebrecBreakage(dataclasses.replace(base.params, **values))
    raise MsmillInputError("breakage", name, sm.did_you_mean(name, list(FITTABLE)))


def current_values(model: Any) -> dict[str, float]:
    """The fittable parameter values of a breakage sub-model object."""
    src = model.params if isinstance(model, VogelSwebrecBreakage) else model.ore
    return {k: float(getattr(src, k)) for k in FITTABLE[model.name]}


def impact_grid(tests: Sequence[Any], min_mm: float = DEFAULT_MIN_SIZE_MM) -> SizeGrid:
    """Model grid for single-impact tests: every feed and product sieve, extended down to ``min_mm``.

    Using the measured sieves as class edges keeps a narrow feed fraction
    (e.g. 13.2 x 16 mm) exactly in its class; rebinning it onto an unrelated
    geometric grid would smear it over neighbouring classes.
    """
    sizes = np.unique(np.concatenate([np.concatenate([t.feed_psd.sizes_mm, t.product_psd.sizes_mm])
                                      for t in tests]))
    lo = float(sizes[0])
    n_ext = max(math.ceil(math.log(lo / min_mm) / math.log(math.sqrt(2.0))), 1) if lo > min_mm else 1
    below = lo / math.sqrt(2.0) ** np.arange(n_ext, 0, -1)
    return SizeGrid(np.concatenate([below, sizes]))


def single_impact_product(breakage: Any, grid: SizeGrid, feed_fractions: np.ndarray,
                          speed_m_s: float) -> np.ndarray:
    """Product mass fractions of one impact at ``speed_m_s`` on fresh rock (no damage)."""
    e = float(specific_energy_kwh_t(speed_m_s))
    mids = grid.mids_mm
    ef, d0 = np.full(mids.size, e), np.zeros(mids.size)
    pb = np.asarray(breakage.probability(ef, mids, d0))
    cols = _direct_columns(breakage, grid, sm.fragment_index(breakage, ef, mids, d0, pb))  # (parent, class)
    f = np.asarray(feed_fractions, dtype=float)
    return f * (1.0 - pb) + (f * pb) @ cols


def _direct_columns(breakage: Any, grid: SizeGrid, pb: np.ndarray) -> np.ndarray:
    """Appearance columns ``[parent, class]`` at one ``pb`` (fragment index) per parent, without the tabulation.

    A fit changes ``A`` (or ``beta``) at every step, so the 1025-node tables
    the mill solvers use would be rebuilt each time; here the columns are
    computed exactly at the parents' own ``t10``.
    """
    if hasattr(breakage, "direct_fragments"):  # each sub-model's own columns (its own t10 convention)
        return breakage.direct_fragments(grid.edges_mm, pb)
    return breakage.fragments(grid.edges_mm, np.arange(grid.n_classes), pb)


def _passing_at(grid: SizeGrid, fractions: np.ndarray, sizes_mm: np.ndarray) -> np.ndarray:
    cum = np.concatenate([[0.0], np.cumsum(fractions) * 100.0])
    return np.interp(np.log(sizes_mm), np.log(grid.edges_mm), cum, left=0.0, right=100.0)


def _to_x(values: np.ndarray, bounds: list[tuple[float, float]]) -> np.ndarray:
    """Internal coordinates: log for parameters bounded away from 0, linear otherwise."""
    return np.array([math.log(v) if lo > 0 else v for v, (lo, _) in zip(values, bounds, strict=True)])


def _from_x(x: np.ndarray, bounds: list[tuple[float, float]]) -> np.ndarray:
    return np.array([math.exp(v) if lo > 0 else v for v, (lo, _) in zip(x, bounds, strict=True)])


def _x_bounds(bounds: list[tuple[float, float]]) -> tuple[np.ndarray, np.ndarray]:
    lo = np.array([math.log(a) if a > 0 else a for a, _ in bounds])
    hi = np.array([math.log(b) if a > 0 else b for a, b in bounds])
    return lo, hi


@dataclass(frozen=True)
class ImpactFit:
    """Result of :func:`fit_impact_tests`.

    Attributes
    ----------
    submodel : str
        Breakage sub-model name.
    params : dict[str, float]
        All fittable parameters (fitted or held).
    std_errors : dict[str, float]
        One-sigma Jacobian standard errors of the fitted ones (approximate:
        cumulative passing at neighbouring sieves is correlated).
    rmse_pct : float
        RMS residual of % passing at the measured sieves over all tests.
    ks : dict[str, float]
        In-sample K-S per test id.
    breakage : object
        The fitted sub-model.
    bounds : dict[str, tuple[float, float]]
        Bounds of the fitted parameters (:func:`impact_bounds`).
    on_bound : tuple of str
        Fitted parameters that sit on a bound (their value is the bound's, not the data's).
    start_spread : dict[str, float]
        Per fitted parameter, the spread ``max - min`` of ``ln(value)`` over the starts whose
        objective came within :data:`NEAR_OPTIMUM_REL` of the best: 0.01 is about 1 %. A
        parameter whose lower bound is 0 (``e_min_kwh_t``): ``(max - min) / |best|``, or over
        1 % of the bound range when the best is nearer 0 than that.
    identified : bool
        Every fitted parameter off its bounds, with a multi-start spread below
        :data:`IDENTIFIED_SPREAD` and a finite standard error.
    n_starts : int
        Starts of the optimiser (:func:`fit_impact_tests` ``n_starts``).
    cost : float
        Objective at the optimum: half the weighted sum of squared residuals (fractions passing).
    """

    submodel: str
    params: dict[str, float]
    std_errors: dict[str, float]
    rmse_pct: float
    ks: dict[str, float]
    breakage: Any = field(repr=False)
    bounds: dict[str, tuple[float, float]] = field(default_factory=dict)
    on_bound: tuple[str, ...] = ()
    start_spread: dict[str, float] = field(default_factory=dict)
    identified: bool = True
    n_starts: int = 1
    cost: float = float("nan")


#: Starts within this relative objective of the best count as reaching the optimum.
NEAR_OPTIMUM_REL = 0.01
#: Largest multi-start spread (log units, about a relative spread) of an identified parameter.
IDENTIFIED_SPREAD = 0.05
#: Relative distance (in the optimiser's coordinates, of the bound range) at which a value is on its bound.
ON_BOUND_REL = 1e-3


def _impact_data(tests: Sequence[Any], grid: SizeGrid) -> list[tuple]:
    """Per test: feed fractions on ``grid``, speed (m/s), sieves (mm), measured fraction passing, sqrt(weight)."""
    return [(t.feed_psd.rebin(grid).fractions, float(t.impact_speed_m_s), t.product_psd.sizes_mm,
             np.clip(t.product_psd.passing_pct, 0.0, 100.0) / 100.0, math.sqrt(t.weight)) for t in tests]


def _start_points(x0: np.ndarray, lo: np.ndarray, hi: np.ndarray, n_starts: int, seed: int) -> np.ndarray:
    """``x0`` and ``n_starts - 1`` scrambled Halton points inside ``[lo, hi]`` (optimiser coordinates)."""
    if n_starts <= 1:
        return x0[None]
    from scipy.stats import qmc

    pts = qmc.scale(qmc.Halton(d=x0.size, scramble=True, seed=seed).random(n_starts - 1), lo, hi)
    return np.vstack([x0, pts])


def fit_impact_tests(tests: Sequence[Any], ore: Any, submodel: str = "ab_t10",
                     fit: Sequence[str] | None = None, start: dict[str, float] | None = None,
                     n_starts: int = 8, seed: int = 0,
                     bounds: dict[str, tuple[float, float]] | None = None) -> ImpactFit:
    """Fit a breakage sub-model's parameters to single-impact tests' whole product PSDs.

    Least squares on the cumulative fraction passing at every measured sieve
    (``docs/breakage.md`` section 5.1 gives the reasons): bounded residuals, so
    an empty or near-empty sieve class weighs what its mass weighs, and a curve
    closed at 100 % one sieve higher or lower changes the objective by that
    sieve's residual only.

    Parameters
    ----------
    tests : sequence of Experiment
        ``kind = "single_impact"`` experiments (one ore).
    ore : str or Ore or BreakageParameters
        Ore supplying held parameters and start values.
    submodel : {"ab_t10", "jk_t10", "energy_t10", "vogel_swebrec"}
        Breakage sub-model (:data:`FITTABLE`).
    fit : sequence of str, optional
        Parameters to fit (default all of :data:`FITTABLE` ``[submodel]``).
    start : dict, optional
        Start values overriding the ore-derived ones (the first start).
    n_starts : int
        Optimiser starts: the ore-derived one and ``n_starts - 1`` Halton points
        inside the bounds; the spread of the near-optimal ones is
        :attr:`ImpactFit.start_spread`.
    seed : int
        Seed of the Halton starts.
    bounds : dict, optional
        Bounds overriding :func:`impact_bounds`.
    """
    from scipy.optimize import least_squares

    if submodel not in FITTABLE:
        raise MsmillInputError("breakage", submodel, sm.did_you_mean(submodel, list(FITTABLE)))
    tests = list(tests)
    if not tests or any(t.kind != "single_impact" for t in tests):
        raise MsmillInputError("tests", len(tests), "one or more single-impact tests")
    fit = tuple(fit or FITTABLE[submodel])
    bad = [f for f in fit if f not in FITTABLE[submodel]]
    if bad:
        raise MsmillInputError("fit", bad, f"parameters of {submodel}: {', '.join(FITTABLE[submodel])}")
    bp = breakage_parameters(ore)
    values = current_values(build_breakage(submodel, bp, {}))
    values.update(start or {})
    bnd = impact_bounds(submodel, tests, bp)
    for k, (a, b) in (bounds or {}).items():
        if k not in bnd or not (0.0 <= a < b) or (bnd[k][0] > 0 and a <= 0):
            raise MsmillInputError(f"bounds.{k}", (a, b), f"LOW < HIGH for one of {', '.join(bnd)} "
                                   "(LOW > 0 except for e_min_kwh_t)")
        bnd[k] = (float(a), float(b))
    pbounds = [bnd[f] for f in fit]
    grid = impact_grid(tests)
    data = _impact_data(tests, grid)

    def model_for(x: np.ndarray) -> Any:
        return build_breakage(submodel, bp, {**values, **dict(zip(fit, _from_x(x, pbounds), strict=True))})

    def resid(x: np.ndarray) -> np.ndarray:
        brk = model_for(x)
        return np.concatenate([w * (_passing_at(grid, single_impact_product(brk, grid, f, v), s) / 100.0 - p)
                               for f, v, s, p, w in data])

    lo, hi = _x_bounds(pbounds)
    inset = 1e-9 * (hi - lo)
    x0 = np.clip(_to_x(np.maximum(np.array([values[f] for f in fit]), [b[0] for b in pbounds]), pbounds),
                 lo + inset, hi - inset)
    sols = [least_squares(resid, xs, bounds=(lo, hi), method="trf", x_scale="jac")
            for xs in np.clip(_start_points(x0, lo, hi, n_starts, seed), lo + inset, hi - inset)]
    costs = np.array([s.cost for s in sols])
    sol = sols[int(np.argmin(costs))]
    near = np.array([s.x for s, c in zip(sols, costs, strict=True)
                     if c <= sol.cost * (1.0 + NEAR_OPTIMUM_REL) + 1e-14])
    # log coordinates: the spread of ln(value) is relative; linear ones (lower bound 0) relative to the best
    # value, or to 1 % of the bound range when the best is near 0
    scale = np.array([1.0 if b[0] > 0 else max(abs(sol.x[i]), 0.01 * (hi[i] - lo[i]))
                      for i, b in enumerate(pbounds)])
    spread = {f: float(np.ptp(near[:, i]) / scale[i]) for i, f in enumerate(fit)}
    brk = model_for(sol.x)
    r = sol.fun
    dof = max(r.size - len(fit), 1)
    s2 = float(r @ r) / dof
    try:
        cov_x = np.linalg.inv(sol.jac.T @ sol.jac) * s2
        se_x = np.sqrt(np.clip(np.diag(cov_x), 0.0, None))
    except np.linalg.LinAlgError:
        se_x = np.full(len(fit), np.inf)
    params = current_values(brk)
    vals = _from_x(sol.x, pbounds)
    se = {f: float(se_x[i] * (vals[i] if pbounds[i][0] > 0 else 1.0)) for i, f in enumerate(fit)}
    tol = ON_BOUND_REL * (hi - lo)
    on_bound = tuple(f for i, f in enumerate(fit) if sol.x[i] - lo[i] <= tol[i] or hi[i] - sol.x[i] <= tol[i])
    identified = (not on_bound and all(v <= IDENTIFIED_SPREAD for v in spread.values())
                  and all(math.isfinite(v) for v in se.values()))
    ks = {t.id: measured_ks(t.product_psd, PSD(grid, single_impact_product(brk, grid, d[0], d[1]),
                                                  validate=False)) for t, d in zip(tests, data, strict=True)}
    return ImpactFit(submodel, params, se, 100.0 * math.sqrt(float(r @ r) / r.size), ks, brk,
                     bounds={f: bnd[f] for f in fit}, on_bound=on_bound, start_spread=spread,
                     identified=identified, n_starts=len(sols), cost=float(sol.cost))


#: Retained mass (%) below which a sieve class is left out of :func:`noise_sigma` (a lab's 4-decimal
#: rounding and empty classes carry no information on the scatter).
NOISE_MASS_FLOOR_PCT = 1e-2
#: Replicates of :func:`bootstrap_std_errors`.
N_BOOTSTRAP = 32


def _retained_pct(passing_pct: np.ndarray) -> np.ndarray:
    return np.diff(np.concatenate([[0.0], passing_pct, [100.0]]))  # pan, sieve classes, oversize


def _predicted_passing(fit: ImpactFit, grid: SizeGrid, test: Any) -> np.ndarray:
    prod = single_impact_product(fit.breakage, grid, test.feed_psd.rebin(grid).fractions, float(test.impact_speed_m_s))
    return _passing_at(grid, prod, test.product_psd.sizes_mm)


def noise_sigma(tests: Sequence[Any], fit: ImpactFit) -> float:
    """Scatter of the tests about a fit: ``sigma`` of ``m_meas = m_fit exp(sigma z)`` per retained mass.

    The pooled standard deviation of ``ln(m_meas / m_fit)`` over the sieve classes
    (pan and oversize included) that hold more than :data:`NOISE_MASS_FLOOR_PCT`
    in both, each test's mean removed (a lab renormalises its masses to 100 %),
    with the fitted parameters' degrees of freedom taken off. Multiplicative
    scatter of each retained mass is the usual model of sieving and sampling
    error (docs/breakage.md section 5.1).
    """
    grid = impact_grid(tests)
    parts = []
    for t in tests:
        mm = _retained_pct(np.clip(t.product_psd.passing_pct, 0.0, 100.0))
        mp = _retained_pct(_predicted_passing(fit, grid, t))
        ok = (mm > NOISE_MASS_FLOOR_PCT) & (mp > NOISE_MASS_FLOOR_PCT)
        if ok.sum() >= 2:
            lr = np.log(mm[ok] / mp[ok])
            parts.append(lr - lr.mean())
    if not parts:
        return 0.0
    r = np.concatenate(parts)
    return float(math.sqrt(float(r @ r) / max(r.size - len(parts) - len(fit.std_errors), 1)))


def bootstrap_std_errors(tests: Sequence[Any], ore: Any, fit: ImpactFit, n_boot: int = N_BOOTSTRAP,
                         seed: int = 0) -> tuple[dict[str, float], float]:
    """Parametric-bootstrap standard errors of a single-impact fit, and the scatter ``sigma`` they assume.

    ``n_boot`` replicate sets of the tests are made from the fitted sub-model's
    products at each test's own sieves, every retained mass scattered by
    :func:`noise_sigma`'s ``sigma`` (``msmill.model.synthetic.noisy_passing``),
    and refitted (one start, at the fit). The standard deviation of the refitted
    values is the standard error. Unlike the Jacobian error (sieves treated as
    independent, while one test's cumulative residuals move together) and the
    jackknife over a handful of tests (a few degrees of freedom), it follows how
    a lab's scatter propagates into the parameters; it assumes the fitted
    sub-model and multiplicative scatter (docs/breakage.md section 5.1).
    """
    from msmill.model.synthetic import noisy_passing

    sigma = noise_sigma(tests, fit)
    names = list(fit.std_errors)
    if sigma <= 0 or n_boot < 2:
        return {k: float("nan") for k in names}, sigma
    grid = impact_grid(tests)
    rng = np.random.default_rng(seed)
    preds = []
    for t in tests:
        prod = single_impact_product(fit.breakage, grid, t.feed_psd.rebin(grid).fractions, float(t.impact_speed_m_s))
        preds.append(PSD(grid, prod, validate=False))
    draws = []
    for _ in range(n_boot):
        reps = []
        for t, pred in zip(tests, preds, strict=True):
            sizes = t.product_psd.sizes_mm
            p = noisy_passing(pred, sizes, sigma, rng)
            if t.product_psd.passing_pct[-1] >= 100.0:
                p[-1] = 100.0  # the lab's curve closes where this one did
            reps.append(dataclasses.replace(t, product_psd=PSD.from_passing(sizes[: p.size], p)))
        f = fit_impact_tests(reps, ore, fit.submodel, fit=names, start=fit.params, n_starts=1,
                             bounds=fit.bounds)
        draws.append([f.params[k] for k in names])
    sd = np.std(np.array(draws), axis=0, ddof=1)
    return {k: float(v) for k, v in zip(names, sd, strict=True)}, sigma


#: How :func:`compare_submodels` holds tests out: one impact speed at a time, or one test at a time.
HOLD_OUT = ("speed", "test")


def compare_submodels(tests: Sequence[Any], ore: Any, submodels: Sequence[str] | None = None,
                      hold_out: str = "speed", n_starts: int = 8,
                      starts: dict[str, dict[str, float]] | None = None) -> pd.DataFrame:
    """Held-out K-S of each sub-model: fit without some tests, predict them.

    ``submodels``: default every fittable one (:data:`FITTABLE`), the mill's default ``jk_t10`` among them.
    ``hold_out``: ``"speed"`` (fit on all impact speeds but one, predict the held-out
    speed's tests) or ``"test"`` (leave one test out at a time). ``n_starts``: as
    :func:`fit_impact_tests`; ``starts``: per sub-model, the first start's values
    (e.g. the all-test fit, from which a held-out fit moves little).

    Returns
    -------
    pandas.DataFrame
        One row per (sub-model, held-out test): ``submodel, held_out_speed_m_s,
        id, ks_held_out`` and ``fit_<p>``, the parameters fitted without it.
    """
    if hold_out not in HOLD_OUT:
        raise MsmillInputError("hold_out", hold_out, sm.did_you_mean(hold_out, list(HOLD_OUT)))
    submodels = tuple(FITTABLE) if submodels is None else tuple(submodels)
    tests = list(tests)
    speeds = sorted({float(t.impact_speed_m_s) for t in tests})
    if len(speeds) < 2:
        raise MsmillInputError("single-impact tests", f"{len(speeds)} speed(s)",
                               "tests at two or more impact speeds (fit on some, predict the others)")
    groups = ([[t for t in tests if float(t.impact_speed_m_s) == v] for v in speeds] if hold_out == "speed"
              else [[t] for t in tests])
    grid = impact_grid(tests)
    rows = []
    for name in submodels:
        for held in groups:
            ids = {t.id for t in held}
            f = fit_impact_tests([t for t in tests if t.id not in ids], ore, name, n_starts=n_starts,
                                 start=(starts or {}).get(name))
            for t in held:
                v = float(t.impact_speed_m_s)
                pred = single_impact_product(f.breakage, grid, t.feed_psd.rebin(grid).fractions, v)
                rows.append({"submodel": name, "held_out_speed_m_s": v, "id": t.id,
                             "ks_held_out": measured_ks(t.product_psd, PSD(grid, pred, validate=False)),
                             **{f"fit_{k}": f.params[k] for k in FITTABLE[name]}})
    return pd.DataFrame(rows)


def impact_report(tests: Sequence[Any], ore: Any, submodels: Sequence[str] | None = None,
                  hold_out: str = "test", n_starts: int = 8,
                  n_boot: int = N_BOOTSTRAP) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Every sub-model fitted to all tests and held out: the table ``msmill calibrate`` prints.

    Returns
    -------
    summary : pandas.DataFrame
        One row per sub-model: ``submodel, ks_fit_mean, ks_held_out_mean,
        rmse_pct, identified, on_bound`` (comma-separated names or ``""``), and
        ``noise_sigma`` (:func:`noise_sigma`) and per fitted parameter ``<p>``,
        ``se_bootstrap_<p>`` (:func:`bootstrap_std_errors`: the standard error
        ``msmill calibrate`` reports), ``se_<p>`` (Jacobian), ``se_jackknife_<p>``
        (``sqrt((n-1)/n sum (theta_i - mean)^2)`` over the leave-one-test-out fits;
        NaN with ``hold_out="speed"``), ``spread_<p>`` (multi-start), ``lo_<p>``, ``hi_<p>`` (bounds).
    held_out : pandas.DataFrame
        :func:`compare_submodels` rows.
    """
    submodels = tuple(FITTABLE) if submodels is None else tuple(submodels)
    fits = {name: fit_impact_tests(tests, ore, name, n_starts=n_starts) for name in submodels}
    # held-out fits start from the all-test optimum (one start each: the multi-start is the all-test fit's)
    held = compare_submodels(tests, ore, submodels, hold_out=hold_out, n_starts=1,
                             starts={name: f.params for name, f in fits.items()})
    rows = []
    for name, f in fits.items():
        row: dict[str, Any] = {"submodel": name, "ks_fit_mean": float(np.mean(list(f.ks.values()))),
                               "ks_held_out_mean": float(held.loc[held["submodel"] == name, "ks_held_out"].mean()),
                               "rmse_pct": f.rmse_pct, "identified": f.identified, "on_bound": ",".join(f.on_bound)}
        mine = held[held["submodel"] == name]
        boot, row["noise_sigma"] = bootstrap_std_errors(tests, ore, f, n_boot=n_boot)
        for k in FITTABLE[name]:
            th = mine[f"fit_{k}"].to_numpy(dtype=float)
            jk = (math.sqrt((th.size - 1) / th.size * float(np.sum((th - th.mean()) ** 2)))
                  if hold_out == "test" and th.size > 1 else float("nan"))
            row.update({k: f.params[k], f"se_bootstrap_{k}": boot[k], f"se_{k}": f.std_errors[k],
                        f"se_jackknife_{k}": jk,
                        f"spread_{k}": f.start_spread[k], f"lo_{k}": f.bounds[k][0], f"hi_{k}": f.bounds[k][1]})
        rows.append(row)
    return pd.DataFrame(rows), held


# ---------------------------------------------------------------- mill surveys
#: Parameters :func:`calibrate_surveys` can fit, with bounds, and the ore field each sets.
SURVEY_FITTABLE: dict[str, tuple[float, float]] = {
    "l_ref_mm": (2.0, 500.0), "A_pct": (5.0, 100.0), "b_t_per_kwh": (0.02, 20.0), "gamma": (0.5, 50.0),
}


#: Confidence level of :meth:`SurveyCalibration.interval` unless told.
INTERVAL_LEVEL = 0.95


def welch_satterthwaite_dof(parts: Sequence[tuple[float, float]]) -> float:
    """Effective degrees of freedom of ``sqrt(sum s_i^2)`` from parts ``(s_i, dof_i)``.

    ``(sum s_i^2)^2 / sum(s_i^4 / dof_i)``; parts with NaN or zero ``s_i`` are skipped, and
    ``inf`` when none is left.
    """
    num, den = 0.0, 0.0
    for s, nu in parts:
        if s == s and s > 0.0 and nu > 0:
            num += s * s
            den += s ** 4 / nu
    return num * num / den if den > 0.0 else math.inf


@dataclass(frozen=True)
class SurveyCalibration:
    """Result of :func:`calibrate_surveys` for one ore.

    Attributes
    ----------
    ore : str
    fitted : tuple of str
        Fitted parameters (ore field names: ``l_ref_mm``, ``A_pct``, ``b_t_per_kwh``, ``gamma``).
    params : dict[str, float]
        Fitted values.
    std_errors : dict[str, float]
        Total standard errors: ``sqrt(jackknife**2 + stage**2)`` (the jackknife alone when
        no stage-parameter samples were drawn).
    jackknife_std_errors : dict[str, float]
        Jackknife (leave-one-survey-out) standard errors: the surveys' scatter.
    stage_std_errors : dict[str, float]
        Standard deviation of the parameters refitted with each of ``stage_samples``
        posterior samples of the stage parameters (:class:`~msmill.model.providers.PosteriorSample`):
        what the surrogate's uncertainty adds; NaN when none were drawn.
    jacobian_std_errors : dict[str, float]
        ``L_ref`` fits with ``objective="ssq"``: ``sqrt(s² / JᵀJ)`` from the
        sieve residuals (treats sieves as independent, so usually smaller); NaN otherwise.
    objective : str
        ``"ks"`` (mean K-S) or ``"ssq"`` (weighted sum of squares of % passing).
    table : pandas.DataFrame
        Per survey: ``id, ks_before, ks_fit, ks_cv`` (K-S with the start
        parameters, with the fit, and held out: predicted with parameters
        fitted without it) and the leave-one-out parameter values.
    interpolation_ks : float
        Largest K-S between the spline-interpolated and the exact products at
        the optimum (``L_ref`` only; 0 otherwise).
    seconds : float
        Wall time of the calibration (s).
    n_points : int
        Distinct operating points.
    stage_samples : int
        Posterior samples of the stage parameters behind :attr:`stage_std_errors` (0: none).
    stage_params : pandas.DataFrame
        The parameters fitted with each posterior sample (one row per sample).
    dof : dict[str, float]
        Degrees of freedom of :attr:`std_errors` (Welch-Satterthwaite over the ``n - 1`` of the
        jackknife and the ``stage_samples - 1`` of the posterior spread): both parts are estimated
        from a handful of refits, so an interval is ``t`` quantiles of these, not normal ones
        (:meth:`interval`).
    """

    ore: str
    fitted: tuple[str, ...]
    params: dict[str, float]
    std_errors: dict[str, float]
    jacobian_std_errors: dict[str, float]
    objective: str
    table: pd.DataFrame
    interpolation_ks: float
    seconds: float
    n_points: int
    jackknife_std_errors: dict[str, float] = field(default_factory=dict)
    stage_std_errors: dict[str, float] = field(default_factory=dict)
    stage_samples: int = 0
    stage_params: pd.DataFrame = field(default_factory=pd.DataFrame)
    dof: dict[str, float] = field(default_factory=dict)

    def interval(self, name: str, level: float = INTERVAL_LEVEL) -> tuple[float, float]:
        """Two-sided ``level`` confidence interval of a fitted parameter: value -+ t quantile x s.e.

        The quantile is Student's ``t`` with :attr:`dof` degrees of freedom (normal when ``dof`` is
        unknown): with 8 surveys and 8 posterior samples a 95 % interval is about 2.3 s.e. wide each
        side, not 1.96.
        """
        from scipy.stats import t

        if not 0.0 < level < 1.0:
            raise MsmillInputError("level", level, "a confidence level between 0 and 1")
        q = float(t.ppf(0.5 + level / 2.0, self.dof.get(name, math.inf)))  # inf dof: the normal quantile
        v, se = self.params[name], self.std_errors[name]
        return v - q * se, v + q * se

    def provenance(self) -> str:
        """One-line provenance text for the calibrated ore file."""
        def one(k: str) -> str:
            lo, hi = self.interval(k)
            return f"{k} = {self.params[k]:.4g} +- {self.std_errors[k]:.2g} (95 % {lo:.4g}-{hi:.4g})"

        fit = ", ".join(one(k) for k in self.fitted)
        how = ("jackknife s.e." if not self.stage_samples else
               f"s.e. of the jackknife and of {self.stage_samples} stage-parameter posterior samples")
        return (f"msmill calibrate: {fit} ({how}), objective {self.objective}, "
                f"{len(self.table)} surveys, mean K-S {self.table['ks_fit'].mean():.3f} fitted, "
                f"{self.table['ks_cv'].mean():.3f} leave-one-out")


def _objective_fn(model: Any, objective: str) -> Callable[[np.ndarray, np.ndarray], float]:
    """``f(products (n, N), idx) -> objective`` over the surveys ``idx``."""
    sv = model.surveys
    sieves = [(e.product_psd.sizes_mm[:-1], e.product_psd.passing_pct[:-1], e.weight) for e in sv]

    def ks(prod: np.ndarray, idx: np.ndarray) -> float:
        return float(np.mean([measured_ks(sv[i].product_psd, PSD(model.grid, prod[i], validate=False))
                              for i in idx]))

    def ssq(prod: np.ndarray, idx: np.ndarray) -> float:
        tot = 0.0
        for i in idx:
            s, p, w = sieves[i]
            r = _passing_at(model.grid, prod[i], s) - p
            tot += w * float(r @ r)
        return tot

    return ks if objective == "ks" else ssq


def _spline_products(model: Any, lref_nodes: np.ndarray) -> Callable[[float], np.ndarray]:
    from scipy.interpolate import CubicSpline

    stack = np.stack([model.products(model.with_ore(l_ref_mm=float(L))) for L in lref_nodes])
    spl = CubicSpline(np.log(lref_nodes), stack, axis=0)

    def at(L: float) -> np.ndarray:
        p = np.clip(spl(math.log(L)), 0.0, None)
        return p / p.sum(axis=-1, keepdims=True)

    return at


def _fit_1d(obj: Callable[[float], float], lo: float, hi: float) -> float:
    from scipy.optimize import minimize_scalar

    grid = np.exp(np.linspace(math.log(lo), math.log(hi), 161))
    vals = np.array([obj(g) for g in grid])
    k = int(np.argmin(vals))
    a, b = grid[max(k - 1, 0)], grid[min(k + 1, grid.size - 1)]
    if a == b:
        return float(a)
    res = minimize_scalar(lambda u: obj(math.exp(u)), bounds=(math.log(a), math.log(b)), method="bounded",
                          options={"xatol": 1e-5})
    return float(math.exp(res.x)) if res.fun <= vals[k] else float(grid[k])


#: Posterior samples of the stage parameters :func:`calibrate_surveys` refits with by default.
DEFAULT_STAGE_SAMPLES = 8


def calibrate_surveys(model: Any, fit: Sequence[str] = ("l_ref_mm",), objective: str = "ssq",
                      n_nodes: int = 9, bounds: dict[str, tuple[float, float]] | None = None,
                      cross_validate: bool = True, stage_samples: int = DEFAULT_STAGE_SAMPLES,
                      seed: int = 0) -> SurveyCalibration:
    """Fit ore parameters to the surveys of a :class:`~msmill.model.validation.SurveyModel`.

    Parameters
    ----------
    model : SurveyModel
        Surveys of one ore, with the stage parameters cached per operating point.
    fit : sequence of str
        From :data:`SURVEY_FITTABLE`; not ``b_t_per_kwh`` with ``l_ref_mm``.
    objective : {"ssq", "ks"}
        Weighted sum of squares of % passing at the measured sieves (default:
        smooth, and its jackknife standard error is sound), or the mean K-S
        (the paper's metric; non-smooth, so its jackknife error is unreliable).
    n_nodes : int
        Spline nodes over ``ln L_ref`` (``L_ref``-only fits).
    bounds : dict, optional
        Bounds overriding :data:`SURVEY_FITTABLE`.
    cross_validate : bool
        Leave-one-survey-out refits (K-S held out and jackknife standard errors).
    stage_samples : int
        Posterior samples of the stage parameters (a provider with
        ``sample_stage_parameters``, e.g. the default surrogate; ignored for a
        table): the fit is repeated with each, and the spread of the fitted
        values is the stage-parameter part of the standard error
        (:attr:`SurveyCalibration.stage_std_errors`). 0: none.
    seed : int
        Seed of the posterior samples.
    """
    t0 = time.perf_counter()
    fit = tuple(dict.fromkeys(fit))
    if not fit or any(f not in SURVEY_FITTABLE for f in fit):
        raise MsmillInputError("fit", list(fit), f"a non-empty subset of {', '.join(SURVEY_FITTABLE)}")
    if "b_t_per_kwh" in fit and "l_ref_mm" in fit:
        raise MsmillInputError("fit", list(fit), "not both b and L_ref (they enter Eq. 11 only as b/L_ref)")
    if objective not in OBJECTIVES:
        raise MsmillInputError("objective", objective, sm.did_you_mean(objective, list(OBJECTIVES)))
    bnd = {**SURVEY_FITTABLE, **(bounds or {})}
    n = len(model.surveys)
    if cross_validate and n < 3:
        raise MsmillInputError("surveys", n, "at least 3 surveys of the ore for leave-one-out cross-validation")
    f_obj = _objective_fn(model, objective)
    start = model.products()
    every = np.arange(n)
    interp_ks = 0.0
    if fit == ("l_ref_mm",):
        lo, hi = bnd["l_ref_mm"]
        at = _spline_products(model, np.exp(np.linspace(math.log(lo), math.log(hi), n_nodes)))

        def solve(idx: np.ndarray) -> dict[str, float]:
            return {"l_ref_mm": _fit_1d(lambda L: f_obj(at(L), idx), lo, hi)}

        def predict(p: dict[str, float]) -> np.ndarray:
            return at(p["l_ref_mm"])
    else:
        solve, predict = _direct_solver(model, fit, bnd, f_obj)
    best = solve(every)
    exact = model.products(model.with_ore(**best))
    if fit == ("l_ref_mm",):
        interp_ks = float(max(ks_statistic(PSD(model.grid, a, validate=False), PSD(model.grid, b, validate=False))
                              for a, b in zip(exact, predict(best), strict=True)))
    rows = [{"id": e.id, "ks_before": k0, "ks_fit": k1} for e, k0, k1 in
            zip(model.surveys, model.ks(start), model.ks(exact), strict=True)]
    se = {f: float("nan") for f in fit}
    if cross_validate:
        loo = []
        for i in range(n):
            p = solve(np.delete(every, i))
            loo.append(p)
            rows[i]["ks_cv"] = float(model.ks(predict(p))[i])
            rows[i].update({f"loo_{k}": v for k, v in p.items()})
        for f in fit:
            th = np.array([p[f] for p in loo])
            se[f] = float(math.sqrt((n - 1) / n * np.sum((th - th.mean()) ** 2)))
    table = pd.DataFrame(rows)
    if "ks_cv" not in table:
        table["ks_cv"] = np.nan
    jse = {f: float("nan") for f in fit}
    if fit == ("l_ref_mm",) and objective == "ssq":
        jse["l_ref_mm"] = _jacobian_se(model, predict, best["l_ref_mm"])
    stage_se = {f: float("nan") for f in fit}
    draws = pd.DataFrame()
    n_samples = int(stage_samples) if hasattr(model.provider, "sample_stage_parameters") else 0
    if n_samples == 1 or n_samples < 0:
        raise MsmillInputError("stage_samples", stage_samples, "0 (none) or 2 or more posterior samples")
    if n_samples:
        from msmill.model.providers import posterior_samples

        draws = pd.DataFrame([calibrate_surveys(model.with_provider(member), fit, objective, n_nodes, bounds,
                                                cross_validate=False, stage_samples=0).params
                              for member in posterior_samples(model.provider, n_samples, seed)])
        stage_se = {f: float(draws[f].std(ddof=1)) for f in fit}
    total = {f: float(math.hypot(se[f], stage_se[f])) if n_samples else se[f] for f in fit}
    dof = {f: welch_satterthwaite_dof([(se[f], n - 1), (stage_se[f], n_samples - 1)]) for f in fit}
    return SurveyCalibration(model.ore.name, fit, best, total, jse, objective, table, interp_ks,
                             time.perf_counter() - t0, model.n_points, jackknife_std_errors=se,
                             stage_std_errors=stage_se, stage_samples=n_samples, stage_params=draws, dof=dof)


def _jacobian_se(model: Any, predict: Callable, l_ref_mm: float, h: float = 1e-3) -> float:
    """``L_ref`` standard error ``L sqrt(s² / JᵀJ)`` with ``J = dr/d ln L`` of the sieve residuals."""
    def resid(L: float) -> np.ndarray:
        prod = predict({"l_ref_mm": L})
        return np.concatenate([math.sqrt(e.weight) * (_passing_at(model.grid, prod[i], e.product_psd.sizes_mm[:-1])
                                                       - e.product_psd.passing_pct[:-1])
                               for i, e in enumerate(model.surveys)])

    r = resid(l_ref_mm)
    J = (resid(l_ref_mm * math.exp(h)) - resid(l_ref_mm * math.exp(-h))) / (2 * h)
    s2 = float(r @ r) / max(r.size - 1, 1)
    jtj = float(J @ J)
    return l_ref_mm * math.sqrt(s2 / jtj) if jtj > 0 else float("inf")


def _direct_solver(model: Any, fit: tuple[str, ...], bnd: dict, f_obj: Callable) -> tuple[Callable, Callable]:
    """Nelder-Mead on the exact model (several parameters); each evaluation assembles every point."""
    from scipy.optimize import minimize

    bounds = [bnd[f] for f in fit]
    lo, hi = _x_bounds(bounds)
    cache: dict[tuple, np.ndarray] = {}

    def predict(p: dict[str, float]) -> np.ndarray:
        key = tuple(round(p[f], 10) for f in fit)
        if key not in cache:
            cache[key] = model.products(model.with_ore(**p))
        return cache[key]

    def as_params(x: np.ndarray) -> dict[str, float]:
        return dict(zip(fit, _from_x(np.clip(x, lo, hi), bounds), strict=True))

    state = {"x": np.clip(_to_x(np.array([float(getattr(model.ore, f)) for f in fit]), bounds), lo, hi),
             "step": 0.1, "first": True}

    def solve(idx: np.ndarray) -> dict[str, float]:
        """First call from the ore's values; later (leave-one-out) calls warm-start from the first fit."""
        x0 = state["x"]
        simplex = np.vstack([x0, x0 + state["step"] * np.eye(len(fit))])
        res = minimize(lambda x: f_obj(predict(as_params(x)), idx), x0, method="Nelder-Mead",
                       options={"xatol": 1e-3, "fatol": 1e-8, "maxfev": 60 * len(fit),
                                "initial_simplex": simplex})
        if state["first"]:
            state.update(x=np.clip(res.x, lo, hi), step=0.02, first=False)
        return as_params(res.x)

    return solve, predict


def calibrated_ore(ore: Any, cal: SurveyCalibration) -> Any:
    """Copy of an ``msmill.ore.Ore`` with the parameters of ``cal`` and its provenance."""
    text = cal.provenance()
    new = ore.with_l_ref(cal.params["l_ref_mm"], text) if "l_ref_mm" in cal.fitted else ore
    upd: dict[str, Any] = {}
    for name in ("A_pct", "b_t_per_kwh", "gamma"):  # the ore's field names
        if name in cal.fitted:
            upd[name] = cal.params[name]
    if upd:
        srcs = dict(new.sources)
        for key, names in (("breakage", ("A_pct", "b_t_per_kwh")), ("damage", ("gamma",))):
            if any(n in upd for n in names):
                srcs[key] = text
        upd["sources"] = srcs
        new = new.model_copy(update=upd)
    return new
