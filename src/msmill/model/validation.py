"""Predict a set of surveys and compare with the measured products (paper Section 4, Figs. 11-13).

The metric is the two-sample Kolmogorov-Smirnov statistic of domain notes
Section 8: the largest absolute difference between the measured and predicted
cumulative passing curves, both read (log-size interpolation) on the union of
their sieve sizes, as a fraction (0 = identical curves, 1 = disjoint).
:func:`measured_ks` reads it only at sizes at or above the finest measured
sieve: below it the measured curve is unknown (the pan), and
:func:`msmill.psd.ks_statistic`'s reading convention (0 % one sieve step below
the finest sieve) would add ~0.01 even for a perfect prediction.

:class:`SurveyModel` is the fast path shared with calibration: the stage
parameters, streams and impact statistics of every distinct operating point
are computed once; the linear system is assembled once per (operating point,
breakage parameters), so surveys at one point share it, and each survey costs
one sparse solve.
"""

from __future__ import annotations

import dataclasses
import warnings
from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd

from msmill.errors import OutOfDomainWarning
from msmill.model import submodels as sm
from msmill.model.expected_value import assemble
from msmill.model.mill import DEFAULT_MIN_SIZE_MM, Mill, _single_threaded_blas, breakage_parameters
from msmill.model.providers import load_provider
from msmill.psd import PSD, SizeGrid

__all__ = ["SurveyModel", "ValidationResult", "design_space_flags", "measured_ks", "model_grid_for",
           "validate"]


def measured_ks(measured: PSD, predicted: PSD) -> float:
    """K-S statistic (fraction) on the union of both sieve sets, at sizes >= the finest measured sieve.

    Parameters
    ----------
    measured : PSD
        Measured distribution (its grid's ``edges_mm[1:]`` are the sieves).
    predicted : PSD
        Predicted distribution (any grid).
    """
    sizes = np.union1d(measured.sizes_mm, predicted.sizes_mm)
    sizes = sizes[sizes >= measured.sizes_mm[0] * (1 - 1e-12)]
    d = np.abs(np.asarray(measured.passing_at(sizes)) - np.asarray(predicted.passing_at(sizes)))
    return float(np.clip(d.max() / 100.0, 0.0, 1.0))


def model_grid_for(experiments: list[Any]) -> SizeGrid:
    """One model grid for a set of surveys: sqrt(2) series from 0.038 mm to the largest feed top."""
    top = max(float(e.feed_psd.grid.edges_mm[-1]) for e in experiments)
    return SizeGrid.geometric(DEFAULT_MIN_SIZE_MM, max(top, 2 * DEFAULT_MIN_SIZE_MM))


def design_space_flags(exp: Any) -> str:
    """Where a survey lies outside the surrogate's design space (domain notes Sec. 1), by how much.

    Returns an empty string inside. Checks feed rate, gate angle, upper-stage
    speed and the feed's P80 against ``msmill.machine.DESIGN_SPACE``.
    """
    from msmill.machine import DESIGN_SPACE

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", OutOfDomainWarning)
        op = exp.operating_point()
    vals = {"feed_tph": op.feed_tph, "gate_deg": op.gate_deg, "speed_rpm": op.upper_speed_rpm,
            "size_mm": exp.feed_psd.p80_mm}
    out = []
    for name, v in vals.items():
        lo, hi = DESIGN_SPACE[name]
        if v < lo:
            out.append(f"{name} {v:.3g} below {lo:g} by {lo - v:.3g}")
        elif v > hi:
            out.append(f"{name} {v:.3g} above {hi:g} by {v - hi:.3g}")
    return "; ".join(out)


def _op_key(op: Any, n_stages: int) -> tuple:
    return (tuple(op.stage_speeds(n_stages)), float(op.feed_tph), float(op.gate_deg))


class SurveyModel:
    """Steady-state products of many surveys of one ore, with operators shared per operating point.

    Parameters
    ----------
    ore : str or Ore or BreakageParameters
        Ore (start values of calibrated parameters).
    surveys : list of Experiment
        Surveys (``kind = "survey"``) of this ore.
    stage_parameters : provider or path
        Stage-parameter source (default: the packaged DEM table).
    grid : SizeGrid, optional
        Model grid (default :func:`model_grid_for`).
    **mill_options
        Sub-model choices and expected-value options of :class:`msmill.model.Mill`
        (``transport``, ``impacts``, ``breakage``, ``damage``, ``impacted``,
        ``damage_classes``, ``quadrature_nodes``).
    """

    def __init__(self, ore: Any, surveys: list[Any], stage_parameters: Any = "default",
                 grid: SizeGrid | None = None, **mill_options: Any) -> None:
        self.surveys = list(surveys)
        self.grid = grid or model_grid_for(self.surveys)
        provider = load_provider(stage_parameters) if isinstance(stage_parameters, str) else stage_parameters
        self.provider = provider
        self._mill_options = dict(mill_options)
        # the K-S and the fit use the posterior-mean prediction: no uncertainty band per solve
        self.mill = Mill(ore, provider, grid=self.grid, solver="expected_value",
                         **{"band_samples": 0, **mill_options})
        self.ore = self.mill.ore
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", OutOfDomainWarning)
            self.ops = [e.operating_point() for e in self.surveys]
        n = self.mill.provider.n_stages
        self.keys = [_op_key(op, n) for op in self.ops]
        self.feeds = np.stack([e.feed_psd.rebin(self.grid).fractions for e in self.surveys])
        self._stage: dict[tuple, tuple] = {}
        self.warnings: dict[tuple, list[str]] = {}

    @property
    def n_points(self) -> int:
        """Number of distinct operating points."""
        return len(set(self.keys))

    def _stage_stats(self, key: tuple, op: Any) -> tuple:
        hit = self._stage.get(key)
        if hit is None:
            m = self.mill
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                params = m.provider.stage_parameters(self.grid.mids_mm, list(key[0]), op.feed_tph, op.gate_deg)
            streams = sm.transition_of(m.transport, params)
            stats = sm.without_stopped_rotors(m.impacts.impacts(params, np.asarray(key[0], dtype=float)),
                                              np.asarray(key[0], dtype=float))
            hit = (params, streams, stats)
            self._stage[key] = hit
            self.warnings[key] = [str(w.message) for w in caught]
        return hit

    def submodels_for(self, ore: sm.BreakageParameters, breakage: Any = None) -> tuple[Any, Any]:
        """Breakage and damage sub-models for ore parameters ``ore`` (same names as the mill's)."""
        names = self.mill.submodel_names()
        brk = breakage if breakage is not None else sm.resolve("breakage", names["breakage"], ore)
        dmg = sm.resolve("damage", names["damage"], ore)
        return brk, dmg

    def products(self, ore: sm.BreakageParameters | None = None, breakage: Any = None) -> np.ndarray:
        """Product mass fractions (n_surveys, N) on :attr:`grid` for ore parameters ``ore``.

        ``breakage`` (an object) overrides the breakage sub-model built from ``ore``.
        """
        ore = ore or self.ore
        brk, dmg = self.submodels_for(ore, breakage)
        out = np.zeros_like(self.feeds)
        m = self.mill
        with _single_threaded_blas():
            for key in dict.fromkeys(self.keys):
                idx = [i for i, k in enumerate(self.keys) if k == key]
                _params, streams, stats = self._stage_stats(key, self.ops[idx[0]])
                lm = assemble(self.grid.edges_mm, streams, stats, brk, dmg, m.damage_classes,
                              m.quadrature_nodes, m.impacted)
                for i in idx:
                    x = lm.steady_state(lm.feed_vector(self.feeds[i], 1.0))
                    p = np.clip(np.asarray(lm.out_op @ x), 0.0, None)
                    out[i] = p / p.sum()
        return out

    def ks(self, products: np.ndarray) -> np.ndarray:
        """K-S statistic of every survey's measured product against ``products`` (fractions)."""
        return np.array([measured_ks(e.product_psd, PSD(self.grid, products[i], validate=False))
                         for i, e in enumerate(self.surveys)])

    def with_provider(self, provider: Any) -> SurveyModel:
        """The same surveys, grid, ore parameters and sub-models with another stage-parameter provider."""
        return SurveyModel(self.ore, self.surveys, provider, grid=self.grid, **self._mill_options)

    def with_ore(self, **changes: Any) -> sm.BreakageParameters:
        """The ore parameters with some fields replaced (``l_ref_mm``, ``A_pct``, ``gamma`` ...)."""
        return dataclasses.replace(self.ore, **changes)


@dataclass(frozen=True)
class ValidationResult:
    """Outcome of :func:`validate`.

    Attributes
    ----------
    table : pandas.DataFrame
        One row per survey: ``id, ore, ks, p80_measured_mm, p80_predicted_mm,
        feed_tph, speed_rpm, gate_deg, impact_kw, measured_power_kw,
        outside_design_space, domain_notes, source``.
    summary : pandas.DataFrame
        Per ore: ``ore, n, ks_mean, ks_median, ks_min, ks_max, best_id, worst_id``.
    measured, predicted : dict[str, PSD]
        Measured product and predicted product per survey id.
    results : dict[str, MillResult]
        Full predictions per survey id.
    """

    table: pd.DataFrame
    summary: pd.DataFrame
    measured: dict[str, PSD]
    predicted: dict[str, PSD]
    results: dict[str, Any]


def validate(experiments: Any, stage_parameters: Any = "default", ores: dict[str, Any] | None = None,
             **mill_options: Any) -> ValidationResult:
    """Predict every survey and compute its K-S statistic against the measured product.

    Parameters
    ----------
    experiments : ExperimentSet or list of Experiment
        Surveys (single-impact tests are ignored here).
    stage_parameters : provider or path
        Stage-parameter source (default: the packaged DEM table).
    ores : dict, optional
        Ore (name, ``Ore`` or ``BreakageParameters``) to use per ore name of the
        surveys, e.g. calibrated ones; default the registry's.
    **mill_options
        Sub-model and solver options of :class:`msmill.model.Mill`.
    """
    from msmill.model.power import power_estimate

    surveys = [e for e in getattr(experiments, "experiments", experiments) if e.kind == "survey"]
    if not surveys:
        from msmill.errors import MsmillInputError

        raise MsmillInputError("experiments", 0, "at least one survey (kind = 'survey')")
    grid = model_grid_for(surveys)
    provider = load_provider(stage_parameters) if isinstance(stage_parameters, str) else stage_parameters
    rows, measured, predicted, results = [], {}, {}, {}
    mills: dict[str, Mill] = {}
    for e in surveys:
        if e.ore not in mills:
            ore = breakage_parameters((ores or {}).get(e.ore, e.ore))
            mills[e.ore] = Mill(ore, provider, grid=grid, **{"band_samples": 0, **mill_options})  # K-S of the mean
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            res = mills[e.ore].run(e.feed_psd, e.operating_point(), timeseries=False, held_below=False)
        ks = measured_ks(e.product_psd, res.product_psd)
        pw = power_estimate(res)
        op = e.operating_point
        flags = design_space_flags(e)
        notes = [flags] if flags else []
        notes += sorted({str(w.message) for w in caught if issubclass(w.category, OutOfDomainWarning)
                         and "design space" not in str(w.message)})
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            o = op()
        rows.append({"id": e.id, "ore": e.ore, "ks": ks, "p80_measured_mm": e.product_psd.p80_mm,
                     "p80_predicted_mm": res.p80_mm, "feed_tph": e.feed_tph, "speed_rpm": o.upper_speed_rpm,
                     "gate_deg": o.gate_deg, "impact_kw": pw.impact_kw,
                     "measured_power_kw": e.power_kw if e.power_kw is not None else np.nan,
                     "outside_design_space": bool(flags), "domain_notes": " | ".join(notes),
                     "source": e.source})
        measured[e.id], predicted[e.id], results[e.id] = e.product_psd, res.product_psd, res
    table = pd.DataFrame(rows)
    return ValidationResult(table, summarise(table), measured, predicted, results)


def summarise(table: pd.DataFrame) -> pd.DataFrame:
    """Per-ore K-S summary of a validation table (best = smallest K-S)."""
    out = []
    for ore, g in table.groupby("ore", sort=False):
        out.append({"ore": ore, "n": len(g), "ks_mean": g["ks"].mean(), "ks_median": g["ks"].median(),
                    "ks_min": g["ks"].min(), "ks_max": g["ks"].max(),
                    "best_id": g.loc[g["ks"].idxmin(), "id"], "worst_id": g.loc[g["ks"].idxmax(), "id"],
                    "n_outside_design_space": int(g["outside_design_space"].sum())})
    return pd.DataFrame(out)
