"""Poisson and Gaussian-mixture fits by minimum Kullback-Leibler divergence.

The secondary-impact statistics of a stage are summarised by two parametric
distributions (paper Section 3.3.1): the number of secondary impacts per
primary impact is Poisson (Eq. 13) and impact velocities are a Gaussian
mixture (Eq. 14). Both are fitted by minimising the KL divergence (Eq. 15)
``D_KL(P || Q) = sum P ln(P / Q)`` from the empirical distribution ``P`` to the
model ``Q``, and every fit reports the KL it reached (``kl_``).

The estimators follow the scikit-learn API: the constructor only stores
parameters, :meth:`fit` validates the data, learns and returns ``self``, and
learned attributes end in ``_``.

Empirical densities
-------------------
* Counts are discrete: ``P`` is the empirical probability mass function over
  the observed counts, ``Q`` the Poisson pmf there. Minimising
  ``D_KL(P || Poisson(lambda))`` over ``lambda``: ``d/dlambda sum_k P_k (k ln
  lambda - lambda) = mean/lambda - 1 = 0``, so the KL-optimal ``lambda`` is
  exactly the sample mean (the same as maximum likelihood); no iteration is
  needed.
* Velocities are continuous: ``P`` is a **histogram** (bin masses ``P_b``, bin
  edges from the Freedman-Diaconis rule, clipped to ``min_bins..max_bins``
  bins spanning the data) and ``Q_b`` is the mixture's probability mass in the
  same bins (differences of its CDF; mixture mass outside the histogram's
  range is not renormalised away, so it counts against the fit).
  The KL is the discrete ``sum_b P_b ln(P_b / Q_b)`` over non-empty bins; it
  is the KL between the two piecewise-constant densities on those bins and is
  insensitive to the bin width in a way a KL of point densities is not. A
  finite sample of ``N`` draws from the true model carries a bias of about
  ``(n_bins - 1) / (2 N)``, so small samples cannot reach very small KL.

The mixture fit starts from scikit-learn's ``GaussianMixture`` (EM) for
``K = 1..k_max`` components, keeps the ``K`` with the lowest BIC, and then
refines all ``3K - 1`` free parameters by minimising the binned KL with
L-BFGS-B (weights through a softmax, sigmas through a log, sigmas floored at a
quarter of a bin width and capped at the data range, means bounded to the
data range).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy import optimize, special, stats

from msmill.errors import MsmillInputError
from msmill.stageparams import GaussianMixture

__all__ = ["GaussianMixtureKLFit", "PoissonKLFit", "kl_divergence"]


def kl_divergence(p: np.ndarray, q: np.ndarray) -> float:
    """Discrete KL divergence ``sum p ln(p / q)`` (nats) over entries with ``p > 0``.

    Parameters
    ----------
    p, q : array_like
        Probability masses on the same support; ``p`` is normalised to sum 1,
        ``q`` is used as given (floored at 1e-300).
    """
    p = np.asarray(p, dtype=float)
    q = np.asarray(q, dtype=float)
    p = p / p.sum()
    m = p > 0
    return float(np.sum(p[m] * np.log(p[m] / np.maximum(q[m], 1e-300))))


class PoissonKLFit:
    """Poisson distribution of counts fitted by minimum KL divergence (paper Eq. 13, 15).

    Attributes (after :meth:`fit`)
    ------------------------------
    lambda_ : float
        Poisson mean; equal to the sample mean, which minimises
        ``D_KL(empirical || Poisson)`` (see module docstring).
    kl_ : float
        ``D_KL(empirical pmf || Poisson(lambda_))`` (nats).
    n_samples_ : int
        Number of counts fitted.
    support_ : ndarray
        Observed count values ``k`` (ascending).
    empirical_pmf_ : ndarray
        Empirical probability of each ``support_`` value.
    lambda_stderr_ : float
        Standard error of ``lambda_`` (``sqrt(var / n)`` of the sample).
    """

    def fit(self, counts: Any) -> PoissonKLFit:
        """Fit to an array of non-negative integer counts; returns ``self``."""
        k = np.asarray(counts)
        if k.ndim != 1 or k.size == 0:
            raise MsmillInputError("counts", f"shape {k.shape}", "a non-empty 1-D array of counts")
        if not np.all(np.isfinite(k)) or np.any(k < 0) or np.any(k != np.round(k)):
            raise MsmillInputError("counts", "non-integer or negative values", "integers >= 0")
        k = k.astype(np.int64)
        values, n = np.unique(k, return_counts=True)
        p = n / k.size
        lam = float(k.mean())
        self.n_samples_ = int(k.size)
        self.support_ = values
        self.empirical_pmf_ = p
        self.lambda_ = lam
        self.lambda_stderr_ = float(k.std(ddof=1) / np.sqrt(k.size)) if k.size > 1 else float("nan")
        self.kl_ = kl_divergence(p, self.pmf(values))
        return self

    def pmf(self, k: Any) -> np.ndarray:
        """Poisson probability of each count in ``k``."""
        return stats.poisson.pmf(np.asarray(k), self.lambda_)


class GaussianMixtureKLFit:
    """1-D Gaussian mixture fitted by minimum KL divergence (paper Eq. 14, 15).

    Parameters
    ----------
    k_max : int
        Largest number of components tried; ``K`` is chosen by BIC of the EM fits.
    min_bins, max_bins : int
        Bounds of the Freedman-Diaconis histogram bin count.
    refine : bool
        Refine the EM solution by minimising the binned KL (default True).
        With False the BIC-selected EM solution is kept (its KL still reported).
    random_state : int
        Seed of the EM initialisation.

    Attributes (after :meth:`fit`)
    ------------------------------
    n_components_ : int
        Chosen ``K``.
    weights_, means_, sigmas_ : ndarray
        Mixture weights, means and standard deviations (units of the data,
        m/s for velocities), sorted by mean.
    kl_ : float
        Binned ``D_KL(histogram || mixture)`` of the final fit (nats).
    kl_em_ : float
        The same for the EM initialisation.
    bic_ : ndarray
        BIC of the EM fit for ``K = 1..k_max``.
    bin_edges_ : ndarray
        Histogram bin edges used for the KL.
    n_samples_ : int
    """

    def __init__(
        self,
        k_max: int = 4,
        min_bins: int = 10,
        max_bins: int = 80,
        refine: bool = True,
        random_state: int = 0,
    ) -> None:
        self.k_max = k_max
        self.min_bins = min_bins
        self.max_bins = max_bins
        self.refine = refine
        self.random_state = random_state

    # ------------------------------------------------------------------ fit
    def fit(self, x: Any) -> GaussianMixtureKLFit:
        """Fit to a 1-D sample; returns ``self``."""
        from sklearn.mixture import GaussianMixture as SkGM

        if not isinstance(self.k_max, int | np.integer) or self.k_max < 1:
            raise MsmillInputError("k_max", self.k_max, "an integer >= 1")
        if self.min_bins < 2 or self.max_bins < self.min_bins:
            raise MsmillInputError("min_bins/max_bins", (self.min_bins, self.max_bins), "2 <= min_bins <= max_bins")
        v = np.asarray(x, dtype=float).ravel()
        if v.size < 2 or not np.all(np.isfinite(v)):
            raise MsmillInputError("x", f"{v.size} values", "at least 2 finite values")
        self.n_samples_ = int(v.size)
        edges = self._edges(v)
        self.bin_edges_ = edges
        counts, _ = np.histogram(v, bins=edges)
        p = counts / counts.sum()
        self.hist_mass_ = p
        width = float(np.min(np.diff(edges)))
        sig_floor = 0.25 * width

        if np.ptp(v) == 0:  # degenerate sample: one narrow component
            self._set(np.array([1.0]), np.array([v[0]]), np.array([sig_floor]))
            self.bic_ = np.array([np.nan])
            self.kl_em_ = self.kl_ = self._kl(p)
            return self

        k_top = int(min(self.k_max, max(1, np.unique(v).size - 1), max(1, v.size // 5)))
        bics, models = [], []
        for k in range(1, k_top + 1):
            gm = SkGM(n_components=k, random_state=self.random_state, n_init=2, reg_covar=sig_floor**2)
            gm.fit(v[:, None])
            bics.append(gm.bic(v[:, None]))
            models.append(gm)
        self.bic_ = np.asarray(bics)
        best = models[int(np.argmin(bics))]
        w = best.weights_.ravel()
        mu = best.means_.ravel()
        sd = np.sqrt(best.covariances_.ravel())
        self._set(w, mu, np.maximum(sd, sig_floor))
        self.kl_em_ = self._kl(p)
        if self.refine:
            self._refine(p, sig_floor)
        self.kl_ = self._kl(p)
        return self

    def _edges(self, v: np.ndarray) -> np.ndarray:
        lo, hi = float(v.min()), float(v.max())
        if hi <= lo:
            return np.array([lo - 0.5, lo + 0.5])
        q75, q25 = np.percentile(v, [75, 25])
        h = 2 * (q75 - q25) / v.size ** (1 / 3)
        n = int(np.ceil((hi - lo) / h)) if h > 0 else self.min_bins
        n = int(np.clip(n, self.min_bins, self.max_bins))
        return np.linspace(lo, hi, n + 1)

    def _bin_mass(self, w: np.ndarray, mu: np.ndarray, sd: np.ndarray) -> np.ndarray:
        # not renormalised: mixture mass outside the histogram's range counts as a miss, so no
        # component can wander off and act as a free uniform background
        e = self.bin_edges_
        cdf = special.ndtr((e[:, None] - mu) / sd) @ w
        return np.diff(cdf)

    def _kl(self, p: np.ndarray) -> float:
        return kl_divergence(p, self._bin_mass(self.weights_, self.means_, self.sigmas_))

    def _refine(self, p: np.ndarray, sig_floor: float) -> None:
        k = self.weights_.size
        mask = p > 0

        def unpack(theta: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
            a = np.concatenate([[0.0], theta[: k - 1]])
            w = np.exp(a - a.max())
            w /= w.sum()
            mu = theta[k - 1 : 2 * k - 1]
            sd = sig_floor + np.exp(theta[2 * k - 1 :])
            return w, mu, sd

        def objective(theta: np.ndarray) -> float:
            q = self._bin_mass(*unpack(theta))
            return float(-np.sum(p[mask] * np.log(np.maximum(q[mask], 1e-300))))

        w0 = np.maximum(self.weights_, 1e-9)
        a0 = np.log(w0[1:] / w0[0])
        s0 = np.log(np.maximum(self.sigmas_ - sig_floor, 1e-3 * sig_floor))
        theta0 = np.concatenate([a0, self.means_, s0])
        lo, hi = float(self.bin_edges_[0]), float(self.bin_edges_[-1])
        span = hi - lo
        theta0[k - 1 : 2 * k - 1] = np.clip(theta0[k - 1 : 2 * k - 1], lo, hi)
        theta0[2 * k - 1 :] = np.minimum(theta0[2 * k - 1 :], np.log(span))
        bounds = [(-30.0, 30.0)] * (k - 1) + [(lo, hi)] * k + [(None, float(np.log(span)))] * k
        f0 = objective(theta0)
        res = optimize.minimize(objective, theta0, method="L-BFGS-B", bounds=bounds, options={"maxiter": 500})
        if np.isfinite(res.fun) and res.fun <= f0:
            self._set(*unpack(res.x))

    def _set(self, w: np.ndarray, mu: np.ndarray, sd: np.ndarray) -> None:
        order = np.argsort(mu)
        w = np.asarray(w, dtype=float)[order]
        self.weights_ = w / w.sum()
        self.means_ = np.asarray(mu, dtype=float)[order]
        self.sigmas_ = np.asarray(sd, dtype=float)[order]
        self.n_components_ = int(w.size)

    # ------------------------------------------------------------- results
    def pdf(self, x: Any) -> np.ndarray:
        """Mixture density at ``x`` (1 / units of the data)."""
        return self.to_stageparams().pdf(np.asarray(x, dtype=float))

    def to_stageparams(self) -> GaussianMixture:
        """The fit as a :class:`msmill.stageparams.GaussianMixture` (m/s)."""
        w = self.weights_ / self.weights_.sum()
        return GaussianMixture(
            weights=[float(a) for a in w],
            means_m_s=[float(a) for a in self.means_],
            sigmas_m_s=[float(a) for a in self.sigmas_],
        )

    def empirical(self) -> tuple[np.ndarray, np.ndarray]:
        """``(bin_edges, density)`` of the histogram the fit was measured against."""
        return self.bin_edges_, self.hist_mass_ / np.diff(self.bin_edges_)
