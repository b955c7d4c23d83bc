"""The stage-statistics surrogate: target transforms + one GP per target.

:class:`StageSurrogate` is trained from any iterable of
:class:`msmill.stageparams.RunStatistics` (a stage-parameter table's runs, or
the SQL store's ``training_runs(...)``) and predicts every stage's statistics
at any design point, with uncertainty.

Stage inputs
------------
The training runs share one speed recipe (stage speed / upper-stage speed,
e.g. ``[1, 1, 1, 1, 2]``). A stage's targets are predicted at the design
point ``(size, feed, speed_s / factor_s, gate)``: each stage sees its own
speed expressed as the equivalent upper-stage speed of the recipe. An
arbitrary per-stage speed recipe therefore works stage by stage (assuming a
stage's statistics depend mostly on its own speed); a stage whose equivalent
speed lies outside the speeds it was trained on is reported by
:meth:`StageSurrogate.domain_excess`.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np

from msmill.errors import MsmillInputError
from msmill.stageparams import RunStatistics
from msmill.surrogate.gp import SurrogateGP
from msmill.surrogate.space import INPUTS, DesignSpace
from msmill.surrogate.targets import N_LEVELS, StagePrediction, TrainingSet, decode_stage

#: A point is *thin in data* when the surrogate's posterior spread there exceeds this quantile of the
#: spreads its training runs have with themselves left out: farther from the other runs than 90 % of
#: the runs are from theirs (docs/surrogate.md, "Where the data are thin").
THIN_DATA_QUANTILE = 0.9


@dataclass(frozen=True)
class DataSupport:
    """How well the training runs cover query points (:meth:`StageSurrogate.data_support`).

    Attributes
    ----------
    spread_ratio : ndarray (N,)
        Posterior sd of the mean over the prior sd (median over targets) at each point.
    threshold : float
        The :data:`THIN_DATA_QUANTILE` quantile of the same ratio at the training runs, each left out.
    thin : ndarray (N,) of bool
        ``spread_ratio > threshold``.
    nearest_run : ndarray (N,) of int
        Index of the nearest training run (unit-cube distance, size in ln).
    nearest_distance : ndarray (N,)
        Its distance in the unit cube of the design space (0-2: the cube's diagonal is 2).
    """

    spread_ratio: np.ndarray
    threshold: float
    thin: np.ndarray
    nearest_run: np.ndarray
    nearest_distance: np.ndarray


#: where a surrogate's providers take filling curves from (:attr:`StageSurrogate.filling_curves`)
FILLING_CURVES = (None, "table")


class StageSurrogate:
    """Gaussian-process surrogate of per-stage DEM statistics over the design space.

    Parameters
    ----------
    design_space : DesignSpace, optional
        Input bounds for scaling (default paper Table 2).
    n_restarts : int
        GP optimiser restarts per target.
    random_state : int
        Seed of the restarts.
    filling_curves : {None, "table"}
        Where a provider built on this surrogate takes the filling curves (``StageParameters.filling_*``)
        from: None, the training runs' own (none when they carry none); ``"table"``, the packaged
        single-point DEM table's, for runs that start from a filled mill and so never measure filling.
        Saved in the surrogate file (:mod:`msmill.surrogate.persist`).
    n_levels : int
        Quantile levels per velocity distribution (:data:`msmill.surrogate.targets.SIGMA_FACTORS` lists
        the supported ones; default 28): more levels lower the representation's own KL floor and add
        GP targets. Saved in the file's target layout.

    Attributes (after :meth:`fit`)
    ------------------------------
    training_ : TrainingSet
    gp_ : SurrogateGP
    domain_ : ndarray (4, 2)
        Smallest and largest training value of every input.
    """

    def __init__(self, design_space: DesignSpace | None = None, n_restarts: int = 2,
                 random_state: int = 0, filling_curves: str | None = None, n_levels: int = N_LEVELS) -> None:
        if filling_curves not in FILLING_CURVES:
            raise MsmillInputError("filling_curves", filling_curves, " or ".join(map(str, FILLING_CURVES)))
        self.design_space = design_space or DesignSpace()
        self.n_restarts = n_restarts
        self.random_state = random_state
        self.filling_curves = filling_curves
        self.n_levels = n_levels

    def fit(self, runs: TrainingSet | Iterable[RunStatistics],
            warm_start: list[dict[str, Any]] | None = None) -> StageSurrogate:
        """Encode the runs and fit the GPs; returns ``self``."""
        ts = runs if isinstance(runs, TrainingSet) else TrainingSet.from_runs(runs, self.n_levels)
        if ts.n_runs < 2:
            raise MsmillInputError("runs", ts.n_runs, "at least 2 runs to fit a surrogate")
        gp = SurrogateGP(self.design_space, n_restarts=self.n_restarts, warm_start=warm_start,
                         random_state=self.random_state)
        return self._set(ts, gp.fit(ts.X, ts.Y, ts.noise_var))

    def _set(self, ts: TrainingSet, gp: SurrogateGP) -> StageSurrogate:
        self.training_ = ts
        self.gp_ = gp
        self.domain_ = np.stack([ts.X.min(axis=0), ts.X.max(axis=0)], axis=1)
        return self

    @property
    def n_stages(self) -> int:
        """Number of stages."""
        return self.training_.layout.n_stages

    @property
    def speed_factors(self) -> np.ndarray:
        """Stage speed / upper-stage speed of the training recipe."""
        return self.training_.speed_factors

    # ------------------------------------------------------------------ inputs
    def stage_inputs(self, sizes_mm, stage_speeds_rpm, feed_tph: float, gate_deg: float) -> np.ndarray:
        """Design points of every (stage, size): shape (S, N, 4); see the module docstring."""
        sizes = np.atleast_1d(np.asarray(sizes_mm, dtype=float))
        speeds = np.asarray(stage_speeds_rpm, dtype=float)
        if speeds.shape != (self.n_stages,):
            raise MsmillInputError("stage_speeds_rpm", list(speeds), f"{self.n_stages} speeds (one per stage)")
        equiv = speeds / self.speed_factors
        X = np.empty((self.n_stages, sizes.size, 4))
        X[..., 0] = sizes
        X[..., 1] = feed_tph
        X[..., 2] = equiv[:, None]
        X[..., 3] = gate_deg
        return X

    def domain_excess(self, X: np.ndarray) -> np.ndarray:
        """How far points (..., 4) lie outside the training domain, per input (>= 0).

        Size in multiples (``ratio - 1`` beyond the nearest trained size), the
        other inputs in their own units.
        """
        X = np.asarray(X, dtype=float)
        lo, hi = self.domain_[:, 0], self.domain_[:, 1]
        ex = np.maximum(lo - X, 0.0) + np.maximum(X - hi, 0.0)
        ex[..., 0] = np.maximum(lo[0] / X[..., 0], X[..., 0] / hi[0]) - 1.0
        return np.maximum(ex, 0.0)

    def data_support(self, X: np.ndarray) -> DataSupport:
        """How well the training runs cover design points ``X`` (N, 4) (physical units).

        The posterior spread is the GP's own measure of distance to data: it grows with the distance to
        the training runs in units of the fitted length scales. It is compared with the spread each
        training run would have without itself (closed-form leave-one-out, computed once per surrogate).
        """
        X = np.atleast_2d(np.asarray(X, dtype=float))
        loo = self.__dict__.get("_loo_spread")
        if loo is None:
            loo = self.__dict__["_loo_spread"] = self.gp_.loo_spread_ratio()
        ratio = self.gp_.spread_ratio(X)
        thr = float(np.quantile(loo, THIN_DATA_QUANTILE))
        u, ut = self.design_space.to_unit(X), self.design_space.to_unit(self.training_.X)
        d = np.sqrt(np.sum((u[:, None, :] - ut[None, :, :]) ** 2, axis=-1))
        near = np.argmin(d, axis=1)
        return DataSupport(ratio, thr, ratio > thr, near, d[np.arange(len(X)), near])

    # ------------------------------------------------------------------ predicting
    def _outputs(self, stage: int) -> np.ndarray:
        return np.flatnonzero(self.training_.layout.stage_of == stage)

    def predict_targets(self, X_stage: np.ndarray, return_std: bool = False):
        """Targets of every stage at its own points ``X_stage`` (S, N, 4).

        Returns
        -------
        mean : ndarray (S, N, T)
            Full target rows (each stage's own columns filled; others NaN;
            the run-level time predicted at stage 1's points).
        std : ndarray (S, N, T), if ``return_std``
        """
        S, N = X_stage.shape[:2]
        T = self.training_.layout.n_targets
        mean = np.full((S, N, T), np.nan)
        std = np.full((S, N, T), np.nan)
        for s in range(S):
            idx = self._outputs(s + 1)
            if s == 0:
                idx = np.concatenate([idx, self._outputs(0)])
            r = self.gp_.predict(X_stage[s], return_std=return_std, outputs=idx)
            m, sd = r if return_std else (r, None)
            mean[s][:, idx] = m
            if return_std:
                std[s][:, idx] = sd
        return (mean, std) if return_std else mean

    def sample_targets(self, X_stage: np.ndarray, n_samples: int, rng=None) -> np.ndarray:
        """Posterior samples of the target rows: shape (n_samples, S, N, T) (see :meth:`predict_targets`)."""
        rng = np.random.default_rng(rng)
        S, N = X_stage.shape[:2]
        out = np.full((n_samples, S, N, self.training_.layout.n_targets), np.nan)
        for s in range(S):
            idx = self._outputs(s + 1)
            if s == 0:
                idx = np.concatenate([idx, self._outputs(0)])
            out[:, s][..., idx] = self.gp_.sample(X_stage[s], n_samples, outputs=idx, rng=rng)
        return out

    def decode(self, Y_stage: np.ndarray) -> list[StagePrediction]:
        """Decode target rows (S, N, T) into one :class:`StagePrediction` per stage."""
        return [decode_stage(Y_stage[s], self.training_.layout, s + 1) for s in range(Y_stage.shape[0])]

    def characteristic_time_s(self, Y_stage: np.ndarray) -> float:
        """Model time step from predicted rows (mean of ``exp`` of the run-level target over sizes)."""
        return float(np.mean(np.exp(Y_stage[0, :, -1])))

    def __repr__(self) -> str:
        if not hasattr(self, "training_"):
            return "StageSurrogate(unfitted)"
        d = self.domain_
        rng = ", ".join(f"{n} {lo:g}-{hi:g}" for n, (lo, hi) in zip(INPUTS, d, strict=True))
        return f"StageSurrogate({self.training_.n_runs} runs, {self.training_.layout.n_targets} targets; {rng})"
