"""Where to run the DEM next: space-filling start, then cost-aware batch acquisition.

:func:`plan_batch` is the library function the campaign CLI calls:

1. While the surrogate has fewer than ``n_initial`` runs (or none), the batch
   continues a scrambled Sobol sequence (``scipy.stats.qmc``) in the unit cube
   of the design space (size in ``ln``).
2. Afterwards, from ``n_candidates`` Sobol candidates, points are chosen
   greedily by the largest summed predictive variance of the standardised
   targets (optionally weighted per target), divided by the expected DEM cost
   of the point (:class:`CostModel`) to the power ``cost_power``. The batch is
   spread by the **kriging believer** rule: after each pick the chosen point is
   added to every GP as if observed (with the GP's white noise), which, with
   the hyperparameters fixed, updates the posterior variance exactly (the
   variance does not depend on the observed value). Points already planned
   but not yet run (``pending``) are believed the same way before the first pick.

The update is the incremental (Cholesky / Gram-Schmidt) form: with
``g_t(x) = c_{t-1}(x, p_t) / sqrt(c_{t-1}(p_t, p_t) + s^2)``,
``var_t(x) = var_{t-1}(x) - g_t(x)^2`` and
``c_{t-1}(x, p) = c_0(x, p) - sum_{tau < t} g_tau(x) g_tau(p)``.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.linalg import cholesky, solve_triangular
from scipy.stats import qmc

from msmill.errors import MsmillInputError
from msmill.surrogate.gp import SurrogateGP
from msmill.surrogate.space import DesignSpace

#: Runs before the acquisition takes over from the space-filling design (2 d + 2).
DEFAULT_N_INITIAL = 10
#: Size exponent and feed exponent of the prior DEM cost ``~ feed / size^4``
#: (particles ~ feed / size^3, time step ~ size).
PRIOR_COST_EXPONENTS = (-4.0, 1.0)
#: Fine-rock cost, ``t = exp(ln_k) (feed / 30 t/h) (size / 4 mm)^-exponent`` (s of one core): rocks x time
#: steps dominate below the sizes the training runs timed. Measured with the campaign protocol at 30 t/h,
#: 1500 rpm, gates 40 deg (``benchmarks/data/fine_rock_cost``: 4 mm 1089 s, 3 mm 4430 s of CPU, 2 mm about
#: 29,000 s from a partial run's rate): ``ln_k = ln 1089``, exponent 4.75 (a log-log fit through 4 and 2 mm;
#: 3 mm then 4170 s, 0.94x). Steeper than the 4 of rocks x steps alone: more rocks fit less in cache.
FINE_COST = (math.log(1089.0), 4.75)
#: Timings of runs below this size (mm) refit the fine-rock scale
FINE_COST_SIZE_MM = 6.0
#: Fine timings from which the fine-rock term's gate and speed slopes are fitted too
FINE_SLOPE_MIN_TIMINGS = 6


def initial_design(n_points: int, design_space: DesignSpace | None = None, seed: int = 0,
                   method: str = "sobol", skip: int = 0) -> np.ndarray:
    """Space-filling design points (n_points, 4) in physical units.

    Parameters
    ----------
    n_points : int
        Number of points.
    design_space : DesignSpace, optional
        Bounds (default paper Table 2).
    seed : int
        Seed of the scrambling.
    method : {"sobol", "lhs"}
        Scrambled Sobol sequence or Latin hypercube.
    skip : int
        Points of the (Sobol) sequence already used; the design continues after them.
    """
    space = design_space or DesignSpace()
    if method == "sobol":
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # "balance properties ... power of 2": n is the batch
            u = qmc.Sobol(d=4, scramble=True, seed=seed).random(skip + n_points)[skip:]
    elif method == "lhs":
        u = qmc.LatinHypercube(d=4, seed=seed + skip).random(n_points)
    else:
        raise MsmillInputError("method", method, "sobol or lhs")
    return space.from_unit(u)


@dataclass(frozen=True)
class CostModel:
    """Expected DEM time of a design point: the larger of ``exp(c . [1, ln size, ln feed, speed_u, gate_u])``
    (fitted to timed runs) and the fine-rock term
    ``exp(ln_k + g (gate_u - 1/2) + s (speed_u - 1/2)) (feed / 30) (size / 4)^-exponent``.

    The log-linear term, fitted where the runs were timed (6.4-30 mm: wall ~ size^-0.97), extrapolated to
    2-4 mm predicts a twentieth of what such runs cost; below the timed sizes the rocks x time steps of
    the fine-rock term take over (:data:`FINE_COST`). Its gate and speed slopes ``g``, ``s`` are fitted
    to the fine timings once there are :data:`FINE_SLOPE_MIN_TIMINGS` (the fine campaign's 3.5-6 mm
    runs: an open gate empties the mill and costs about half, ``g`` = -0.85; rms log error 0.38 -> 0.23).

    Attributes
    ----------
    coef : tuple of float
        Coefficients (``speed_u``, ``gate_u``: unit-cube coordinates).
    n_timings : int
        Timings behind the fit (0: the prior ``~ feed / size^4`` in relative units, without the fine term).
    fine : tuple of float or None
        ``(ln_k, exponent, g, s)`` of the fine-rock term (s); None: none.
    """

    coef: tuple[float, ...] = (0.0, PRIOR_COST_EXPONENTS[0], PRIOR_COST_EXPONENTS[1], 0.0, 0.0)
    n_timings: int = 0
    design_space: DesignSpace = field(default_factory=DesignSpace)
    fine: tuple[float, float, float, float] | None = None

    def _features(self, X: np.ndarray) -> np.ndarray:
        X = np.atleast_2d(np.asarray(X, dtype=float))
        u = self.design_space.to_unit(X)
        return np.column_stack([np.ones(len(X)), np.log(X[:, 0]), np.log(X[:, 1]), u[:, 2], u[:, 3]])

    def predict_s(self, X: np.ndarray) -> np.ndarray:
        """Expected time (s of one core, or relative units for the prior) of design points (P, 4)."""
        t = np.exp(self._features(X) @ np.asarray(self.coef))
        if self.fine is None:
            return t
        X = np.atleast_2d(np.asarray(X, dtype=float))
        ln_k, e, g, s = self.fine
        u = self.design_space.to_unit(X) - 0.5
        return np.maximum(t, np.exp(ln_k + g * u[:, 3] + s * u[:, 2]) * (X[:, 1] / 30.0) * (X[:, 0] / 4.0) ** -e)

    @classmethod
    def from_timings(cls, X: np.ndarray, wall_s: Sequence[float],
                     design_space: DesignSpace | None = None) -> CostModel:
        """Fit to measured wall times (s) of runs at ``X``.

        With at least 6 timings all five coefficients are fitted by least
        squares (ridge-regularised towards the prior exponents); with fewer,
        the prior exponents are kept and only the scale is fitted. The fine-rock
        term is :data:`FINE_COST`, its scale refitted (geometric mean, exponent
        kept) to the timings below :data:`FINE_COST_SIZE_MM` where there are any,
        with its gate and speed slopes (ridge towards 0) from
        :data:`FINE_SLOPE_MIN_TIMINGS` of them.
        """
        space = design_space or DesignSpace()
        X = np.atleast_2d(np.asarray(X, dtype=float))
        t = np.asarray(wall_s, dtype=float)
        ok = np.isfinite(t) & (t > 0)
        X, t = X[ok], t[ok]
        base = cls(design_space=space)
        if t.size == 0:
            return base
        F, y = base._features(X), np.log(t)
        prior = np.asarray(base.coef)
        fine = _fit_fine_term(X, y, space)
        if t.size < 6:
            c0 = float(np.mean(y - F[:, 1:] @ prior[1:]))
            return cls((c0, *prior[1:]), int(t.size), space, fine)
        lam = 1e-2 * t.size
        A = F.T @ F + lam * np.diag([0.0, 1, 1, 1, 1])
        coef = np.linalg.solve(A, F.T @ y + lam * np.r_[0.0, prior[1:]])
        return cls(tuple(float(c) for c in coef), int(t.size), space, fine)

    @classmethod
    def from_runs(cls, runs: Iterable, design_space: DesignSpace | None = None) -> CostModel:
        """Fit to the ``provenance["wall_s"]`` of :class:`~msmill.stageparams.RunStatistics`."""
        X, t = [], []
        for r in runs:
            w = r.provenance.get("wall_s")
            if w is not None:
                X.append(r.design.inputs())
                t.append(float(w))
        return cls.from_timings(np.array(X).reshape(-1, 4), t, design_space)


def _fit_fine_term(X: np.ndarray, ln_t: np.ndarray, space: DesignSpace) -> tuple[float, float, float, float]:
    """``(ln_k, exponent, g, s)`` of the fine-rock term from the timings (``ln`` s) below :data:`FINE_COST_SIZE_MM`.

    The exponent is :data:`FINE_COST`'s; the scale is the timings' geometric mean and, from
    :data:`FINE_SLOPE_MIN_TIMINGS` of them, the gate and speed slopes are fitted with it by least
    squares, ridge-regularised towards 0 (flat) as the log-linear term is towards its prior.
    """
    ln_k, e = FINE_COST
    rows = X[:, 0] < FINE_COST_SIZE_MM
    if not rows.any():
        return ln_k, e, 0.0, 0.0
    y = ln_t[rows] - np.log(X[rows, 1] / 30.0) + e * np.log(X[rows, 0] / 4.0)
    if rows.sum() < FINE_SLOPE_MIN_TIMINGS:
        return float(np.mean(y)), e, 0.0, 0.0
    u = space.to_unit(X[rows]) - 0.5
    F = np.column_stack([np.ones(len(y)), u[:, 3], u[:, 2]])
    A = F.T @ F + 1e-3 * len(y) * np.diag([0.0, 1.0, 1.0])
    c = np.linalg.solve(A, F.T @ y)
    return float(c[0]), e, float(c[1]), float(c[2])


def group_weights(names: Sequence[str]) -> np.ndarray:
    """Acquisition weights giving every target group (``s<stage>.<group>``) the same total weight.

    Without them the ``N_LEVELS`` quantile targets of a velocity distribution
    would outweigh a stage's single hit probability ``N_LEVELS`` to one.
    """
    groups = [n.rsplit(".", 1)[0] for n in names]
    size = {g: groups.count(g) for g in set(groups)}
    return np.array([1.0 / size[g] for g in groups])


@dataclass(frozen=True)
class BatchPlan:
    """A planned batch of DEM runs.

    Attributes
    ----------
    points : ndarray (n, 4)
        ``size_mm, feed_tph, speed_rpm, gate_deg``.
    score : ndarray (n,)
        Summed predictive variance (standardised targets) at the pick, before
        dividing by cost (NaN for space-filling points).
    expected_cost_s : ndarray (n,)
        Expected wall time per point (s; relative units under the prior cost).
    method : str
        ``"sobol"`` or ``"believer"``.
    """

    points: np.ndarray
    score: np.ndarray
    expected_cost_s: np.ndarray
    method: str


def _latent_kernel(gp: SurrogateGP, j: int):
    return gp.estimators_[j].kernel_.k1


def plan_batch(model: SurrogateGP | None, n_points: int, design_space: DesignSpace | None = None, *,
               n_existing: int | None = None, pending: np.ndarray | None = None, cost: CostModel | None = None,
               cost_power: float = 1.0, weights: np.ndarray | None = None, n_candidates: int = 512,
               n_initial: int = DEFAULT_N_INITIAL, seed: int = 0, max_cost_s: float | None = None) -> BatchPlan:
    """Plan the next batch of ``n_points`` DEM runs (see the module docstring).

    Parameters
    ----------
    model : SurrogateGP or None
        The current fit (``StageSurrogate.gp_``), or None before any run.
    n_points : int
        Batch size.
    design_space : DesignSpace, optional
        Bounds of the candidates (default: the model's, else paper Table 2).
    n_existing : int, optional
        Runs done so far (default: the model's training runs).
    pending : ndarray (p, 4), optional
        Points planned earlier and not yet run; the batch avoids them.
    cost : CostModel, optional
        Expected DEM cost (default the prior ``~ feed / size^4``).
    cost_power : float
        Exponent of the cost in the acquisition (0 ignores cost).
    weights : ndarray (T,), optional
        Weight of every target's variance (default 1).
    n_candidates : int
        Sobol candidates scored.
    n_initial : int
        Runs before the acquisition replaces the space-filling design.
    seed : int
        Seed of the Sobol scrambling (candidates use ``seed + 1``).
    max_cost_s : float, optional
        No candidate whose expected cost exceeds this (s, the cost model's units) is chosen: a cap on
        the wall time of one run (a fine-rock point at a high feed can cost a whole session). The
        space-filling design is not capped.
    """
    if not isinstance(n_points, int | np.integer) or n_points < 1:
        raise MsmillInputError("batch", n_points, "an integer >= 1")
    if max_cost_s is not None and not max_cost_s > 0:
        raise MsmillInputError("max_cost_s", max_cost_s, "a positive cost (s) or None")
    space = design_space or (model.design_space if model is not None else DesignSpace())
    cost = cost or CostModel(design_space=space)
    n_done = n_existing if n_existing is not None else (0 if model is None else model.X_train_.shape[0])
    n_pend = 0 if pending is None else len(pending)
    if model is None or n_done < n_initial:
        pts = initial_design(n_points, space, seed=seed, skip=n_done + n_pend)
        return BatchPlan(pts, np.full(n_points, np.nan), cost.predict_s(pts), "sobol")
    cand = initial_design(n_candidates, space, seed=seed + 1)
    Uc = space.to_unit(cand)
    w = np.ones(model.n_targets) if weights is None else np.asarray(weights, dtype=float)
    Up = space.to_unit(np.asarray(pending, dtype=float)) if n_pend else None
    state = [_OutputState(model, j, Uc, Up) for j in range(model.n_targets)]
    cand_cost_s = cost.predict_s(cand)
    divisor = cand_cost_s ** cost_power
    # a candidate at a point already run or pending adds nothing (the store keeps a point once): the
    # fine campaign re-planned its first run's point, a candidate of the same deterministic set
    taken = np.asarray(model.X_train_, dtype=float)
    taken = np.vstack([taken, np.asarray(pending, dtype=float)]) if n_pend else taken
    run_already = (np.abs(Uc[:, None, :] - space.to_unit(taken)[None]) < 1e-9).all(axis=2).any(axis=1)
    too_dear = np.zeros(len(cand), dtype=bool) if max_cost_s is None else cand_cost_s > max_cost_s
    if too_dear.all():
        raise MsmillInputError("max_cost_s", max_cost_s, f"at least the cheapest candidate's expected cost, "
                               f"{float(cand_cost_s.min()):.3g} s")
    chosen, scores = [], []
    for _ in range(n_points):
        total = sum(wj * s.var for wj, s in zip(w, state, strict=True))
        acq = total / divisor
        acq[run_already | too_dear] = -np.inf
        acq[chosen] = -np.inf
        i = int(np.argmax(acq))
        chosen.append(i)
        scores.append(float(total[i]))
        for s in state:
            s.believe(i)
    pts = cand[chosen]
    return BatchPlan(pts, np.array(scores), cost.predict_s(pts), "believer")


class _OutputState:
    """Posterior variance of one GP over the candidates, updated point by point (kriging believer)."""

    def __init__(self, gp: SurrogateGP, j: int, Uc: np.ndarray, Up: np.ndarray | None = None) -> None:
        e = gp.estimators_[j]
        self.k = _latent_kernel(gp, j)
        self.Uc = Uc
        Ut, L = e.X_train_, e.L_
        if Up is not None and len(Up):  # believe the pending points: refactor with them as data
            Ut = np.vstack([Ut, Up])
            K = e.kernel_(Ut)
            K[np.diag_indices_from(K)] += np.r_[np.broadcast_to(e.alpha, (e.X_train_.shape[0],)),
                                                np.zeros(len(Up))]
            L = cholesky(K, lower=True)
        self.V = solve_triangular(L, self.k(Ut, Uc), lower=True)  # (n, C)
        self.var = np.maximum(self.k.diag(Uc) - np.sum(self.V**2, axis=0), 0.0)
        self.noise = float(gp.white_[j]) + 1e-10
        self.G: list[np.ndarray] = []  # g_t over the candidates

    def believe(self, i: int) -> None:
        """Condition on candidate ``i`` as if it had been observed."""
        c = self.k(self.Uc, self.Uc[i:i + 1])[:, 0] - self.V.T @ self.V[:, i]
        for g in self.G:
            c = c - g * g[i]
        g = c / np.sqrt(max(c[i], 0.0) + self.noise)
        self.G.append(g)
        self.var = np.maximum(self.var - g * g, 0.0)
