"""Standard errors of time averages from correlated DEM records (issue 36).

A DEM statistic over a measurement window is a *ratio estimator*
``R = sum(num) / sum(den)`` over the window's time slices: a stream is the
mass of tagged rock that went one way over the mass tagged, a hit probability
the mass hit over the mass tagged, a mean velocity the sum of speeds over the
number of impacts, a mean hold-up the sum of masses over the number of
samples. Consecutive slices are correlated (rock that stays in a stage is
tagged again; the flow pulsates), so the error of ``R`` is not that of
independent samples. Each estimator here takes the per-slice ``num`` and
``den`` series of one statistic (equal slices of the window, in time order)
and returns the standard error of ``R`` and the degrees of freedom it rests
on (for a t quantile instead of 2):

* :class:`BatchMeans` -- ``k`` consecutive batches, ``R`` per batch,
  ``SE = sd(R_b) / sqrt(k)``, ``k - 1`` degrees of freedom (today's runs use
  ``k = 5``);
* :class:`OverlappingBatchMeans` -- every window of ``b`` consecutive slices
  (Meketon and Schmeiser 1984), about ``1.5 (n / b - 1)`` degrees of freedom;
* :class:`AutocorrelationTime` -- the integrated autocorrelation time of the
  linearised series with Sokal's automatic window (``M >= c tau``);
* :class:`BlockBootstrap` -- the moving-block bootstrap (Kuensch 1989) of the
  slices, blocks of ``b`` slices.

The linearised series of a ratio is ``z_i = (num_i - R den_i) / mean(den)``:
``Var(R) = Var(mean(z))`` to first order (the delta method). Estimators are
small registered classes (:data:`ERROR_ESTIMATORS`) behind one method,
``standard_error(num, den) -> SamplingError``.

**Between runs.** Feed-seed replicas of one point differ by more than any
within-window estimator allows, and the excess does not shrink with the
window (30 mm: the rms z of the streams rises from 1.3 with 2 s windows to
1.9 with 8 s ones): each run settles into its own state and keeps it for
longer than a window. A single run cannot see that part, so it comes from
replicas: :class:`BetweenRunVariance` is a standard deviation per kind of
statistic (:data:`STATISTIC_KINDS`), ``sigma_b = a (size / 20 mm)^beta``
(absolute for fractions, relative to the value for the rest), fitted by
restricted maximum likelihood to replica sets (:func:`fit_between_run`), and
a run's honest error is ``sqrt(se_within^2 + sigma_b^2)``
(:meth:`BetweenRunVariance.total`). The packaged fit is
``msmill/data/sampling/between_run.json`` (``scripts/calibrate_sampling_errors.py``).
"""

from __future__ import annotations

import json
import math
from abc import ABC, abstractmethod
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from msmill.errors import MsmillInputError

__all__ = [
    "ERROR_ESTIMATORS",
    "RELATIVE_KINDS",
    "RUN_ERROR_ESTIMATOR",
    "STATISTIC_KINDS",
    "AutocorrelationTime",
    "BatchMeans",
    "BetweenRunVariance",
    "BlockBootstrap",
    "ErrorEstimator",
    "OverlappingBatchMeans",
    "ReplicaSet",
    "SamplingError",
    "default_between_run",
    "error_estimator",
    "fit_between_run",
    "fit_variance_law",
    "legacy_factors",
    "paired_deviations",
    "replica_set_z_scores",
    "replica_sets",
    "replica_z_scores",
    "seed_error_ratios",
    "slice_sums",
    "stage_values",
    "statistic_kind",
    "statistics_by_name",
    "t_quantile",
]

#: statistic name (``StageStatistics.sampling_error`` key, or ``"holdup"``) -> kind of statistic
STATISTIC_KINDS: dict[str, str] = {
    "kickback": "streams", "refeed": "streams", "pass_through": "streams", "primary_hit_probability": "hit",
    "primary_velocity_mean_m_s": "velocity", "secondary_velocity_mean_m_s": "velocity",
    "secondary_lambda": "count", "holdup": "holdup"}
#: kinds whose between-run deviation scales with the value (the others are fractions: absolute)
RELATIVE_KINDS = frozenset({"velocity", "count", "holdup"})
#: the within-run estimator the runs report (chosen against replicas: ``benchmarks/error_calibration.py``)
RUN_ERROR_ESTIMATOR = "autocorrelation_time"
#: rock size (mm) the between-run deviation is referred to
REFERENCE_SIZE_MM = 20.0
#: largest |beta| of the between-run size law (a sixteenfold change over 2-30 mm at 1)
BETA_MAX = 4.0


def statistic_kind(name: str) -> str | None:
    """Kind of a statistic named ``name`` or ``"s<stage>.<name>"`` (None: not one with a between-run model)."""
    return STATISTIC_KINDS.get(name.split(".", 1)[-1])


@dataclass(frozen=True)
class SamplingError:
    """A standard error and the degrees of freedom behind it (``inf``: a normal quantile is right)."""

    se: float
    dof: float

    def half_width(self, coverage: float = 0.95) -> float:
        """Half width of the two-sided interval of ``coverage`` (the t quantile at ``dof``)."""
        return self.se * t_quantile(coverage, self.dof)


def t_quantile(coverage: float, dof: float) -> float:
    """Two-sided Student-t quantile (normal for ``dof = inf``; NaN below one degree of freedom)."""
    from scipy import stats

    if not 0 < coverage < 1:
        raise MsmillInputError("coverage", coverage, "a number in (0, 1)")
    if not dof >= 1:
        return float("nan")
    q = 0.5 + 0.5 * coverage
    return float(stats.norm.ppf(q) if math.isinf(dof) else stats.t.ppf(q, dof))


def slice_sums(t_s: np.ndarray, weights: np.ndarray, window_s: tuple[float, float], n_slices: int) -> np.ndarray:
    """Sums of ``weights`` (samples at times ``t_s``, s) over ``n_slices`` equal slices of the window.

    Samples outside the window are left out; one at its end goes to the last slice.
    """
    t0, t1 = map(float, window_s)
    if not t1 > t0:
        raise MsmillInputError("window_s", window_s, "(start, end) with end > start (s)")
    t = np.asarray(t_s, dtype=float)
    w = np.broadcast_to(np.asarray(weights, dtype=float), t.shape)
    inside = (t >= t0) & (t <= t1)
    k = np.minimum(((t[inside] - t0) / (t1 - t0) * n_slices).astype(np.int64), n_slices - 1)
    return np.bincount(k, weights=w[inside], minlength=n_slices)


def _series(num: np.ndarray, den: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    num = np.asarray(num, dtype=float)
    den = np.asarray(den, dtype=float)
    if num.shape != den.shape or num.ndim != 1:
        raise MsmillInputError("num/den", (num.shape, den.shape), "two 1-D series of one length")
    return num, den


def _linearised(num: np.ndarray, den: np.ndarray) -> np.ndarray | None:
    """``z_i = (num_i - R den_i) / mean(den)`` (None without denominator)."""
    total = den.sum()
    if not total > 0:
        return None
    r = num.sum() / total
    return (num - r * den) / den.mean()


class ErrorEstimator(ABC):
    """Standard error of a ratio estimator from per-slice numerator and denominator series."""

    name: ClassVar[str] = ""

    @abstractmethod
    def standard_error(self, num: np.ndarray, den: np.ndarray) -> SamplingError:
        """The standard error of ``sum(num) / sum(den)`` and its degrees of freedom (NaN: no estimate)."""


@dataclass(frozen=True)
class BatchMeans(ErrorEstimator):
    """``n_batches`` consecutive batches of slices; ``R`` per batch; ``sd / sqrt(k)``, ``k - 1`` dof.

    Batches without denominator are left out (``k`` counts those with one).
    """

    n_batches: int = 5
    name: ClassVar[str] = "batch_means"

    def standard_error(self, num: np.ndarray, den: np.ndarray) -> SamplingError:
        num, den = _series(num, den)
        if num.size < self.n_batches:
            return SamplingError(float("nan"), float("nan"))
        b = np.array_split(np.arange(num.size), self.n_batches)
        n_b = np.array([num[i].sum() for i in b])
        d_b = np.array([den[i].sum() for i in b])
        ok = d_b > 0
        if ok.sum() < 2:
            return SamplingError(float("nan"), float("nan"))
        r = n_b[ok] / d_b[ok]
        return SamplingError(float(r.std(ddof=1) / math.sqrt(r.size)), float(r.size - 1))


@dataclass(frozen=True)
class OverlappingBatchMeans(ErrorEstimator):
    """Every run of ``batch_slices`` consecutive slices (default ``round(sqrt(n))``), on the linearised series.

    ``sigma^2 = n b / ((n - b) (n - b + 1)) sum_j (zbar_j - zbar)^2`` estimates ``n Var(zbar)``; degrees
    of freedom ``1.5 (n / b - 1)`` (Meketon and Schmeiser 1984).
    """

    batch_slices: int | None = None
    name: ClassVar[str] = "overlapping_batch_means"

    def standard_error(self, num: np.ndarray, den: np.ndarray) -> SamplingError:
        num, den = _series(num, den)
        z = _linearised(num, den)
        n = num.size
        b = self.batch_slices or max(1, round(math.sqrt(n)))
        if z is None or n < 4 or not 1 <= b < n:
            return SamplingError(float("nan"), float("nan"))
        c = np.concatenate([[0.0], np.cumsum(z)])
        means = (c[b:] - c[:-b]) / b
        sigma2 = n * b / ((n - b) * (n - b + 1)) * float(np.sum((means - z.mean()) ** 2))
        return SamplingError(math.sqrt(sigma2 / n), 1.5 * (n / b - 1))


@dataclass(frozen=True)
class AutocorrelationTime(ErrorEstimator):
    """``Var(zbar) = gamma_0 tau / n``, ``tau = 1 + 2 sum_{k<=M} rho_k`` with the smallest ``M >= c tau(M)``.

    Sokal's automatic window; degrees of freedom about ``n / tau`` (independent samples' worth). ``tau``
    is kept at least 1 (a negative sum, anticorrelated slices, is noise at these lengths).
    """

    c: float = 5.0
    name: ClassVar[str] = "autocorrelation_time"

    def tau(self, z: np.ndarray) -> float:
        """Integrated autocorrelation time (slices) of a series."""
        n = z.size
        d = z - z.mean()
        f = np.fft.rfft(d, 2 * n)
        acf = np.fft.irfft(f * np.conj(f))[:n] / n
        if not acf[0] > 0:
            return float("nan")
        rho = acf / acf[0]
        taus = 1 + 2 * np.cumsum(rho[1:])
        m = np.arange(1, n)
        ok = np.flatnonzero(m >= self.c * taus)
        tau = float(taus[ok[0]]) if ok.size else float(taus[-1])
        return max(tau, 1.0)

    def standard_error(self, num: np.ndarray, den: np.ndarray) -> SamplingError:
        num, den = _series(num, den)
        z = _linearised(num, den)
        n = num.size
        if z is None or n < 4:
            return SamplingError(float("nan"), float("nan"))
        tau = self.tau(z)
        g0 = float(np.mean((z - z.mean()) ** 2))
        return SamplingError(math.sqrt(g0 * tau / n), max(n / tau - 1, 1.0))


@dataclass(frozen=True)
class BlockBootstrap(ErrorEstimator):
    """Moving-block bootstrap of the slices: ``n_boot`` resamples of blocks of ``block_slices`` (default
    ``round(n^(1/3))``, at least 1), ``R`` of each; ``SE = sd`` over the resamples. Degrees of freedom:
    about the number of blocks (``n / b - 1``)."""

    block_slices: int | None = None
    n_boot: int = 400
    seed: int = 0
    name: ClassVar[str] = "block_bootstrap"

    def standard_error(self, num: np.ndarray, den: np.ndarray) -> SamplingError:
        num, den = _series(num, den)
        n = num.size
        b = self.block_slices or max(1, round(n ** (1 / 3)))
        if n < 4 or not den.sum() > 0 or b >= n:
            return SamplingError(float("nan"), float("nan"))
        n_blocks = math.ceil(n / b)
        rng = np.random.default_rng(self.seed)
        starts = rng.integers(0, n - b + 1, size=(self.n_boot, n_blocks))
        idx = (starts[..., None] + np.arange(b)).reshape(self.n_boot, -1)[:, :n]
        d = den[idx].sum(axis=1)
        r = num[idx].sum(axis=1)[d > 0] / d[d > 0]
        if r.size < 2:
            return SamplingError(float("nan"), float("nan"))
        return SamplingError(float(r.std(ddof=1)), float(n / b - 1))


def replica_z_scores(values: np.ndarray, errors: np.ndarray) -> np.ndarray:
    """Each replica's deviation from the mean of the others, in units of its standard deviation.

    ``z_i = (x_i - mean_{j != i} x_j) / sqrt(se_i^2 + sum_{j != i} se_j^2 / (m - 1)^2)`` for ``m``
    independent replicas ``x`` with reported errors ``se``: with honest errors ``E[z^2] = 1`` (more if the
    errors are themselves estimated from few degrees of freedom). Replicas without a finite error are
    left out; fewer than two: empty.
    """
    x = np.asarray(values, dtype=float)
    e = np.asarray(errors, dtype=float)
    ok = np.isfinite(x) & np.isfinite(e) & (e > 0)
    x, e = x[ok], e[ok]
    m = x.size
    if m < 2:
        return np.zeros(0)
    others = (x.sum() - x) / (m - 1)
    var = e**2 + (np.sum(e**2) - e**2) / (m - 1) ** 2
    return (x - others) / np.sqrt(var)


@dataclass(frozen=True)
class ReplicaSet:
    """Feed-seed replicas of one statistic at one point: values and their within-run errors."""

    kind: str
    size_mm: float
    values: np.ndarray
    se_within: np.ndarray
    dof_within: np.ndarray


@dataclass(frozen=True)
class BetweenRunVariance:
    """Between-run standard deviation per kind, ``sigma_b = a (size / 20 mm)^beta`` (times the value for
    :data:`RELATIVE_KINDS`), and what it rests on.

    ``params[kind] = (log_a, beta)``; ``cov[kind]`` their 2x2 covariance (REML curvature); ``n_sets`` the
    replica sets behind each kind; ``size_range_mm`` the sizes they span.
    """

    params: Mapping[str, tuple[float, float]]
    cov: Mapping[str, tuple[tuple[float, float], tuple[float, float]]] = field(default_factory=dict)
    n_sets: Mapping[str, int] = field(default_factory=dict)
    size_range_mm: tuple[float, float] = (math.nan, math.nan)
    provenance: Mapping[str, Any] = field(default_factory=dict)
    #: per kind, ``sqrt(sum se_ac^2 / sum se_bm5^2)`` over the replicas: what turns a five-batch-means error
    #: (runs before 2026-12-05, whose series were not kept) into the run estimator's on average
    legacy_factor: Mapping[str, float] = field(default_factory=dict)
    #: ``(log c, beta)``: the velocity-quantile targets' iid sampling variance times ``c (size / 20)^beta``
    #: is what the replicas scatter by (:meth:`quantile_variance_factor`)
    quantile_var_law: tuple[float, float] = (0.0, 0.0)

    def quantile_variance_factor(self, size_mm: float) -> float:
        """Factor on the iid sampling variance of a fitted velocity mixture's quantiles at ``size_mm``."""
        log_c, beta = self.quantile_var_law
        return math.exp(log_c) * (float(size_mm) / REFERENCE_SIZE_MM) ** beta

    def legacy_total(self, kind: str | None, size_mm: float, value: float, se_batch_means: float) -> float:
        """Honest error of a statistic from a five-batch-means error (runs without series)."""
        f = self.legacy_factor.get(kind, 1.0) if kind else 1.0
        return math.hypot(f * se_batch_means, self.sigma(kind, size_mm, value) if kind else 0.0)

    def sigma(self, kind: str, size_mm: float, value: float = 1.0) -> float:
        """Between-run standard deviation of a statistic of ``kind`` at ``size_mm`` (0 for an unknown kind)."""
        if kind not in self.params:
            return 0.0
        log_a, beta = self.params[kind]
        s = math.exp(log_a) * (float(size_mm) / REFERENCE_SIZE_MM) ** beta
        return s * abs(float(value)) if kind in RELATIVE_KINDS else s

    def dof(self, kind: str) -> float:
        """Degrees of freedom of ``sigma_b^2`` (``2 / Var(log sigma_b^2)`` at the reference size; at least 1)."""
        c = self.cov.get(kind)
        if not c or not c[0][0] > 0:
            return math.inf
        return max(1.0 / (2.0 * c[0][0]), 1.0) if math.isfinite(c[0][0]) else 1.0

    def total(self, kind: str | None, size_mm: float, value: float, within: SamplingError) -> SamplingError:
        """``sqrt(se_within^2 + sigma_b^2)`` with Welch-Satterthwaite degrees of freedom."""
        sb = self.sigma(kind, size_mm, value) if kind else 0.0
        if not sb > 0 or not np.isfinite(within.se):
            return within
        v_w, v_b = within.se**2, sb**2
        d_w = within.dof if within.dof > 0 else math.inf
        denom = v_w**2 / d_w + v_b**2 / self.dof(kind)
        return SamplingError(math.sqrt(v_w + v_b), (v_w + v_b) ** 2 / denom if denom > 0 else math.inf)

    def to_dict(self) -> dict[str, Any]:
        return {"kind": "msmill_between_run_variance", "format_version": 1,
                "reference_size_mm": REFERENCE_SIZE_MM, "relative_kinds": sorted(RELATIVE_KINDS),
                "params": {k: list(v) for k, v in self.params.items()},
                "cov": {k: [list(r) for r in v] for k, v in self.cov.items()}, "n_sets": dict(self.n_sets),
                "size_range_mm": list(self.size_range_mm), "legacy_factor": dict(self.legacy_factor),
                "quantile_var_law": list(self.quantile_var_law), "provenance": dict(self.provenance)}

    @classmethod
    def from_dict(cls, doc: Mapping[str, Any]) -> BetweenRunVariance:
        if doc.get("kind") != "msmill_between_run_variance":
            raise MsmillInputError("kind", doc.get("kind"), "msmill_between_run_variance")
        return cls(params={k: (float(a), float(b)) for k, (a, b) in doc["params"].items()},
                   cov={k: ((float(r[0][0]), float(r[0][1])), (float(r[1][0]), float(r[1][1])))
                        for k, r in doc.get("cov", {}).items()},
                   n_sets={k: int(v) for k, v in doc.get("n_sets", {}).items()},
                   size_range_mm=tuple(map(float, doc.get("size_range_mm", (math.nan, math.nan)))),
                   provenance=dict(doc.get("provenance", {})),
                   legacy_factor={k: float(v) for k, v in doc.get("legacy_factor", {}).items()},
                   quantile_var_law=tuple(map(float, doc.get("quantile_var_law", (0.0, 0.0)))))

    @classmethod
    def read(cls, path: str | Path) -> BetweenRunVariance:
        return cls.from_dict(json.loads(Path(path).read_text(encoding="utf-8")))


def replica_sets(docs: Sequence[Mapping[str, Any]], estimator: ErrorEstimator) -> list[ReplicaSet]:
    """Replica sets of every statistic with a kind, from the replicas of one point.

    ``docs``: replica exports of one point (``scripts/error_replicas.py``'s ``series.json``: ``size_mm`` and
    ``series = {name: {"num": [...], "den": [...]}}``); the within-run errors are ``estimator``'s.
    """
    if not docs:
        return []
    size = float(docs[0]["size_mm"])
    out = []
    for key in docs[0]["series"]:
        kind = statistic_kind(key)
        if kind is None or not all(key in d["series"] for d in docs):
            continue
        vals, ses, dofs = [], [], []
        for d in docs:
            num, den = (np.asarray(d["series"][key][c], dtype=float) for c in ("num", "den"))
            e = estimator.standard_error(num, den)
            vals.append(num.sum() / den.sum() if den.sum() > 0 else np.nan)
            ses.append(e.se)
            dofs.append(e.dof)
        out.append(ReplicaSet(kind, size, np.array(vals), np.array(ses), np.array(dofs)))
    return out


def replica_set_z_scores(r: ReplicaSet, between: BetweenRunVariance | None = None) -> np.ndarray:
    """:func:`replica_z_scores` of one set, with the within-run errors or the totals of ``between``."""
    if between is None:
        return replica_z_scores(r.values, r.se_within)
    v = np.nanmean(r.values)
    tot = [between.total(r.kind, r.size_mm, v, SamplingError(float(se), float(d))).se
           for se, d in zip(r.se_within, r.dof_within, strict=True)]
    return replica_z_scores(r.values, np.array(tot))


def legacy_factors(sets: Sequence[ReplicaSet], batch_sets: Sequence[ReplicaSet]) -> dict[str, float]:
    """Per kind ``sqrt(sum se^2 / sum se_bm^2)``: ``sets`` with the run estimator's errors, ``batch_sets`` the
    same statistics (same order) with five batch means'."""
    num: dict[str, float] = {}
    den: dict[str, float] = {}
    for r, b in zip(sets, batch_sets, strict=True):
        ok = np.isfinite(r.se_within) & np.isfinite(b.se_within)
        num[r.kind] = num.get(r.kind, 0.0) + float(np.sum(r.se_within[ok] ** 2))
        den[r.kind] = den.get(r.kind, 0.0) + float(np.sum(b.se_within[ok] ** 2))
    return {k: math.sqrt(num[k] / den[k]) for k in num if den[k] > 0}


def fit_variance_law(size_mm: Sequence[float], ratio: Sequence[float], weight: Sequence[float]) -> tuple[float, float]:
    """``(log c, beta)`` of ``ratio = c (size / 20 mm)^beta`` by weighted least squares in logs (one size: beta 0)."""
    x = np.log(np.asarray(size_mm, dtype=float) / REFERENCE_SIZE_MM)
    y = np.log(np.asarray(ratio, dtype=float))
    w = np.asarray(weight, dtype=float)
    if np.unique(x).size < 2:
        return float(np.sum(w * y) / np.sum(w)), 0.0
    beta, log_c = np.polyfit(x, y, 1, w=np.sqrt(w))
    return float(log_c), float(np.clip(beta, -BETA_MAX, BETA_MAX))


def _reml(theta: np.ndarray, sets: Sequence[ReplicaSet], relative: bool) -> float:
    """Negative restricted log likelihood of ``x_i = mu + b_i + e_i`` over replica sets."""
    log_a, beta = theta
    nll = 0.0
    for r in sets:
        scale = abs(float(np.mean(r.values))) if relative else 1.0
        sb2 = (math.exp(log_a) * (r.size_mm / REFERENCE_SIZE_MM) ** beta * scale) ** 2
        v = r.se_within**2 + sb2
        w = 1.0 / v
        mu = float(np.sum(w * r.values) / np.sum(w))
        nll += 0.5 * float(np.sum(np.log(v)) + np.sum(w * (r.values - mu) ** 2) + math.log(np.sum(w)))
    return nll


def fit_between_run(sets: Sequence[ReplicaSet], kinds: Sequence[str] | None = None,
                    provenance: Mapping[str, Any] | None = None) -> BetweenRunVariance:
    """Restricted-maximum-likelihood fit of ``sigma_b = a (size / 20 mm)^beta`` per kind to replica sets.

    Sets with fewer than three finite replicas are left out. With replicas at one size only, ``beta`` is
    held at 0. The optimum is sought on a grid (``log a`` in -14..1, ``beta`` in +-:data:`BETA_MAX`) and
    refined by Nelder-Mead (the likelihood is flat towards ``a -> 0`` and has several optima). The
    covariance is the inverse of the REML curvature (numerical Hessian; ``inf`` where it is not positive).
    """
    from scipy.optimize import minimize

    by_kind: dict[str, list[ReplicaSet]] = {}
    for r in sets:
        ok = np.isfinite(r.values) & np.isfinite(r.se_within) & (r.se_within > 0)
        if ok.sum() >= 3 and (kinds is None or r.kind in kinds):
            by_kind.setdefault(r.kind, []).append(ReplicaSet(r.kind, r.size_mm, r.values[ok], r.se_within[ok],
                                                             r.dof_within[ok]))
    params, cov, n_sets = {}, {}, {}
    sizes = [r.size_mm for v in by_kind.values() for r in v]
    for kind, ks in by_kind.items():
        rel = kind in RELATIVE_KINDS
        one_size = len({r.size_mm for r in ks}) < 2
        f = (lambda t, ks=ks, rel=rel: _reml(np.array([t[0], 0.0]), ks, rel)) if one_size else \
            (lambda t, ks=ks, rel=rel: _reml(t, ks, rel))
        grid = [np.array([la] if one_size else [la, b]) for la in np.arange(-14.0, 1.01, 0.5)
                for b in ([0.0] if one_size else np.arange(-BETA_MAX, BETA_MAX + 0.01, 0.5))]
        x0 = min(grid, key=f)
        lo, hi = np.array([-20.0, -BETA_MAX])[:x0.size], np.array([3.0, BETA_MAX])[:x0.size]
        res = minimize(lambda t, f=f, lo=lo, hi=hi: f(np.clip(t, lo, hi)), x0, method="Nelder-Mead",
                       options={"xatol": 1e-5, "fatol": 1e-9, "maxiter": 4000})
        x = np.clip(res.x, lo, hi)
        h = _hessian(f, x)
        try:
            c = np.linalg.inv(h) if np.all(np.linalg.eigvalsh(h) > 0) else np.full_like(h, np.inf)
        except np.linalg.LinAlgError:
            c = np.full_like(h, np.inf)
        if one_size:
            params[kind] = (float(x[0]), 0.0)
            cov[kind] = ((float(c[0, 0]), 0.0), (0.0, 0.0))
        else:
            params[kind] = (float(x[0]), float(x[1]))
            cov[kind] = ((float(c[0, 0]), float(c[0, 1])), (float(c[1, 0]), float(c[1, 1])))
        n_sets[kind] = len(ks)
    rng = (float(min(sizes)), float(max(sizes))) if sizes else (math.nan, math.nan)
    return BetweenRunVariance(params, cov, n_sets, rng, dict(provenance or {}))


def _hessian(f: Any, x: np.ndarray, h: float = 1e-3) -> np.ndarray:
    """Central-difference Hessian of ``f`` at ``x``."""
    n = x.size
    out = np.zeros((n, n))
    e = np.eye(n) * h
    for i in range(n):  # 1-2 parameters
        for j in range(n):
            out[i, j] = (f(x + e[i] + e[j]) - f(x + e[i] - e[j]) - f(x - e[i] + e[j]) + f(x - e[i] - e[j])) / (4 * h * h)
    return out


_DEFAULT: list[BetweenRunVariance] = []


def default_between_run() -> BetweenRunVariance:
    """The packaged between-run fit (``msmill/data/sampling/between_run.json``), read once."""
    if not _DEFAULT:
        text = resources.files("msmill").joinpath("data", "sampling", "between_run.json").read_text(encoding="utf-8")
        _DEFAULT.append(BetweenRunVariance.from_dict(json.loads(text)))
    return _DEFAULT[0]


#: name -> estimator class
ERROR_ESTIMATORS: dict[str, type[ErrorEstimator]] = {
    cls.name: cls for cls in (BatchMeans, OverlappingBatchMeans, AutocorrelationTime, BlockBootstrap)}


def error_estimator(name: str, **kwargs: object) -> ErrorEstimator:
    """The estimator registered as ``name`` (one line naming the choices otherwise)."""
    if name not in ERROR_ESTIMATORS:
        raise MsmillInputError("error_estimator", name, ", ".join(sorted(ERROR_ESTIMATORS)))
    return ERROR_ESTIMATORS[name](**kwargs)


# --------------------------------------------------------------------------- run against run
#: statistics of a stage whose errors come from the run's batches (the velocity means' are independent-sample
#: ones in runs before 2026-12-02)
BATCH_STATISTICS = ("kickback", "refeed", "pass_through", "primary_hit_probability", "secondary_lambda")


def stage_values(stage: Any) -> dict[str, tuple[float, float | None]]:
    """``name -> (value, reported sampling error or None)`` of a stage's seven error-carrying statistics.

    ``stage`` is a :class:`~msmill.stageparams.StageStatistics`; the names are those of
    :data:`STATISTIC_KINDS` without the hold-up (streams and hit probability as fractions,
    lambda per rock, velocity means in m/s).
    """
    se = stage.sampling_error
    out = {k: (float(getattr(stage, k)), se.get(k)) for k in BATCH_STATISTICS}
    out["primary_velocity_mean_m_s"] = (stage.primary_velocity.mean(), se.get("primary_velocity_mean_m_s"))
    out["secondary_velocity_mean_m_s"] = (stage.secondary_velocity.mean(), se.get("secondary_velocity_mean_m_s"))
    return out


def _paired(a: Any, b: Any):
    """``(name, key, x, se_x, y, se_y)`` for every stage and statistic both runs have errors of."""
    for sa, sb in zip(a.stages, b.stages, strict=True):
        va, vb = stage_values(sa), stage_values(sb)
        for k, (x, ex) in va.items():
            y, ey = vb[k]
            if ex and ey:
                yield f"stage {sa.stage} {k}", k, x, ex, y, ey


def _batches(run: Any) -> int:
    return int(((run.provenance or {}).get("stats") or {}).get("n_batches", 5))


def paired_deviations(a: Any, b: Any, normal_equivalent: bool = False) -> list[tuple[float, str]]:
    """``(|a - b| / sqrt(se_a^2 + se_b^2), "stage s name")`` for every statistic both runs report an error of.

    Parameters
    ----------
    a, b : RunStatistics
        Two runs of the same machine (same stages).
    normal_equivalent : bool
        Give each deviation as the normal deviate of the same two-sided p-value. The errors of
        :data:`BATCH_STATISTICS` come from ``n_batches`` (5) batches, so each is itself uncertain
        and the deviation is Student-t distributed with the Welch-Satterthwaite degrees of freedom
        (``n_batches - 1`` per run); with 5 batches ``|t| > 2`` has a chance of about 0.1, not
        0.046. The velocity means' deviations are taken as normal.
    """
    if not normal_equivalent:
        return [(abs(x - y) / float(np.hypot(ex, ey)), name) for name, _k, x, ex, y, ey in _paired(a, b)]
    from scipy import stats

    na, nb = _batches(a) - 1, _batches(b) - 1
    out = []
    for name, k, x, ex, y, ey in _paired(a, b):
        t = abs(x - y) / float(np.hypot(ex, ey))
        if k in BATCH_STATISTICS:
            nu = (ex**2 + ey**2) ** 2 / (ex**4 / na + ey**4 / nb)
            t = float(stats.norm.isf(stats.t.sf(t, nu)))
        out.append((t, name))
    return out


def statistics_by_name(runs: Sequence[Any]) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """``"stage s name" -> (values over the runs, their reported errors, nan where none)``."""
    out: dict[str, tuple[list[float], list[float]]] = {}
    for r in runs:
        for st in r.stages:
            for k, (x, se) in stage_values(st).items():
                v = out.setdefault(f"stage {st.stage} {k}", ([], []))
                v[0].append(x)
                v[1].append(np.nan if se is None else se)
    return {k: (np.asarray(a), np.asarray(b)) for k, (a, b) in out.items()}


def seed_error_ratios(runs: Sequence[Any]) -> tuple[dict[str, list[float]], float, float]:
    """How the errors runs report compare with their scatter over feed seeds of one point.

    Per statistic (at least three runs reporting an error): the between-seed standard deviation
    over the median reported error.

    Returns
    -------
    (per_family, median, streams_pooled)
        ``per_family``: name (as in :func:`stage_values`) -> one ratio per stage; ``median``: over
        every statistic; ``streams_pooled``: the square root of the variance ratio pooled over the
        stages and the three streams. nan where there is none. Below 1 the reported errors
        overstate the scatter, above 1 they understate it.
    """
    families = (*BATCH_STATISTICS, "primary_velocity_mean_m_s", "secondary_velocity_mean_m_s")
    cal: dict[str, list[tuple[float, float]]] = {f: [] for f in families}
    for name, (x, e) in statistics_by_name(runs).items():
        fam = name.split(" ", 2)[2]
        if np.isfinite(e).sum() >= 3:
            cal[fam].append((float(np.var(x, ddof=1)), float(np.nanmedian(e)) ** 2))
    per_family = {fam: [float(np.sqrt(v / e2)) for v, e2 in pairs if e2 > 0] for fam, pairs in cal.items()}
    per_family = {fam: r for fam, r in per_family.items() if r}
    every = [x for r in per_family.values() for x in r]
    streams = [p for fam in ("kickback", "refeed", "pass_through") for p in cal[fam] if p[1] > 0]
    pooled = float(np.sqrt(np.mean([v / e2 for v, e2 in streams]))) if streams else float("nan")
    return per_family, float(np.median(every)) if every else float("nan"), pooled
