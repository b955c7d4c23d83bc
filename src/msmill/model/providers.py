"""Stage-parameter providers: where the mill model gets its DEM statistics.

A provider answers one question: for every stage and every size class of the
model's grid, what are the transport streams and the primary / secondary
impact statistics? It implements the small :class:`StageParameterProvider`
protocol, so the Gaussian-process surrogate can be added later as one more
provider.

Providers shipped here
----------------------
:class:`TableProvider`
    A :class:`msmill.stageparams.StageParameterTable` (runs at one operating
    point, several rock sizes) read from JSON, or the simple TOML / CSV table
    format defined in :func:`read_simple_table`. Values are interpolated
    linearly in ``ln(size)`` between runs; velocity mixtures are interpolated
    as a mixture of the two neighbouring mixtures (weights ``1 - w`` and
    ``w``), which keeps every interpolated distribution valid; secondary-impact
    count distributions (Poisson mixtures) are interpolated the same way.
:class:`RunProvider`
    The statistics of one DEM run (:class:`msmill.stageparams.RunStatistics`),
    applied to every size.

Sizes outside the sizes covered are extrapolated (a table: the end run's
values continued along the table's least-squares trend in ``ln(size)``, up to
:data:`EXTRAPOLATION_SPANS` times the covered span, then held; one run:
clamped) and flagged in ``StageParameters.extrapolated``; the mill result
reports the share of feed and product mass concerned (no warning). An
operating point that differs from the one the statistics were measured at
warns.
"""

from __future__ import annotations

import csv
import dataclasses
import warnings
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from msmill.errors import MsmillInputError, OutOfDomainWarning, SummaryNote, from_validation_error
from msmill.providers_base import (
    CountArrays,
    MixtureArrays,
    StageParameterProvider,
    StageParameters,
)
from msmill.stageparams import (
    CountDistribution,
    FillingTransport,
    RunStatistics,
    StageParameterTable,
    StageStatistics,
)
from msmill.validate import existing_file, read_text, read_toml

__all__ = [
    "RunProvider",
    "StageParameterProvider",
    "TableProvider",
    "WithFillingCurves",
    "load_provider",
    "machine_mismatch",
    "named_parameter_path",
    "read_simple_table",
    "sense_surrogate_path",
]

_REL_TOL = 0.01  # relative difference of an operating value that triggers a warning
#: Impact velocities above this (m/s, mean or spread of a mixture component) are
#: implausible for an impact mill (bottom-stage tip speed at 3800 rpm is ~75 m/s)
#: and are reported with a warning.
PLAUSIBLE_VELOCITY_M_S = 300.0


def _check_operating_point(design, stage_speeds_rpm, feed_tph, gate_deg, source: str) -> None:
    diffs = []
    if stage_speeds_rpm is not None:
        a = np.asarray(stage_speeds_rpm, dtype=float)
        b = np.asarray(design.stage_speeds_rpm, dtype=float)
        if a.shape != b.shape or np.any(np.abs(a - b) > _REL_TOL * np.maximum(b, 1.0)):
            diffs.append(f"stage speeds {np.round(a, 1).tolist()} rpm vs {np.round(b, 1).tolist()} rpm")
    if feed_tph is not None and abs(feed_tph - design.feed_tph) > _REL_TOL * design.feed_tph:
        diffs.append(f"feed {feed_tph:g} t/h vs {design.feed_tph:g} t/h")
    if gate_deg is not None and abs(gate_deg - design.gate_deg) > 0.5:
        diffs.append(f"gate {gate_deg:g} deg vs {design.gate_deg:g} deg")
    if diffs:
        warnings.warn(
            f"stage parameters from {source} were measured at another operating point ("
            + "; ".join(diffs) + ")", OutOfDomainWarning, stacklevel=3)


def _mixture_rows(stats: list[StageStatistics], attr: str) -> tuple[np.ndarray, ...]:
    k = max(getattr(s, attr).n_components for s in stats)
    w = np.zeros((len(stats), k))
    m = np.zeros((len(stats), k))
    sd = np.ones((len(stats), k))
    for i, s in enumerate(stats):
        g = getattr(s, attr)
        n = g.n_components
        w[i, :n], m[i, :n], sd[i, :n] = g.weights, g.means_m_s, g.sigmas_m_s
    return w, m, sd


def _check_velocities(runs: list[RunStatistics], source: str) -> None:
    bad = []
    for r in runs:
        for st in r.stages:
            for kind in ("primary_velocity", "secondary_velocity"):
                g = getattr(st, kind)
                w = np.asarray(g.weights)
                big = (np.abs(g.means_m_s) > PLAUSIBLE_VELOCITY_M_S) | (np.asarray(g.sigmas_m_s) > PLAUSIBLE_VELOCITY_M_S)
                if np.any(big & (w > 0)):
                    bad.append(f"{r.design.size_mm:g} mm stage {st.stage} {kind.split('_')[0]} "
                               f"(weight {w[big].sum():.2g})")
    if bad:
        warnings.warn(
            f"{source} has velocity-mixture components beyond {PLAUSIBLE_VELOCITY_M_S:g} m/s "
            f"({len(bad)} distributions, e.g. {'; '.join(bad[:3])}); check the fits",
            OutOfDomainWarning, stacklevel=4)


def _run_arrays(runs: list[RunStatistics]) -> dict[str, Any]:
    """Stack runs into arrays of shape (R, S, ...)."""
    n_s = runs[0].n_stages
    out: dict[str, Any] = {
        "streams": np.array([[s.streams for s in r.stages] for r in runs]),
        "hit": np.array([[s.primary_hit_probability for s in r.stages] for r in runs]),
        "lam": np.array([[s.secondary_lambda for s in r.stages] for r in runs]),
    }
    for attr, key in (("primary_velocity", "pv"), ("secondary_velocity", "sv")):
        k = max(getattr(s, attr).n_components for r in runs for s in r.stages)
        arr = np.zeros((3, len(runs), n_s, k))
        arr[2] = 1.0
        for i, r in enumerate(runs):
            w, m, sd = _mixture_rows(list(r.stages), attr)
            arr[0, i, :, : w.shape[1]] = w
            arr[1, i, :, : w.shape[1]] = m
            arr[2, i, :, : w.shape[1]] = sd
        out[key] = arr
    out["sc"] = _count_rows(runs)
    has_regions = all(s.region_weights is not None and s.region_streams is not None
                      for r in runs for s in r.stages)
    if has_regions:
        out["rw"] = np.array([[s.region_weights for s in r.stages] for r in runs])
        out["rs"] = np.array([[s.region_streams for s in r.stages] for r in runs])
    if all(r.inlet_destinations is not None and all(s.destinations is not None for s in r.stages) for r in runs):
        out["tr"] = np.array([[r.inlet_destinations] + [s.destinations for s in r.stages] for r in runs])
    return out


def _common_fills(curves: list[FillingTransport]) -> tuple[np.ndarray, np.ndarray]:
    """Fills (K,) and tagged masses (K,) of the fill bins (:data:`msmill.stageparams.FILLING_BINS`)
    that some curve has a point in: the curves' tag-mass-weighted mean fill there, and their summed mass."""
    from msmill.stageparams import FILLING_BINS

    h = np.concatenate([c.fill for c in curves])
    m = np.concatenate([c.tag_mass_kg for c in curves])
    b = np.searchsorted(FILLING_BINS, h, side="right") - 1
    bins = np.unique(b)
    return (np.array([np.average(h[b == k], weights=m[b == k]) for k in bins]),
            np.array([m[b == k].sum() for k in bins]))


def filling_curves(runs: list[RunStatistics]) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """The runs' filling curves (``filling_transport``) at common fills: fills (K,), ratios (R, K), weights (R,).

    One fill per fill bin that some run has a point in (:func:`_common_fills`); each run's
    curve (:meth:`~msmill.stageparams.FillingTransport.ratio_at`) at those fills; each run's
    tagged mass. None unless every run has a curve.
    """
    curves = [r.filling_transport for r in runs]
    if not curves or any(c is None for c in curves):
        return None
    fill, _ = _common_fills(curves)
    return fill, np.array([c.ratio_at(fill) for c in curves]), np.array([sum(c.tag_mass_kg) for c in curves])


def pool_filling_curves(curves: list[FillingTransport], reference: tuple[float, float] | None = None,
                        reference_lag_s: float | None = None) -> FillingTransport:
    """Several measurements of one point's filling curve (e.g. runs with other feed seeds) as one curve.

    Each run's curve is relative to its own window (fill over the window's mean hold-up,
    residence over the window chain's), and one short window measures those references to
    10-20 % for coarse rock. Curves that carry them (``window_holdup_kg``,
    ``window_residence_steps``) are first put on a common reference: ``reference``
    (``(holdup_kg, residence_steps)``, e.g. those of a long window at the same point,
    :meth:`RunStatistics.window_reference`, its steps of ``reference_lag_s``) or else the runs'
    mean of each: ``fill * holdup / common holdup``, ``ratio * residence / common residence``
    (points at or above the common steady hold-up are dropped); curves without them are taken
    as they are. Residences are compared in seconds: a curve's steps are of its own lag
    (``lag_s``; runs of one point can have different characteristic times), a curve or
    reference without a lag is taken to be on the common lag (``reference_lag_s``, else the
    curves' mean lag). Then the fills of :func:`_common_fills`, there the curves' ratios
    averaged with their tagged masses as weights, and the bins' summed tagged masses.
    """
    if not curves:
        raise ValueError("no filling curves to pool")
    if len(curves) == 1 and reference is None:
        return curves[0]
    has_ref = [c.window_holdup_kg is not None and c.window_residence_steps is not None for c in curves]
    lags = [c.lag_s for c, r in zip(curves, has_ref, strict=True) if r and c.lag_s is not None]
    lag = float(reference_lag_s) if reference_lag_s is not None else (float(np.mean(lags)) if lags else None)
    if lag is not None and not (lag > 0 and np.isfinite(lag)):
        raise ValueError(f"reference_lag_s: got {reference_lag_s}; allowed: a positive, finite lag (s)")

    def steps_on_lag(c: FillingTransport) -> float:  # the curve's window residence in steps of the common lag
        return c.window_residence_steps * (c.lag_s / lag if c.lag_s is not None and lag is not None else 1.0)

    if reference is not None:
        hold, res = map(float, reference)
        if not (hold > 0 and res > 0 and np.isfinite(hold) and np.isfinite(res)):
            raise ValueError(f"reference: got {reference}; allowed: a positive, finite (holdup_kg, residence_steps)")
    else:
        ref = [c for c, r in zip(curves, has_ref, strict=True) if r]
        hold = float(np.mean([c.window_holdup_kg for c in ref])) if ref else None
        res = float(np.mean([steps_on_lag(c) for c in ref])) if ref else None
    common = []
    for c, r in zip(curves, has_ref, strict=True):
        if not r:
            common.append(c)
            continue
        h = np.asarray(c.fill) * c.window_holdup_kg / hold
        keep = h < 1.0
        if not keep.any():
            continue
        common.append(FillingTransport(
            fill=h[keep].tolist(), residence_ratio=(np.asarray(c.residence_ratio)[keep] * steps_on_lag(c)
                                                    / res).tolist(),
            tag_mass_kg=np.asarray(c.tag_mass_kg)[keep].tolist()))
    if not common:
        raise ValueError("every filling point lies at or above the runs' mean steady hold-up")
    fill, mass = _common_fills(common)
    w = np.array([sum(c.tag_mass_kg) for c in common])
    ratio = np.average([c.ratio_at(fill) for c in common], axis=0, weights=w)
    return FillingTransport(fill=fill.tolist(), residence_ratio=ratio.tolist(), tag_mass_kg=mass.tolist(),
                            window_residence_steps=res, window_holdup_kg=hold, lag_s=lag)


def pooled_filling(runs: list[RunStatistics]) -> tuple[np.ndarray, np.ndarray] | None:
    """The runs' filling curves pooled into one: fills (K,) and residence ratios (K,).

    :func:`filling_curves` averaged over the runs, weighted by their tagged masses.
    None unless every run has a curve.
    """
    curves = filling_curves(runs)
    if curves is None:
        return None
    fill, ratios, w = curves
    return fill, np.average(ratios, axis=0, weights=w)


def _count_rows(runs: list[RunStatistics]) -> np.ndarray:
    """Secondary-count mixtures stacked as (2, R, S, C): weights, means (padding weight 0)."""
    counts = [[s.secondary_count or CountDistribution.poisson(s.secondary_lambda) for s in r.stages] for r in runs]
    c = max(d.n_components for row in counts for d in row)
    arr = np.zeros((2, len(runs), runs[0].n_stages, c))
    for i, row in enumerate(counts):
        for j, d in enumerate(row):
            arr[0, i, j, : d.n_components] = d.weights
            arr[1, i, j, : d.n_components] = d.means
    return arr


#: Extrapolation reach beyond the sizes covered, as a multiple of the covered ln-size span
#: (docs/model.md, "Sizes outside the stage statistics"): a table covering 6-30 mm extrapolates
#: its trends down to 1.2 mm and up to 150 mm, and holds the values reached there beyond.
EXTRAPOLATION_SPANS = 1.0


def _trend_slope(xr: np.ndarray, arr: np.ndarray) -> np.ndarray:
    """Least-squares slope of ``arr`` (R, ...) against ``xr`` (R,) over all runs (per element)."""
    dx = xr - xr.mean()
    shape = (-1,) + (1,) * (arr.ndim - 1)
    return np.sum(dx.reshape(shape) * (arr - arr.mean(axis=0)), axis=0) / np.sum(dx * dx)


class _SizeInterpolation:
    """Linear interpolation in ln(size) between a table's neighbouring runs, with its trend outside them.

    Outside the sizes covered: the end run's value plus the table's ln-size trend (least squares over
    all runs) times the distance, the distance capped at ``EXTRAPOLATION_SPANS`` x the covered span.
    """

    def __init__(self, run_sizes_mm: np.ndarray, sizes_mm: np.ndarray) -> None:
        lo, hi = run_sizes_mm[0], run_sizes_mm[-1]
        self.outside = (sizes_mm < lo * (1 - 1e-9)) | (sizes_mm > hi * (1 + 1e-9))
        x = np.log(np.clip(sizes_mm, lo, hi))
        self.xr = xr = np.log(run_sizes_mm)
        self.n_runs = len(run_sizes_mm)
        reach = EXTRAPOLATION_SPANS * (xr[-1] - xr[0])
        x_out = np.clip(np.log(sizes_mm), xr[0] - reach, xr[-1] + reach)
        self.dx_out = np.where(self.outside, x_out - x, 0.0)  # 0 inside; one run: reach 0, i.e. clamped
        if self.n_runs == 1:
            self.j = np.zeros(sizes_mm.size, dtype=int)
            self.w = np.zeros(sizes_mm.size)
            self.j1 = self.j
        else:
            self.j = np.clip(np.searchsorted(xr, x, side="right") - 1, 0, self.n_runs - 2)
            self.w = np.clip((x - xr[self.j]) / (xr[self.j + 1] - xr[self.j]), 0.0, 1.0)
            self.j1 = self.j + 1

    @property
    def _trended(self) -> bool:
        return self.n_runs > 1 and bool(np.any(self.outside))

    def lin(self, arr: np.ndarray) -> np.ndarray:
        """``arr`` (R, S, ...) of the runs at the sizes: (S, N, ...)."""
        a0 = np.moveaxis(arr[self.j], 0, 1)
        a1 = np.moveaxis(arr[self.j1], 0, 1)
        ww = self.w.reshape((1, -1) + (1,) * (a0.ndim - 2))
        out = (1 - ww) * a0 + ww * a1
        if self._trended:
            slope = _trend_slope(self.xr, arr)[:, None]  # (S, 1, ...)
            out = out + slope * self.dx_out.reshape((1, -1) + (1,) * (a0.ndim - 2))
        return out

    def shares(self, arr: np.ndarray) -> np.ndarray:
        """:meth:`lin` of shares (last axis sums to 1), clipped at 0 and renormalised."""
        out = np.maximum(self.lin(arr), 0.0)
        out /= out.sum(axis=-1, keepdims=True)
        return out

    def mix(self, arr: np.ndarray) -> MixtureArrays:
        """Velocity mixtures ``arr`` (3, R, S, K): the neighbours' components with weights (1-w), w."""
        w = self.w
        p0 = np.moveaxis(arr[:, self.j], 1, 2)  # (3, S, N, K)
        p1 = np.moveaxis(arr[:, self.j1], 1, 2)
        ww = w[None, :, None]
        weights = np.concatenate([p0[0] * (1 - ww), p1[0] * ww], axis=-1)
        means = np.concatenate([p0[1], p1[1]], axis=-1)
        sig = np.concatenate([p0[2], p1[2]], axis=-1)
        if self._trended:
            # velocities scale with the trend of ln(mean velocity) in ln(size)
            ln_mean = np.log(np.maximum(np.sum(arr[0] * arr[1], axis=-1), 1e-6))  # (R, S)
            f = np.exp(_trend_slope(self.xr, ln_mean)[:, None, None] * self.dx_out[None, :, None])
            means, sig = means * f, sig * f
        return MixtureArrays(weights, means, sig)

    def count_mix(self, arr: np.ndarray, lam: np.ndarray) -> CountArrays:
        """Secondary-count pmfs ``arr`` (2, R, S, C) as the (1-w, w) mixture of the neighbours' pmfs.

        Its mean is the interpolated ``lam``; outside the sizes covered the end run's shape is
        kept and its means scaled to the extrapolated ``lam``.
        """
        p0 = np.moveaxis(arr[:, self.j], 1, 2)  # (2, S, N, C)
        p1 = np.moveaxis(arr[:, self.j1], 1, 2)
        ww = self.w[None, :, None]
        cw = np.concatenate([p0[0] * (1 - ww), p1[0] * ww], axis=-1)
        cm = np.concatenate([p0[1], p1[1]], axis=-1)
        own = np.sum(cw * cm, axis=-1)
        scale = np.where(self.outside[None, :] & (own > 0), lam / np.where(own > 0, own, 1.0), 1.0)
        return CountArrays(cw, cm * scale[..., None])


def _interpolate(runs: list[RunStatistics], sizes_mm: np.ndarray, source: str) -> StageParameters:
    sizes = np.asarray(sizes_mm, dtype=float)
    a = _run_arrays(runs)
    _check_velocities(runs, source)
    ip = _SizeInterpolation(np.array([r.design.size_mm for r in runs]), sizes)
    j, j1, w = ip.j, ip.j1, ip.w
    rw = rs = tr = None
    if "rw" in a:
        rw, rs = ip.shares(a["rw"]), ip.shares(a["rs"])
    if "tr" in a:
        tr = ip.shares(a["tr"])
    times = np.array([r.characteristic_time_s for r in runs])
    if np.ptp(times) > _REL_TOL * times.mean():
        warnings.warn(f"characteristic times of {source} differ ({times.min():g}-{times.max():g} s); "
                      f"using their mean {times.mean():g} s as the time step", SummaryNote,
                      stacklevel=3)
    d = runs[0].design
    lam = np.maximum(ip.lin(a["lam"]), 0.0)
    filling = filling_curves(runs)
    if filling is not None:  # per class, between the neighbouring runs in log size; held outside them
        ww = w[:, None]
        filling = filling[0], (1 - ww) * filling[1][j] + ww * filling[1][j1]
    return StageParameters(
        sizes_mm=sizes.copy(),
        characteristic_time_s=float(times.mean()),
        streams=ip.shares(a["streams"]),
        hit_probability=np.clip(ip.lin(a["hit"]), 0.0, 1.0),
        primary_velocity=ip.mix(a["pv"]),
        secondary_lambda=lam,
        secondary_velocity=ip.mix(a["sv"]),
        design_stage_speeds_rpm=np.asarray(d.stage_speeds_rpm, dtype=float),
        design_feed_tph=d.feed_tph,
        design_gate_deg=d.gate_deg,
        region_weights=rw,
        region_streams=rs,
        source=source,
        secondary_count=ip.count_mix(a["sc"], lam),
        transition=tr,
        extrapolated=ip.outside,
        transition_lag_s=None if tr is None else (1 - w) * times[j] + w * times[j1],
        filling_fill=None if filling is None else filling[0],
        filling_residence_ratio=None if filling is None else filling[1],
    )


class TableProvider:
    """Stage parameters from a :class:`~msmill.stageparams.StageParameterTable`.

    Parameters
    ----------
    table : StageParameterTable
        Runs at one operating point, ascending rock size.
    source : str, optional
        Description used in warnings (e.g. the file name).
    """

    def __init__(self, table: StageParameterTable, source: str = "stage-parameter table") -> None:
        self.table = table
        self.source = source

    @property
    def n_stages(self) -> int:
        """Number of stages of the table's runs."""
        return self.table.runs[0].n_stages

    @property
    def covered_sizes_mm(self) -> tuple[float, float]:
        """Smallest and largest rock size (mm) of the table's runs."""
        sizes = [r.design.size_mm for r in self.table.runs]
        return float(min(sizes)), float(max(sizes))

    @classmethod
    def from_file(cls, path: str | Path) -> TableProvider:
        """Read a JSON table, or the simple ``.toml`` / ``.csv`` format (:func:`read_simple_table`)."""
        p = existing_file(path, "stage_parameters", "stage-parameter table file")
        if p.suffix.lower() in (".toml", ".csv"):
            return cls(read_simple_table(p), source=p.name)
        return cls(StageParameterTable.from_json(p), source=p.name)

    def stage_parameters(self, sizes_mm, stage_speeds_rpm=None, feed_tph=None, gate_deg=None):
        """Parameters at ``sizes_mm`` (mm), interpolated in log size; see the module docstring."""
        _check_operating_point(self.table.runs[0].design, stage_speeds_rpm, feed_tph, gate_deg,
                               self.source)
        return _interpolate(list(self.table.runs), sizes_mm, self.source)

    def __repr__(self) -> str:
        s = self.table.sizes_mm
        return f"TableProvider({self.source}, {len(s)} runs, {s[0]:g}-{s[-1]:g} mm)"


class RunProvider:
    """Stage parameters from the statistics of one DEM run (one rock size).

    Parameters
    ----------
    run : RunStatistics
        The run's statistics.
    source : str, optional
        Description used in warnings.
    """

    def __init__(self, run: RunStatistics, source: str = "DEM run") -> None:
        self.run = run
        self.source = source

    @property
    def n_stages(self) -> int:
        """Number of stages of the run."""
        return self.run.n_stages

    @classmethod
    def from_file(cls, path: str | Path) -> RunProvider:
        """Read a :class:`RunStatistics` JSON file."""
        p = existing_file(path, "stage_parameters", "run-statistics file")
        return cls(RunStatistics.from_json(p), source=p.name)

    def stage_parameters(self, sizes_mm, stage_speeds_rpm=None, feed_tph=None, gate_deg=None):
        """The run's parameters at every size (other sizes are clamped and flagged as extrapolated)."""
        _check_operating_point(self.run.design, stage_speeds_rpm, feed_tph, gate_deg, self.source)
        return _interpolate([self.run], sizes_mm, self.source)

    def __repr__(self) -> str:
        return f"RunProvider({self.source}, {self.run.design.size_mm:g} mm)"


DEFAULT_TABLE = "default"


def default_table_path(field: str = "stage_parameters") -> Path:
    """Path of the packaged DEM-derived table (``msmill/data/stage_parameters/default.json``)."""
    from importlib import resources

    p = Path(str(resources.files("msmill").joinpath("data/stage_parameters/default.json")))
    if not p.is_file():
        raise MsmillInputError(field, DEFAULT_TABLE, "a table file: the packaged DEM-derived default "
                               "table (msmill/data/stage_parameters/default.json) is not installed")
    return p


#: name of the packaged single-point DEM table (``"default"`` is the shipped surrogate when installed)
TABLE_NAME = "table"


class _Wrapper:
    """A provider that passes another's stage parameters on, changed (its ``provider``)."""

    provider: Any

    @property
    def n_stages(self) -> int:
        """Number of stages (the provider's)."""
        return self.provider.n_stages

    @property
    def velocities_at_requested_speeds(self) -> bool:
        return bool(getattr(self.provider, "velocities_at_requested_speeds", False))


class WithFillingCurves(_Wrapper):
    """A provider whose stage parameters take their filling curves from another provider (a table's).

    The filling curves (``StageParameters.filling_*``, the ``dem_matrix_fill``
    transport) come from DEM runs that start empty; campaign runs start from a
    filled mill (``RunSettings.start = "table"``) and carry none, so a surrogate
    trained on them has none. This wrapper gives such a provider the curves of
    ``filling`` at the same sizes (one rule: the curves are shares of the steady
    hold-up and residence, not absolute figures, so they are taken as they are at
    any operating point) and passes everything else through.

    Parameters
    ----------
    provider : StageParameterProvider
        The provider of every other stage parameter (e.g. the surrogate).
    filling : StageParameterProvider
        The provider of the filling curves (e.g. the shipped stage table).
    """

    def __init__(self, provider: Any, filling: Any) -> None:
        self.provider = provider
        self.filling = filling
        self._cache: tuple[bytes, tuple[Any, Any]] | None = None

    @property
    def source(self) -> str:
        return f"{self.provider.source}; filling curves from {self.filling.source}"

    def __getattr__(self, name: str) -> Any:  # anything else is the provider's (e.g. the surrogate itself)
        if name in ("provider", "filling", "_cache"):
            raise AttributeError(name)
        return getattr(self.provider, name)

    def _curves(self, sizes_mm: np.ndarray) -> tuple[Any, Any]:
        key = np.asarray(sizes_mm, dtype=float).tobytes()
        if self._cache is None or self._cache[0] != key:
            with warnings.catch_warnings():  # the table's operating point is not the question here
                warnings.simplefilter("ignore")
                f = self.filling.stage_parameters(np.asarray(sizes_mm, dtype=float))
            self._cache = key, (f.filling_fill, f.filling_residence_ratio)
        return self._cache[1]

    def _with(self, params: StageParameters) -> StageParameters:
        fill, ratio = self._curves(params.sizes_mm)
        return dataclasses.replace(params, filling_fill=fill, filling_residence_ratio=ratio,
                                   source=f"{params.source}; filling curves from {self.filling.source}")

    def stage_parameters(self, sizes_mm, stage_speeds_rpm=None, feed_tph=None, gate_deg=None) -> StageParameters:
        """The provider's parameters at ``sizes_mm`` with ``filling``'s curves there."""
        return self._with(self.provider.stage_parameters(sizes_mm, stage_speeds_rpm, feed_tph, gate_deg))

    def sample_stage_parameters(self, sizes_mm, n_samples: int, stage_speeds_rpm=None, feed_tph=None,
                                gate_deg=None, seed: int | None = 0) -> list[StageParameters]:
        """The provider's samples, each with ``filling``'s curves."""
        return [self._with(p) for p in self.provider.sample_stage_parameters(
            sizes_mm, n_samples, stage_speeds_rpm, feed_tph, gate_deg, seed=seed)]

    def __repr__(self) -> str:
        return f"WithFillingCurves({self.provider!r}, filling={self.filling!r})"


class HeldBelow(_Wrapper):
    """A provider whose stage parameters below the smallest size it covers are those of that size.

    The other bounding rule for rock finer than any DEM run (issue 38): the provider's own rule (the
    surrogate's Gaussian process, the table's ln-size trend) continues the statistics' trends past the
    data; this one holds them at the smallest size the statistics cover (the smallest size class not
    flagged ``extrapolated``). :meth:`msmill.model.Mill.run` solves the mill with both and reports how far
    the product moves (``MillResult.held_below_p80_mm`` ...). It gives no posterior samples.

    Parameters
    ----------
    provider : StageParameterProvider
        The provider whose parameters are held.
    """

    def __init__(self, provider: Any) -> None:
        self.provider = provider

    @property
    def source(self) -> str:
        return f"{self.provider.source}; held below its smallest size"

    def stage_parameters(self, sizes_mm, stage_speeds_rpm=None, feed_tph=None, gate_deg=None) -> StageParameters:
        """The provider's parameters at ``max(sizes_mm, smallest covered size)``, at the requested sizes."""
        sizes = np.asarray(sizes_mm, dtype=float)
        own = self.provider.stage_parameters(sizes, stage_speeds_rpm, feed_tph, gate_deg)
        lo = smallest_covered_mm(own, self.provider)
        if lo is None or not np.any(sizes < lo):
            return own
        held = self.provider.stage_parameters(np.maximum(sizes, lo), stage_speeds_rpm, feed_tph, gate_deg)
        return dataclasses.replace(held, sizes_mm=sizes.copy(), extrapolated=own.extrapolated,
                                   source=f"{held.source}; held below {lo:.3g} mm")

    def __repr__(self) -> str:
        return f"HeldBelow({self.provider!r})"


def smallest_covered_mm(params: StageParameters, provider: Any = None) -> float | None:
    """Smallest rock size (mm) the stage statistics cover, when some size class of ``params`` lies below it.

    The provider's ``covered_sizes_mm`` (an optional extension: the smallest DEM run's size) where it has
    one, else the smallest size class not flagged ``extrapolated``; None when no class lies below it.
    """
    sizes = np.asarray(params.sizes_mm, dtype=float)
    covered = getattr(provider, "covered_sizes_mm", None)
    if covered is not None:
        lo = float(covered[0])
    else:
        if params.extrapolated is None:
            return None
        inside = sizes[~np.asarray(params.extrapolated, dtype=bool)]
        if not inside.size:
            return None
        lo = float(inside.min())
    return lo if np.any(sizes < lo * (1 - 1e-9)) else None


class PosteriorSample(_Wrapper):
    """Posterior draw number ``index`` of a provider's stage parameters, wherever it is asked.

    Each (sizes, operating point) asked draws ``n_samples`` samples once with
    ``seed`` (:meth:`sample_stage_parameters` of ``provider``; cached in
    ``cache``, which the members of one :func:`posterior_samples` set share)
    and answers with draw ``index``. The draws are seeded alike at every
    operating point, so a member is the same standard-normal deviation at each
    point: a consistent perturbation, not a joint posterior draw over points
    (the GP's correlation between operating points is not used).
    """

    def __init__(self, provider: Any, index: int, n_samples: int, seed: int = 0,
                 cache: dict | None = None) -> None:
        if not hasattr(provider, "sample_stage_parameters"):
            raise MsmillInputError("stage_parameters", type(provider).__name__,
                                   "a provider with posterior samples (a surrogate)")
        self.provider, self.index, self.n_samples, self.seed = provider, int(index), int(n_samples), seed
        self._draws = {} if cache is None else cache

    @property
    def source(self) -> str:
        return f"posterior sample {self.index + 1} of {self.n_samples} of {self.provider.source}"

    def __getattr__(self, name: str) -> Any:  # anything else is the provider's
        if name in ("provider", "_draws", "index", "n_samples", "seed"):
            raise AttributeError(name)
        return getattr(self.provider, name)

    def stage_parameters(self, sizes_mm, stage_speeds_rpm=None, feed_tph=None, gate_deg=None) -> StageParameters:
        """Draw :attr:`index` of the posterior at ``sizes_mm`` and the operating point."""
        sizes = np.asarray(sizes_mm, dtype=float)
        key = (sizes.tobytes(), None if stage_speeds_rpm is None else tuple(map(float, stage_speeds_rpm)),
               feed_tph, gate_deg)
        if key not in self._draws:
            self._draws[key] = self.provider.sample_stage_parameters(sizes, self.n_samples, stage_speeds_rpm,
                                                                     feed_tph, gate_deg, seed=self.seed)
        return self._draws[key][self.index]

    def __repr__(self) -> str:
        return f"PosteriorSample({self.index + 1}/{self.n_samples}, {self.provider!r})"


def posterior_samples(provider: Any, n_samples: int, seed: int = 0) -> list[PosteriorSample]:
    """``n_samples`` :class:`PosteriorSample` members of ``provider`` sharing one cache of draws."""
    cache: dict = {}
    return [PosteriorSample(provider, k, n_samples, seed, cache) for k in range(n_samples)]


def default_surrogate_path() -> Path | None:
    """Path of the shipped default surrogate (``msmill/data/surrogates/default.json``), None when absent."""
    p = default_surrogate_path_dir() / "default.json"
    return p if p.is_file() else None


def sense_surrogate_path(sense: str) -> Path | None:
    """The shipped surrogate of the default machine turning as rotation sense ``sense``
    (``msmill/data/surrogates/<sense>.json``; the default sense's is ``default.json``), None when none is."""
    from msmill.machine import DEFAULT_ROTATION_SENSE

    if sense == DEFAULT_ROTATION_SENSE:
        return default_surrogate_path()
    p = default_surrogate_path_dir() / f"{sense}.json"
    return p if p.is_file() else None


def default_surrogate_path_dir() -> Path:
    """Folder of the shipped surrogates (``msmill/data/surrogates``)."""
    from importlib import resources

    return Path(str(resources.files("msmill").joinpath("data/surrogates")))


def machine_mismatch(provider: Any, machine: Any) -> str | None:
    """A note when ``provider``'s DEM runs were made on another machine than ``machine``, else None.

    Only providers that record their machine (:attr:`msmill.surrogate.provider.SurrogateProvider.
    trained_machine`) can be checked; the note names both rotation senses.
    """
    trained = getattr(provider, "trained_machine", None)
    if machine is None or not trained or trained["geometry_hash"] == machine.geometry_hash():
        return None
    return (f"stage parameters from DEM runs of another machine: {trained['name']} (rotation sense "
            f"{trained['rotation_sense']}), not this {machine.name} (rotation sense {machine.rotation_sense}); "
            "the streams can differ by a factor of 2-5 between senses (docs/mill-dem.md)")


def _other_sense(machine: Any) -> str | None:
    """The rotation sense of ``machine`` when it is the default machine turning another way, else None."""
    from msmill.machine import DEFAULT_ROTATION_SENSE, Machine

    if machine is None or machine.rotation_sense in (DEFAULT_ROTATION_SENSE, "custom"):
        return None
    same = machine.with_rotation_sense(DEFAULT_ROTATION_SENSE).geometry_hash() == Machine.default().geometry_hash()
    return machine.rotation_sense if same else None


def named_parameter_path(name: str, field: str = "stage_parameters", machine: Any = None) -> Path | None:
    """The packaged file a name stands for, None for other values.

    ``"default"``: the shipped surrogate trained on the DEM campaign, or, when
    it is not installed, the single-point table with a ``UserWarning`` saying
    so; for the default machine turning another way (``machine``, e.g.
    ``Machine.default().with_rotation_sense("up_up")``) that sense's shipped surrogate
    (:func:`sense_surrogate_path`), a one-line error where none is shipped;
    ``"table"``: the single-point DEM table (``msmill/data/stage_parameters/default.json``).
    """
    import warnings

    if name == TABLE_NAME:
        return default_table_path(field)
    if name != DEFAULT_TABLE:
        return None
    sense = _other_sense(machine)
    if sense is not None:
        p = sense_surrogate_path(sense)
        if p is None:
            raise MsmillInputError(field, name, f"a surrogate file of rotation sense '{sense}' (none is shipped yet: "
                                   "its DEM campaign is under way, docs/campaign.md)")
        return p
    p = default_surrogate_path()
    if p is None:
        table = default_table_path(field)  # raises first when the table is missing too
        warnings.warn("the shipped default surrogate (msmill/data/surrogates/default.json) is not installed: "
                      "using the single-point DEM table ('table') instead", UserWarning, stacklevel=3)
        return table
    return p


def load_provider(path: str | Path) -> Any:
    """Open a parameter file: a table (JSON / TOML / CSV), one run's statistics (JSON) or a surrogate (JSON).

    ``"default"`` names the shipped surrogate (the packaged table when it is
    missing) and ``"table"`` the packaged single-point DEM table
    (:func:`named_parameter_path`).
    """
    import json

    p = named_parameter_path(str(path)) or Path(path)
    from msmill.surrogate.persist import is_surrogate_file

    if is_surrogate_file(p):  # a trained GP surrogate (msmill surrogate fit)
        from msmill.machine import rotation_senses
        from msmill.surrogate.provider import SurrogateProvider

        prov = SurrogateProvider.from_file(p)
        if p == default_surrogate_path():  # its name only: what it does, the file says (filling_curves)
            prov.source = f"shipped default surrogate ({prov.surrogate.training_.n_runs} DEM runs)"
        elif p.parent == default_surrogate_path_dir() and p.stem in rotation_senses():
            prov.source = f"shipped surrogate of rotation sense {p.stem} ({prov.surrogate.training_.n_runs} DEM runs)"
        if prov.surrogate.filling_curves == TABLE_NAME:  # runs from a filled mill: the table's (cold runs)
            table = TableProvider.from_file(default_table_path())
            table.source = "the shipped stage table (cold DEM runs)"
            return WithFillingCurves(prov, table)
        return prov
    if p.suffix.lower() == ".json" and p.exists():
        try:
            kind = json.loads(read_text(p, "stage_parameters", "JSON file")).get("kind")
        except (json.JSONDecodeError, AttributeError):
            kind = None
        if kind != "stage_parameter_table":
            return RunProvider.from_file(p)
    return TableProvider.from_file(p)


# ----------------------------------------------------------------- simple format
class _SimpleRow(BaseModel):
    model_config = ConfigDict(extra="forbid")
    size_mm: float = Field(gt=0)
    stage: int = Field(ge=1)
    kickback: float = Field(ge=0, le=1)
    refeed: float = Field(ge=0, le=1)
    pass_through: float = Field(ge=0, le=1)
    primary_hit_probability: float = Field(ge=0, le=1)
    primary_velocity_mean_m_s: float
    primary_velocity_sigma_m_s: float = Field(gt=0)
    secondary_lambda: float = Field(ge=0)
    secondary_velocity_mean_m_s: float
    secondary_velocity_sigma_m_s: float = Field(gt=0)


class _SimpleDesign(BaseModel):
    model_config = ConfigDict(extra="forbid")
    feed_tph: float = Field(gt=0)
    speed_rpm: float = Field(ge=0)
    gate_deg: float = Field(ge=0, le=90)
    stage_speeds_rpm: list[float] = Field(min_length=1)


class _SimpleTable(BaseModel):
    model_config = ConfigDict(extra="forbid")
    characteristic_time_s: float = Field(gt=0)
    design: _SimpleDesign
    rows: list[_SimpleRow] = Field(min_length=1)
    provenance: dict[str, Any] = Field(default_factory=dict)


_DESIGN_COLS = ("characteristic_time_s", "feed_tph", "speed_rpm", "gate_deg", "stage_speed_rpm")


def read_simple_table(path: str | Path) -> StageParameterTable:
    """Read the simple stage-parameter table format (TOML or CSV).

    TOML layout::

        characteristic_time_s = 0.06
        [design]
        feed_tph = 30.0
        speed_rpm = 1500.0
        gate_deg = 40.0
        stage_speeds_rpm = [1500, 1500, 1500, 1500, 3000]
        [[rows]]            # one per (size, stage)
        size_mm = 10.0
        stage = 1
        kickback = 0.05
        refeed = 0.45
        pass_through = 0.50
        primary_hit_probability = 0.4
        primary_velocity_mean_m_s = 25.0
        primary_velocity_sigma_m_s = 5.0
        secondary_lambda = 2.0
        secondary_velocity_mean_m_s = 6.0
        secondary_velocity_sigma_m_s = 3.0

    CSV layout: one row per (size, stage) with the ``[[rows]]`` columns above
    plus ``characteristic_time_s, feed_tph, speed_rpm, gate_deg,
    stage_speed_rpm`` (the design columns must be constant, except
    ``stage_speed_rpm`` which is the speed of that row's stage). Velocity
    distributions are single Gaussians in this format. Every size must list
    every stage 1..n.

    Returns
    -------
    StageParameterTable
        Validated; errors are one line naming the file, row and field.
    """
    p = Path(path)
    if p.suffix.lower() == ".toml":
        data = read_toml(p, "stage_parameters", "stage-parameter TOML file")
    else:
        lines = read_text(p, "stage_parameters", "stage-parameter CSV file").splitlines()
        raw = [r for r in csv.DictReader(line for line in lines if not line.lstrip().startswith("#"))]
        if not raw:
            raise MsmillInputError(p.name, "no rows", "a CSV table with a header and rows")
        missing = [c for c in _DESIGN_COLS if c not in raw[0]]
        if missing:
            raise MsmillInputError(f"{p.name}.{missing[0]}", None, "a column in the CSV table")
        first = raw[0]
        for i, r in enumerate(raw):
            for c in _DESIGN_COLS[:-1]:
                if r[c] != first[c]:
                    raise MsmillInputError(f"{p.name}.rows.{i}.{c}", r[c], f"the same value in every row ({first[c]})")
        speeds: dict[int, str] = {}
        for r in raw:
            speeds.setdefault(int(float(r["stage"])), r["stage_speed_rpm"])
        data = {
            "characteristic_time_s": first["characteristic_time_s"],
            "design": {"feed_tph": first["feed_tph"], "speed_rpm": first["speed_rpm"],
                       "gate_deg": first["gate_deg"],
                       "stage_speeds_rpm": [speeds[k] for k in sorted(speeds)]},
            "rows": [{k: v for k, v in r.items() if k not in _DESIGN_COLS} for r in raw],
        }
    try:
        t = _SimpleTable.model_validate(data)
    except ValidationError as exc:
        raise from_validation_error(exc, prefix=p.name) from None
    by_size: dict[float, list[_SimpleRow]] = {}
    for r in t.rows:
        by_size.setdefault(r.size_mm, []).append(r)
    runs = []
    for size in sorted(by_size):
        rows = sorted(by_size[size], key=lambda r: r.stage)
        stages = [{
            "stage": r.stage, "kickback": r.kickback, "refeed": r.refeed,
            "pass_through": r.pass_through,
            "primary_hit_probability": r.primary_hit_probability,
            "primary_velocity": {"weights": [1.0], "means_m_s": [r.primary_velocity_mean_m_s],
                                 "sigmas_m_s": [r.primary_velocity_sigma_m_s]},
            "secondary_lambda": r.secondary_lambda,
            "secondary_velocity": {"weights": [1.0], "means_m_s": [r.secondary_velocity_mean_m_s],
                                   "sigmas_m_s": [r.secondary_velocity_sigma_m_s]},
        } for r in rows]
        runs.append({
            "design": {**t.design.model_dump(), "size_mm": size},
            "characteristic_time_s": t.characteristic_time_s,
            "stages": stages,
        })
    try:
        return StageParameterTable.model_validate(
            {"runs": runs, "provenance": {"source": p.name, **t.provenance}})
    except ValidationError as exc:
        raise from_validation_error(exc, prefix=p.name) from None
