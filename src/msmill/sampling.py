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
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from msmill.errors import MsmillInputError

__all__ = ["ERROR_ESTIMATORS", "AutocorrelationTime", "BatchMeans", "BlockBootstrap", "ErrorEstimator",
           "OverlappingBatchMeans", "SamplingError", "error_estimator", "replica_z_scores", "slice_sums", "t_quantile"]


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


#: name -> estimator class
ERROR_ESTIMATORS: dict[str, type[ErrorEstimator]] = {
    cls.name: cls for cls in (BatchMeans, OverlappingBatchMeans, AutocorrelationTime, BlockBootstrap)}


def error_estimator(name: str, **kwargs: object) -> ErrorEstimator:
    """The estimator registered as ``name`` (one line naming the choices otherwise)."""
    if name not in ERROR_ESTIMATORS:
        raise MsmillInputError("error_estimator", name, ", ".join(sorted(ERROR_ESTIMATORS)))
    return ERROR_ESTIMATORS[name](**kwargs)
