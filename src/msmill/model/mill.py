"""The :class:`Mill`: a chain of named, swappable sub-models and a solver.

Modelled on pvlib's ``ModelChain``: every step (transport, impacts, breakage,
damage) is chosen by name from one lookup table per step or given as an
object implementing the step's protocol; anything left out gets the default.
``repr(mill)`` lists the chosen models. :func:`simulate` is the one-call
convenience wrapper.

Example
-------
>>> mill = Mill("UG2", "table.json", damage="none")          # doctest: +SKIP
>>> res = mill.run(feed_psd, OperatingPoint(feed_tph=30, speed_rpm=1500, gate_deg=40))
>>> res.p80_mm, res.timeseries                                 # doctest: +SKIP
"""

from __future__ import annotations

import copy
import dataclasses
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from msmill.errors import ExtrapolationWarning, MsmillInputError, SummaryNote
from msmill.model import submodels as sm
from msmill.model.expected_value import assemble, steady_products
from msmill.model.providers import (
    HeldBelow,
    StageParameterProvider,
    load_provider,
    machine_mismatch,
    smallest_covered_mm,
)
from msmill.model.result import MillResult, time_to_steady_state, with_band
from msmill.model.solvers import Problem, Solution, resolve_solver
from msmill.psd import PSD, SizeGrid
from msmill.threadpools import single_threaded
from msmill.validate import InputWarning, integer, limit, number

IMPACTED = ("refeed", "all")
DEFAULT_PASSING_SIZES_MM = (0.075, 0.15, 0.6, 1.0, 2.0, 5.0, 10.0)
DEFAULT_MIN_SIZE_MM = 0.038
J_PER_KWH = 3.6e6
#: Fewest Monte-Carlo steps accepted (``mc_steps``): the mill needs ~100 characteristic
#: times to fill, so a handful of steps reports the filling mill's first trickle.
MIN_MC_STEPS = 50
#: Posterior samples behind the uncertainty band, its limits (%) and the quadrature nodes of its solves.
DEFAULT_BAND_SAMPLES = 64
MAX_BAND_SAMPLES = 1024
BAND_LIMITS_PCT = (5.0, 95.0)
DEFAULT_BAND_QUADRATURE_NODES = 4
DEFAULT_BAND_DAMAGE_CLASSES = 4


def _single_threaded_blas():
    """Run BLAS single-threaded: the model's matrices are small (tens to hundreds of rows),
    threads gain nothing and, on a busy machine, spinning BLAS threads cost 10x
    (:func:`msmill.threadpools.single_threaded`: the library scan is made once per process).
    """
    return single_threaded("blas")


def breakage_parameters(ore: Any) -> sm.BreakageParameters:
    """Ore name (looked up with ``msmill.ore.get_ore``), ``Ore`` object or :class:`BreakageParameters`."""
    if isinstance(ore, sm.BreakageParameters):
        return ore
    from msmill.ore import Ore, get_ore  # core layer; imported lazily

    if isinstance(ore, str):
        ore = get_ore(ore)
    if not isinstance(ore, Ore):
        raise MsmillInputError("ore", ore if ore is None else type(ore).__name__,
                               "an ore name (msmill ore list), a msmill.ore.Ore or BreakageParameters")
    return sm.BreakageParameters.from_ore(ore)


def _operating_point(op: Any, feed_tph: float | None = None) -> Any:
    from msmill.machine import OperatingPoint

    if op is None:
        raise MsmillInputError("operating_point", None, "an OperatingPoint or a dict of its fields")
    if isinstance(op, dict):
        op = OperatingPoint(**{**op, **({"feed_tph": feed_tph} if feed_tph else {})})
    if not isinstance(op, OperatingPoint):
        raise MsmillInputError("operating_point", type(op).__name__, "an OperatingPoint or a dict of its fields")
    return op


class Mill:
    """A multi-shaft impact mill model: sub-models, stage parameters and a solver.

    Parameters
    ----------
    ore : str or Ore or BreakageParameters
        Rock to break (name looked up in the ore registry, or parameters).
    stage_parameters : StageParameterProvider or path
        DEM-derived per-stage statistics (a table or one run's statistics file).
    machine : msmill.machine.Machine, optional
        Mill geometry; only its ``n_stages`` is used (checked against the provider).
    transport, impacts, breakage, damage : str or object, optional
        Sub-model names (see :data:`msmill.model.submodels.SUBMODELS`) or objects
        implementing the step's protocol. Defaults: ``dem_matrix``,
        ``speed_scaled``, ``jk_t10``, ``tavares``.
    solver : str or Solver
        How to solve: a name registered in :data:`msmill.model.solvers.SOLVERS`
        (``"expected_value"``, the default, or ``"monte_carlo"``, which takes
        ``parcels_per_step``, ``mc_steps`` and ``seed`` below) or an object with the
        :class:`~msmill.model.solvers.Solver` interface.
    impacted : {"refeed", "all"}
        Which mass is impacted in a step: the rocks that stay (paper step 5b,
        default) or all rocks in the stage before transport (docs/model.md).
    grid : msmill.psd.SizeGrid, optional
        Model size classes; default the sqrt(2) series from 0.038 mm up to the
        feed's top size.
    damage_classes : int
        Number of damage classes of the expected-value solver (default 8).
    quadrature_nodes : int
        Gauss-Hermite nodes per mixture component (default 12).
    parcels_per_step : int
        Monte-Carlo fresh parcels per step (default 2000).
    mc_steps : int, optional
        Monte-Carlo steps (default: twice the expected-value time to steady
        state plus 200 collection steps).
    seed : int, optional
        Monte-Carlo seed.
    passing_sizes_mm : sequence of float
        Sizes at which the result reports % passing.
    band_samples : int
        Posterior samples of the stage parameters behind the uncertainty band
        (5-95 %) on the product PSD and P80, when the provider can sample
        (``sample_stage_parameters``, e.g. the GP surrogate); 0 disables it.
    band_quadrature_nodes, band_damage_classes : int
        Resolution of the band's solves (coarser than the main solve keeps 64
        samples under 2 s). The band is the samples' spread about their median,
        added to the full-resolution prediction, so the coarser resolution's
        bias cancels (:func:`msmill.model.result.with_band`).
    envelope : "default", path, CapacityModel or None
        DEM operating envelope (:mod:`msmill.surrogate.capacity`): :meth:`run` warns
        (:class:`~msmill.surrogate.capacity.AboveCapacityWarning`) when the feed rate
        exceeds the capacity at the feed's F80, speed and gate, and reports
        capacity and steady probability in the result. ``"default"``: the
        shipped envelope (only for the default machine, or no machine given);
        None switches the check off.
    """

    def __init__(self, ore: Any, stage_parameters: Any, machine: Any = None, *,
                 transport: Any = None, impacts: Any = None, breakage: Any = None,
                 damage: Any = None, solver: Any = "expected_value", impacted: str = "refeed",
                 grid: SizeGrid | None = None, damage_classes: int = 8, quadrature_nodes: int = 12,
                 parcels_per_step: int = 2000, mc_steps: int | None = None, seed: int | None = None,
                 passing_sizes_mm=DEFAULT_PASSING_SIZES_MM, band_samples: int = DEFAULT_BAND_SAMPLES,
                 band_quadrature_nodes: int = DEFAULT_BAND_QUADRATURE_NODES,
                 band_damage_classes: int = DEFAULT_BAND_DAMAGE_CLASSES, envelope: Any = "default") -> None:
        self.ore = breakage_parameters(ore)
        if isinstance(stage_parameters, str | Path):
            stage_parameters = load_provider(stage_parameters)
        if not isinstance(stage_parameters, StageParameterProvider):
            raise MsmillInputError("stage_parameters", type(stage_parameters).__name__,
                                   "a provider (TableProvider, RunProvider, ...) or a file path")
        self.provider = stage_parameters
        self.machine = machine
        if machine is not None and getattr(machine, "n_stages", self.provider.n_stages) != self.provider.n_stages:
            raise MsmillInputError("machine.n_stages", machine.n_stages,
                                   f"{self.provider.n_stages} (the stages of the stage parameters)")
        self.machine_note = machine_mismatch(self.provider, machine)
        if self.machine_note:
            warnings.warn(self.machine_note, InputWarning, stacklevel=2)
        self.transport = sm.resolve("transport", transport, self.ore)
        self.impacts = sm.resolve("impacts", impacts, self.ore)
        self.breakage = sm.resolve("breakage", breakage, self.ore)
        self.damage = sm.resolve("damage", damage, self.ore)
        for step in ("breakage", "damage"):
            for need in getattr(getattr(self, step), "requires", ()):
                if hasattr(self.ore, need) and getattr(self.ore, need) is None and need != "tn":
                    raise MsmillInputError(f"ore.{need}", None, f"a value (needed by the {step} sub-model)")
        if impacted not in IMPACTED:
            raise MsmillInputError("impacted", impacted, sm.did_you_mean(impacted, list(IMPACTED)))
        damage_classes = integer(damage_classes, "damage_classes", ge=1)
        limit(damage_classes, "damage_classes")
        quadrature_nodes = integer(quadrature_nodes, "quadrature_nodes", ge=1)
        limit(quadrature_nodes, "quadrature_nodes")
        parcels_per_step = integer(parcels_per_step, "parcels_per_step", ge=1)
        limit(parcels_per_step, "parcels_per_step")
        if mc_steps is not None:
            mc_steps = integer(mc_steps, "mc_steps", ge=MIN_MC_STEPS)
            limit(mc_steps, "mc_steps")
            limit(parcels_per_step * mc_steps, "parcels_per_step x mc_steps", "parcels_total")
        if seed is not None:
            seed = integer(seed, "seed", ge=0, le=2**63 - 1)
        if grid is not None and not isinstance(grid, SizeGrid):
            raise MsmillInputError("grid", type(grid).__name__, "a msmill.psd.SizeGrid or None")
        if grid is not None:
            limit(grid.n_classes, "grid", "grid_classes")
        try:
            passing_sizes_mm = [number(s, "passing_sizes_mm", unit="mm", gt=0) for s in passing_sizes_mm]
        except TypeError:
            raise MsmillInputError("passing_sizes_mm", passing_sizes_mm, "a list of sizes > 0 mm") from None
        self.impacted = impacted
        self.grid = grid
        self.damage_classes = int(damage_classes)
        self.quadrature_nodes = int(quadrature_nodes)
        self.parcels_per_step = int(parcels_per_step)
        self.mc_steps = mc_steps
        self.seed = seed
        self.passing_sizes_mm = tuple(float(s) for s in passing_sizes_mm)
        self.solver = resolve_solver(solver, self)
        if not isinstance(band_samples, int | np.integer) or not 0 <= band_samples <= MAX_BAND_SAMPLES:
            raise MsmillInputError("band_samples", band_samples, f"an integer 0-{MAX_BAND_SAMPLES}")
        self.band_samples = int(band_samples)
        self.band_quadrature_nodes = int(band_quadrature_nodes)
        self.band_damage_classes = int(band_damage_classes)
        self._cache: dict[tuple, tuple] = {}
        self._band_cache: dict[tuple, tuple] = {}
        self.use_envelope(envelope)

    def use_envelope(self, envelope: Any) -> None:
        """Set the operating envelope :meth:`run` checks against (see the class's ``envelope``)."""
        from msmill.surrogate.capacity import CapacityModel, default_capacity_model, load_capacity

        if envelope is None:
            self.capacity = None
        elif isinstance(envelope, CapacityModel):
            self.capacity = envelope
        elif isinstance(envelope, str) and envelope == "default":
            from msmill.machine import Machine

            own = self.machine is None or self.machine == Machine.default()
            self.capacity = default_capacity_model() if own else None  # the shipped envelope is the default mill's
        elif isinstance(envelope, str | Path):
            self.capacity = load_capacity(envelope)
        else:
            raise MsmillInputError("envelope", type(envelope).__name__,
                                   "'default', an envelope JSON path, a CapacityModel or None")

    def check_capacity(self, feed: PSD, operating_point: Any) -> Any:
        """:class:`~msmill.surrogate.capacity.CapacityCheck` of a feed and operating point (None without an envelope)."""
        from msmill.surrogate.capacity import check_capacity

        op = _operating_point(operating_point)
        return check_capacity(self.capacity, feed.p80_mm, op.feed_tph, op.upper_speed_rpm, op.gate_deg)

    # ------------------------------------------------------------------ display
    def __repr__(self) -> str:
        o = self.ore
        lines = [
            "Mill(",
            f"  ore: {o.name} (A={o.A_pct:g} %, b={o.b_t_per_kwh:g} t/kWh, L_ref={o.l_ref_mm:g} mm)",
            f"  stage_parameters: {self.provider!r}",
            f"  transport: {self.transport!r}",
            f"  impacts: {self.impacts!r}",
            f"  breakage: {self.breakage!r}",
            f"  damage: {self.damage!r}",
            f"  solver: {self.solver!r} (impacted={self.impacted!r}, damage_classes={self.damage_classes}, "
            f"quadrature_nodes={self.quadrature_nodes})",
            ")",
        ]
        return "\n".join(lines)

    def submodel_names(self) -> dict[str, str]:
        """The sub-model chosen for each step, by name (or class name)."""
        return {step: getattr(getattr(self, step), "name", type(getattr(self, step)).__name__)
                for step in ("transport", "impacts", "breakage", "damage")}

    # ------------------------------------------------------------------ building
    def model_grid(self, feed: PSD) -> SizeGrid:
        """The size grid used for ``feed`` (the user's grid or the default sqrt(2) series)."""
        if self.grid is not None:
            return self.grid
        top = float(feed.grid.edges_mm[-1])
        return SizeGrid.geometric(DEFAULT_MIN_SIZE_MM, max(top, 2 * DEFAULT_MIN_SIZE_MM))

    def prepare(self, grid: SizeGrid, op: Any) -> tuple:
        """Stage parameters, streams, impact statistics and the linear system (cached).

        The cache key is the grid and the operating point, so repeated runs at
        one point (e.g. several feeds) reuse the operators; warnings raised while
        building are re-issued on every call.
        """
        speeds = op.stage_speeds(self.provider.n_stages)
        key = (grid.edges_mm.tobytes(), tuple(speeds), float(op.feed_tph), float(op.gate_deg))
        hit = self._cache.get(key)
        if hit is None:
            with warnings.catch_warnings(record=True) as caught, _single_threaded_blas():
                warnings.simplefilter("always")
                params = self.provider.stage_parameters(grid.mids_mm, speeds, op.feed_tph, op.gate_deg)
                streams = sm.transition_of(self.transport, params)
                stats = sm.without_stopped_rotors(self.impacts.impacts(params, np.asarray(speeds, dtype=float)),
                                                  np.asarray(speeds, dtype=float))
                lm = None
                if self.solver.needs_operator():
                    lm = assemble(grid.edges_mm, streams, stats, self.breakage, self.damage,
                                  self.damage_classes, self.quadrature_nodes, self.impacted)
            hit = (params, streams, stats, lm, [(w.message, w.category) for w in caught])
            if len(self._cache) > 8:
                self._cache.pop(next(iter(self._cache)))
            self._cache[key] = hit
        for message, category in hit[4]:
            if not issubclass(category, SummaryNote):  # notes go to MillResult.notes only
                warnings.warn(message, category, stacklevel=3)
        return hit

    # ------------------------------------------------------------------ running
    def run(self, feed: PSD, operating_point: Any, *, timeseries: bool = True,
            max_steps: int = 20000, held_below: bool = True) -> MillResult:
        """Predict the mill's response to ``feed`` at ``operating_point``.

        Parameters
        ----------
        feed : msmill.psd.PSD
            Feed size distribution (any grid; rebinned to the model grid).
        operating_point : msmill.machine.OperatingPoint or dict
            Feed rate (t/h), shaft speeds (rpm) and gate angle (deg).
        timeseries : bool
            March in time from an empty mill (Fig. 14 series, time to steady
            state). The expected-value steady state itself always comes from the
            direct solve.
        max_steps : int
            Cap on the number of time steps marched.
        held_below : bool
            Where size classes lie below the sizes the stage statistics cover, solve the steady state
            again with the statistics held at the smallest covered size (:class:`~msmill.model.providers.
            HeldBelow`) and report the product's P80 and passing 75 um under that rule
            (``MillResult.held_below_*``, a note): the sensitivity to the rule for rock finer than any
            DEM run. Costs a second steady-state solve; sweeps turn it off.
        """
        if not isinstance(feed, PSD):
            raise MsmillInputError("feed", type(feed).__name__, "a msmill.psd.PSD")
        op = _operating_point(operating_point)
        max_steps = integer(max_steps, "max_steps", ge=1)
        limit(max_steps, "max_steps", "time_steps")
        with _single_threaded_blas():
            res = self._run(feed, op, timeseries, max_steps)
            if held_below:
                res = self._with_held_below(res, feed, op, max_steps)
        return self._with_capacity(res, feed, op)

    def _with_capacity(self, res: MillResult, feed: PSD, op: Any) -> MillResult:
        """Warn above the envelope's capacity; capacity, probability and a note in the result."""
        from msmill.surrogate.capacity import AboveCapacityWarning

        chk = self.check_capacity(feed, op)
        if chk is None:
            return res
        if chk.above:
            warnings.warn(chk.message(), AboveCapacityWarning, stacklevel=3)
        return dataclasses.replace(res, capacity_tph=chk.capacity_tph, probability_steady=chk.probability_steady,
                                   capacity_is_lower_bound=chk.lower_bound, notes=(*res.notes, chk.message()))

    def _run(self, feed: PSD, op: Any, timeseries: bool, max_steps: int) -> MillResult:
        grid = self.model_grid(feed)
        above = 100.0 - float(feed.passing_at(float(grid.edges_mm[-1])))
        if above > 1e-6:
            warnings.warn(f"{above:.3g} % of the feed is coarser than the model grid's top size "
                          f"({grid.edges_mm[-1]:.4g} mm) and is lumped into its top class",
                          InputWarning, stacklevel=3)
        feed_m = feed.rebin(grid) if feed.grid != grid else feed
        _warn_implausible_feed(feed, self.machine)
        params, streams, stats, lm, caught = self.prepare(grid, op)
        dt = params.characteristic_time_s
        tonnes_per_step = op.feed_tph * dt / 3600.0
        brk_notes = getattr(getattr(self.breakage, "ore", None), "notes", ())  # e.g. a sub-model's default
        notes = [*dict.fromkeys([*self.ore.notes, *brk_notes]), f"stage parameters: {params.source}"]
        notes += [self.machine_note] if self.machine_note else []
        notes += [streams.note] if streams.note else []
        if not self.solver.moves_by_fill and getattr(streams, "filling", None) is not None:
            notes.append(f"transport: the {self.solver.name} solver moves rock by the steady matrix throughout "
                         "(the fill-dependent speed is the expected-value march's)")
        notes += [str(m) for m, _ in caught]
        problem = Problem(feed_m.fractions, grid.edges_mm, streams, stats, lm, tonnes_per_step, timeseries,
                          max_steps, self.breakage, self.damage, self.impacted)
        res = self._result(feed_m, op, grid, dt, tonnes_per_step, self.solver.solve(problem), notes)
        res = _with_extrapolated_share(res, params)
        _warn_extrapolated_share(res)
        if self.band_samples and hasattr(self.provider, "sample_stage_parameters"):
            key = (grid.edges_mm.tobytes(), feed_m.fractions.tobytes(), tuple(op.stage_speeds(self.provider.n_stages)),
                   float(op.feed_tph), float(op.gate_deg))
            if key not in self._band_cache:
                if len(self._band_cache) > 8:
                    self._band_cache.pop(next(iter(self._band_cache)))
                self._band_cache[key] = self.product_band(feed_m, op, grid)
            res = with_band(res, *self._band_cache[key])
        return res

    def _with_held_below(self, res: MillResult, feed: PSD, op: Any, max_steps: int) -> MillResult:
        """The result with the product under the other bounding rule below the covered sizes (:class:`HeldBelow`).

        Nothing to add when no class lies below the sizes the statistics cover.
        """
        with warnings.catch_warnings():  # the run issued them already
            warnings.simplefilter("ignore")
            params = self.prepare(self.model_grid(feed), op)[0]  # cached by the run
        lo = smallest_covered_mm(params, self.provider)
        if lo is None:
            return res
        held = copy.copy(self)
        held.provider, held.band_samples = HeldBelow(self.provider), 0
        held._cache, held._band_cache = {}, {}
        with warnings.catch_warnings():  # the same warnings as the prediction's own
            warnings.simplefilter("ignore")
            other = held._run(feed, op, False, max_steps)
        return dataclasses.replace(res, held_below_mm=lo, held_below_p80_mm=other.p80_mm,
                                   held_below_passing_75um_pct=float(other.product_psd.passing_at(0.075)),
                                   notes=(*res.notes, held_below_note(res, other, lo)))

    def product_band(self, feed: PSD, op: Any, grid: SizeGrid) -> tuple[np.ndarray, np.ndarray]:
        """Product % passing and P80 of posterior samples of the stage parameters.

        Each sample goes through the expected-value solver's steady state
        (at ``band_damage_classes`` and ``band_quadrature_nodes``), all samples
        in one batch (:func:`msmill.model.expected_value.steady_products`).

        Returns
        -------
        passing_pct : ndarray (n_samples, N)
            Product cumulative % passing at ``grid.upper_mm`` per sample.
        p80_mm : ndarray (n_samples,)
        """
        speeds = op.stage_speeds(self.provider.n_stages)
        samples = self.provider.sample_stage_parameters(grid.mids_mm, self.band_samples, speeds,
                                                        op.feed_tph, op.gate_deg, seed=self.seed or 0)
        products = self.batch_products(grid, op, samples, feed.fractions)  # all samples in one batch
        passing, p80 = [], []
        for product in np.clip(products, 0.0, None):
            psd = PSD(grid, product / product.sum(), validate=False)
            passing.append(psd.passing_pct)
            p80.append(psd.p80_mm)
        return np.array(passing), np.array(p80)

    def batch_products(self, grid: SizeGrid, op: Any, params: list, feed_fractions: np.ndarray,
                       tonnes_per_step: np.ndarray | None = None) -> np.ndarray:
        """Steady products of a batch of stage-parameter sets (e.g. posterior samples) at ``op``, solved together.

        At the band's resolution (``band_damage_classes``, ``band_quadrature_nodes``) by
        :func:`msmill.model.expected_value.steady_products`.

        Parameters
        ----------
        params : list of StageParameters
            One set per member, at ``grid.mids_mm``.
        feed_fractions : ndarray (N,) or (N, K)
            Feed mass fractions (K feeds at once: the identity gives transfer matrices).
        tonnes_per_step : ndarray (B,), optional
            Feed of one step of each member (t); default ``op.feed_tph`` over each member's
            characteristic time.

        Returns
        -------
        ndarray (B, N) or (B, N, K)
            Product of one step by size class (t).
        """
        speeds_rpm = np.asarray(op.stage_speeds(self.provider.n_stages), dtype=float)
        transports = [sm.transition_of(self.transport, p) for p in params]
        stats = [sm.without_stopped_rotors(self.impacts.impacts(p, speeds_rpm), speeds_rpm) for p in params]
        if tonnes_per_step is None:
            tonnes_per_step = np.array([op.feed_tph * p.characteristic_time_s / 3600.0 for p in params])
        with _single_threaded_blas():
            return steady_products(grid.edges_mm, transports, stats, self.breakage, self.damage,
                                   self.band_damage_classes, self.band_quadrature_nodes, self.impacted,
                                   feed_fractions, tonnes_per_step)

    def _result(self, feed: PSD, op: Any, grid: SizeGrid, dt: float, tps: float, sol: Solution,
                notes: list[str]) -> MillResult:
        """Format a solver's :class:`~msmill.model.solvers.Solution` as the :class:`MillResult`."""
        prod, held, per, stage_mass = sol.product_series_t, sol.holdup_series_t, sol.per_step, sol.stage_mass_t
        clipped = np.clip(sol.product_fractions, 0.0, None)
        product = PSD(grid, clipped / clipped.sum(), validate=False)
        table = pd.DataFrame({
            "lower_mm": grid.lower_mm, "upper_mm": grid.upper_mm, "mid_mm": grid.mids_mm,
            "feed_mass_fraction": feed.fractions, "product_mass_fraction": product.fractions,
            "feed_passing_pct": feed.passing_pct, "product_passing_pct": product.passing_pct,
        })
        sizes = np.array(self.passing_sizes_mm)
        passing = pd.Series(np.atleast_1d(product.passing_at(sizes)), index=pd.Index(sizes, name="size_mm"),
                            name="product_passing_pct")
        t = (np.arange(prod.size) + 1) * dt
        ts = pd.DataFrame({"time_s": t, "feed_tph": np.full(prod.size, op.feed_tph),
                           "holdup_t": held, "product_tph": prod / dt * 3600.0})
        rate = ts["product_tph"].to_numpy()
        k = self.solver.smoothing_steps
        if k and rate.size >= k:
            # parcel noise: judge steady state on a centred moving average (no lag)
            c = np.cumsum(np.concatenate([[0.0], rate]))
            ma = (c[k:] - c[:-k]) / k
            half = k // 2
            rate = np.concatenate([np.zeros(half), ma, np.full(rate.size - ma.size - half, ma[-1])])
        t_ss = time_to_steady_state(t, rate, op.feed_tph, holdup_t=held) if prod.size else float("nan")
        n_st = stage_mass.shape[0]
        hold = stage_mass.sum(axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            stage_frac = stage_mass / hold[:, None]
        p80 = []
        for s in range(n_st):
            p80.append(PSD(grid, stage_frac[s], validate=False).p80_mm if hold[s] > 0 else float("nan"))
        stages = pd.DataFrame({
            "stage": np.arange(1, n_st + 1),
            "holdup_t": hold,
            "p80_mm": p80,
            "primary_impacts_per_t": per["primary_t"] / tps,
            "secondary_impacts_per_t": per["secondary_t"] / tps,
            "impact_energy_kwh_t": (per["primary_kwh"] + per["secondary_kwh"]) / tps,
            "flinger_energy_j_per_t": per["primary_kwh"] / tps * J_PER_KWH,
        })
        stage_psd = pd.DataFrame(stage_frac.T, index=pd.Index(grid.upper_mm, name="upper_mm"),
                                 columns=[f"stage_{s + 1}" for s in range(n_st)])
        f80 = feed.p80_mm
        return MillResult(
            feed_psd=feed, product_psd=product, psd_table=table,
            p50_mm=product.p50_mm, p80_mm=product.p80_mm, f80_mm=f80,
            reduction_ratio=f80 / product.p80_mm, passing_pct=passing, timeseries=ts,
            time_to_steady_state_s=t_ss, stages=stages, stage_psd=stage_psd,
            primary_impacts_per_t=float(stages["primary_impacts_per_t"].sum()),
            secondary_impacts_per_t=float(stages["secondary_impacts_per_t"].sum()),
            specific_impact_energy_kwh_t=float(stages["impact_energy_kwh_t"].sum()),
            mass_balance_error=float(sol.mass_balance_error), feed_tph=float(op.feed_tph), characteristic_time_s=dt,
            solver=self.solver.name, submodels=self.submodel_names(), notes=(*notes, *sol.notes),
        )


#: Product mass % on stage statistics extrapolated in size above which a prediction warns (not only notes):
#: above it the product's P20 and every passing figure below the trained sizes (75 um and the like) are
#: predictions from extrapolated statistics; below it only the finest tail is (docs/model.md, "What a
#: prediction rests on").
EXTRAPOLATED_WARN_PCT = 20.0


def _warn_extrapolated_share(res: MillResult) -> None:
    """An :class:`ExtrapolationWarning` when more than :data:`EXTRAPOLATED_WARN_PCT` of the product rests on
    stage statistics extrapolated in size."""
    pct = res.extrapolated_product_pct
    if pct == pct and pct > EXTRAPOLATED_WARN_PCT:  # not NaN
        mask = res.extrapolated_classes
        n = "" if mask is None else f" ({int(np.sum(mask))} of {mask.size} size classes)"
        warnings.warn(f"{pct:.0f} % of the product mass{n} rests on stage statistics extrapolated beyond the "
                      f"rock sizes the DEM ran (feed {res.extrapolated_feed_pct:.0f} %): the passing fractions "
                      "there are extrapolations", ExtrapolationWarning, stacklevel=3)


def _warn_implausible_feed(feed: PSD, machine: Any) -> None:
    """Warn when the feed holds rock wider than the mill's feed chute (sieves in the wrong unit, typically)."""
    from msmill.machine import Machine

    chute_m = machine.chute_width_m if machine is not None else Machine.model_fields["chute_width_m"].default
    nonzero = np.flatnonzero(feed.fractions > 1e-12)
    if not nonzero.size:
        return
    top_mm = float(feed.grid.edges_mm[nonzero[-1] + 1])
    if top_mm > 1000.0 * chute_m:
        warnings.warn(f"feed: rock up to {top_mm:.4g} mm is wider than the mill's feed chute "
                      f"({1000.0 * chute_m:g} mm): check the sieve sizes (mm)", InputWarning, stacklevel=4)


def held_below_note(res: MillResult, held: MillResult, lo_mm: float) -> str:
    """One line: how far P80 and passing 75 um move when the statistics are held below ``lo_mm``."""
    p, q = float(res.product_psd.passing_at(0.075)), float(held.product_psd.passing_at(0.075))
    return (f"rule below the DEM's sizes: statistics held at {lo_mm:.3g} mm instead of the provider's "
            f"extrapolation give P80 {held.p80_mm:.3g} mm (here {res.p80_mm:.3g}) and passing 75 um "
            f"{q:.3g} % (here {p:.3g} %)")


def _with_extrapolated_share(res: MillResult, params: Any) -> MillResult:
    """The result with the feed and product mass % whose stage parameters were extrapolated, or rest on
    thin data (inside the trained sizes, far from every training run)."""
    out = {}
    for field, key in (("extrapolated", "extrapolated"), ("thin_data", "thin_data")):
        mask = getattr(params, field, None)
        if mask is not None:
            mask = np.asarray(mask, dtype=bool)
            out[f"{key}_feed_pct"] = 100.0 * float(res.feed_psd.fractions[mask].sum())
            out[f"{key}_product_pct"] = 100.0 * float(res.product_psd.fractions[mask].sum())
            out[f"{key}_classes"] = mask.copy()
    return dataclasses.replace(res, **out) if out else res


def simulate(ore: Any, feed: PSD, operating_point: Any, stage_parameters: Any, machine: Any = None,
             **options: Any) -> MillResult:
    """One-call prediction: ``Mill(ore, stage_parameters, machine, **options).run(feed, operating_point)``.

    Parameters
    ----------
    ore : str or Ore or BreakageParameters
        Rock to break.
    feed : msmill.psd.PSD
        Feed size distribution.
    operating_point : msmill.machine.OperatingPoint or dict
        ``feed_tph``, ``speed_rpm`` or ``stage_speeds_rpm``, ``gate_deg``.
    stage_parameters : provider or path
        Per-stage DEM statistics.
    machine : msmill.machine.Machine, optional
        Mill geometry (stage count checked).
    **options
        Sub-model choices and solver options of :class:`Mill`.
    """
    return Mill(ore, stage_parameters, machine, **options).run(feed, operating_point)
