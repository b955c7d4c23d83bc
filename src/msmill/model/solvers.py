"""Solvers of the mill model: small registered classes behind one interface.

A solver turns one prepared mill (transport, impact statistics, breakage and
damage sub-models, and the expected-value operator where it needs one) and a
feed into a :class:`Solution`: the steady product, the hold-up by stage and
class, impact counts and energies per step, and the time series from an empty
mill. :class:`~msmill.model.mill.Mill` formats the solution into a
:class:`~msmill.model.result.MillResult`; it never asks which solver it holds.

To add a solver, write a class with ``name``, ``smoothing_steps``,
``moves_by_fill``, ``needs_operator`` and ``solve`` (the :class:`Solver`
protocol), a ``from_mill(mill)`` classmethod reading the options it takes
from :class:`~msmill.model.mill.Mill`, and register it in :data:`SOLVERS`.
"""

from __future__ import annotations

import dataclasses
import warnings
from typing import Any, Protocol, runtime_checkable

import numpy as np

from msmill.errors import MsmillInputError
from msmill.model.expected_value import LinearMill
from msmill.model.montecarlo import MonteCarloSolver
from msmill.model.result import time_to_steady_state
from msmill.validate import InputWarning, limit

#: Shortfall of the Monte-Carlo product rate below the feed rate over the collection
#: window above which the run is reported as not at steady state.
MC_STEADY_TOL = 0.1
#: Centred moving-average window (steps) of the Monte-Carlo product rate for the
#: time to steady state.
MC_SMOOTHING_STEPS = 25


@dataclasses.dataclass(frozen=True)
class Problem:
    """One prepared mill and its feed, as every solver receives it.

    Attributes
    ----------
    feed_fractions : ndarray (N,)
        Feed mass fractions on the model grid.
    edges_mm : ndarray (N + 1,)
        Model size-class edges (mm).
    streams : msmill.model.submodels.Transition
        One-step transport of every compartment.
    stats : msmill.model.parameters.ImpactStatistics
        Impact statistics of every stage and size class.
    operator : LinearMill or None
        The expected-value operator (None when the solver said it needs none).
    tonnes_per_step : float
        Feed of one characteristic time step (t).
    timeseries : bool
        Whether to march the mill from empty.
    max_steps : int
        Cap on the steps marched.
    breakage, damage : sub-models
        The mill's breakage and damage steps.
    impacted : {"refeed", "all"}
        Which mass is impacted in a step.
    """

    feed_fractions: np.ndarray
    edges_mm: np.ndarray
    streams: Any
    stats: Any
    operator: LinearMill | None
    tonnes_per_step: float
    timeseries: bool
    max_steps: int
    breakage: Any
    damage: Any
    impacted: str


@dataclasses.dataclass(frozen=True)
class Solution:
    """What a solver found, in tonnes per characteristic step.

    Attributes
    ----------
    product_fractions : ndarray (N,)
        Steady product by size class (mass fractions, not yet clipped).
    stage_mass_t : ndarray (S, N)
        Steady hold-up of each stage by size class (t).
    inlet_t : float
        Hold-up in the inlet zone (t; NaN where the solver does not track it).
    per_step : dict of ndarray (S,)
        ``primary_t``, ``primary_kwh``, ``secondary_t``, ``secondary_kwh``: tonnes impacted and
        impact energy (kWh) per step and stage.
    product_series_t, holdup_series_t : ndarray (T,)
        Product (t) and hold-up (t) of each step from an empty mill (empty without a march).
    mass_balance_error : float
        Largest relative mass-balance error seen.
    notes : tuple of str
        What the solver adds to the result's notes.
    """

    product_fractions: np.ndarray
    stage_mass_t: np.ndarray
    inlet_t: float
    per_step: dict[str, np.ndarray]
    product_series_t: np.ndarray
    holdup_series_t: np.ndarray
    mass_balance_error: float
    notes: tuple[str, ...] = ()


@runtime_checkable
class Solver(Protocol):
    """Interface of a mill solver (see the module docstring)."""

    name: str
    #: Centred moving-average window (steps) on the product rate before the time to steady state is
    #: judged (0: none).
    smoothing_steps: int
    #: Whether the solver moves rock by the fill-dependent transport speed (where the transport has one).
    moves_by_fill: bool

    def needs_operator(self) -> bool:
        """Whether :attr:`Problem.operator` must be assembled for :meth:`solve`."""
        ...

    def solve(self, problem: Problem) -> Solution:
        """Solve one prepared mill."""
        ...


def march(lm: LinearMill, feed_t: np.ndarray, max_steps: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """March the expected-value mill from empty until its product matches the feed.

    Parameters
    ----------
    lm : LinearMill
        The expected-value operator.
    feed_t : ndarray
        Feed state vector of one step (t, :meth:`LinearMill.feed_vector`).
    max_steps : int
        Cap on the steps.

    Returns
    -------
    product_t, holdup_t, mass_balance_error : ndarray (T,)
        Product and hold-up (t) after each step and the relative mass-balance error so far.
    """
    x = np.zeros(lm.n_state)
    fs = feed_t.sum()
    prod, held, err = [], [], []
    cum_fed = cum_out = 0.0
    min_steps = 5 * (lm.n_stages + 1)
    steady_t = float(lm.steady_state(feed_t).sum()) if lm.fill_dependent else 1.0
    for t in range(max_steps):
        x, out = lm.step(x, float(x.sum()) / steady_t)
        x = x + feed_t
        cum_fed += fs
        cum_out += out
        h = float(x.sum())
        prod.append(out)
        held.append(h)
        err.append(abs(cum_fed - h - cum_out) / cum_fed)
        if t >= min_steps and abs(out / fs - 1.0) < 1e-5:
            break
    return np.array(prod), np.array(held), np.array(err)


class ExpectedValue:
    """Expected-value solver: the direct steady state of the linear mill and its march from empty.

    Exact for the discretised model (damage classes, quadrature nodes: :class:`~msmill.model.mill.Mill`'s
    options, used when the operator is assembled); ``docs/model.md`` section 3.
    """

    name = "expected_value"
    smoothing_steps = 0
    moves_by_fill = True

    @classmethod
    def from_mill(cls, mill: Any) -> ExpectedValue:
        """The solver with a :class:`~msmill.model.mill.Mill`'s options (it takes none of its own)."""
        return cls()

    def needs_operator(self) -> bool:
        return True

    def __repr__(self) -> str:
        return "ExpectedValue()"

    def solve(self, problem: Problem) -> Solution:
        lm = problem.operator
        tps = problem.tonnes_per_step
        f = lm.feed_vector(problem.feed_fractions, tps)
        x = lm.steady_state(f)
        if problem.timeseries:
            prod, held, err = march(lm, f, problem.max_steps)
        else:
            prod = held = err = np.zeros(0)
        product = np.asarray(lm.out_op @ x)
        ss_err = abs(product.sum() - tps) / tps
        n, nd, n_st = lm.n_sizes, lm.n_damage, lm.n_stages
        xs = x.reshape(n_st + 1, n, nd)
        y = (lm.impacted @ x).reshape(n_st + 1, n * nd)[1:]
        per = {
            "primary_t": np.array([lm.stages[s].primary_count @ y[s] for s in range(n_st)]),
            "primary_kwh": np.array([lm.stages[s].primary_energy_kwh_t @ y[s] for s in range(n_st)]),
            "secondary_t": np.array([lm.stages[s].secondary_count @ y[s] for s in range(n_st)]),
            "secondary_kwh": np.array([lm.stages[s].secondary_energy_kwh_t @ y[s] for s in range(n_st)]),
        }
        return Solution(product / product.sum(), xs[1:].sum(axis=2), float(xs[0].sum()), per, prod, held,
                        max(float(err.max(initial=0.0)), ss_err))


class MonteCarlo:
    """Parcel Monte-Carlo solver (:class:`~msmill.model.montecarlo.MonteCarloSolver`) over the same sub-models.

    Parameters
    ----------
    parcels_per_step : int
        Fresh feed parcels per step.
    steps : int, optional
        Steps marched (a third of them warm-up); default twice the expected-value time to steady
        state plus 200 collection steps (needs the expected-value operator for its march).
    seed : int, optional
        Seed of the random stream.
    """

    name = "monte_carlo"
    smoothing_steps = MC_SMOOTHING_STEPS
    moves_by_fill = False

    def __init__(self, parcels_per_step: int = 2000, steps: int | None = None, seed: int | None = None) -> None:
        self.parcels_per_step = int(parcels_per_step)
        self.steps = steps
        self.seed = seed

    @classmethod
    def from_mill(cls, mill: Any) -> MonteCarlo:
        """The solver with a :class:`~msmill.model.mill.Mill`'s ``parcels_per_step``, ``mc_steps`` and ``seed``."""
        return cls(mill.parcels_per_step, mill.mc_steps, mill.seed)

    def needs_operator(self) -> bool:
        return self.steps is None

    def __repr__(self) -> str:
        return f"MonteCarlo(parcels_per_step={self.parcels_per_step}, steps={self.steps}, seed={self.seed})"

    def solve(self, problem: Problem) -> Solution:
        tps = problem.tonnes_per_step
        if self.steps is not None:
            n_steps = int(self.steps)
            warm = n_steps // 3
        else:
            lm = problem.operator
            prod, _, _ = march(lm, lm.feed_vector(problem.feed_fractions, tps), problem.max_steps)
            t_ss = time_to_steady_state(np.arange(1, prod.size + 1), prod / tps, 1.0, tol=0.001)
            warm = int(2 * (t_ss if np.isfinite(t_ss) else prod.size)) + 10
            n_steps = warm + 200
        limit(self.parcels_per_step * n_steps, f"parcels_per_step x steps ({self.parcels_per_step} x {n_steps})",
              "parcels_total")
        run = MonteCarloSolver(self.parcels_per_step, self.seed).run(
            problem.edges_mm, problem.streams, problem.stats, problem.breakage, problem.damage,
            problem.feed_fractions, tps, n_steps, warm, problem.impacted)
        coll = run.product[warm:].sum(axis=0)
        out_ratio = float(coll.sum()) / max((n_steps - warm) * tps, 1e-300)
        if out_ratio < 1.0 - MC_STEADY_TOL:
            warnings.warn(f"Monte Carlo with mc_steps={n_steps}: over its last {n_steps - warm} steps the mill "
                          f"put out {100 * out_ratio:.3g} % of its feed, so it was still filling and the "
                          "product PSD is not the steady one; raise mc_steps or leave it unset",
                          InputWarning, stacklevel=4)
        per = {k: v / (n_steps - warm) for k, v in run.counts.items()}
        note = (f"Monte Carlo: {self.parcels_per_step} parcels/step, {n_steps} steps, "
                f"statistics over the last {n_steps - warm}, seed {self.seed}")
        return Solution(coll / coll.sum(), run.stage_mass, float("nan"), per, run.product.sum(axis=1),
                        run.holdup, float(run.mass_balance_error.max()), (note,))


#: Registered solvers by name (``Mill(solver=name)``).
SOLVERS: dict[str, type] = {"expected_value": ExpectedValue, "monte_carlo": MonteCarlo}


def resolve_solver(spec: Any, mill: Any) -> Solver:
    """A solver from its registered name (options from ``mill``) or a :class:`Solver` object."""
    from msmill.model.submodels import did_you_mean

    if isinstance(spec, str):
        if spec not in SOLVERS:
            raise MsmillInputError("solver", spec, did_you_mean(spec, list(SOLVERS)))
        return SOLVERS[spec].from_mill(mill)
    if not isinstance(spec, Solver):
        raise MsmillInputError("solver", type(spec).__name__,
                               "a solver name (" + ", ".join(SOLVERS) + ") or an object with the Solver interface")
    return spec
