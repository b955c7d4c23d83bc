"""Per-stage impact and transport statistics: the contract between DEM and model.

A DEM run of the mill at one design point (one rock size, feed rate, shaft
speeds and gate angle) is summarised as a :class:`RunStatistics`: for every
rotor stage, where rocks go in one characteristic time (kickback, refeed,
pass-through), how often flingers hit them (primary impacts) and how many and
how hard the secondary impacts that follow are. The DEM statistics
(``msmill.dem``) write it, the SQL store (``msmill.surrogate``) keeps it, and the
mill model (``msmill.model``) reads it through a stage-parameter provider.

Conventions (schema version 1)
------------------------------
* Stages are numbered 1 (top) to ``n_stages`` (bottom).
* One model time step equals ``characteristic_time_s``. Of the rock mass in
  stage ``s`` at the start of a step, the fraction ``kickback`` is in stage
  ``s - 1`` one step later, ``refeed`` is still in ``s`` and ``pass_through``
  is in ``s + 1``. Kickback from stage 1 goes to the inlet zone and re-enters
  stage 1 with the fresh feed on the next step; pass-through from the bottom
  stage leaves the mill (through the gates) as product.
* ``primary_hit_probability`` is the probability that a rock in the stage is
  hit by a flinger (first rock-flinger contact per rotor per pass) within one
  characteristic time. ``primary_velocity`` is the distribution of the relative
  normal velocity at those impacts (m/s).
* Secondary impacts (rock-liner, rock-rock, and further rock-flinger contacts
  after a primary impact, until the next primary impact or the rock leaves the
  stage): their count per primary impact is Poisson with mean
  ``secondary_lambda`` (paper Eq. 13) and their relative normal velocity is the
  Gaussian mixture ``secondary_velocity`` (paper Eq. 14).
* ``destinations`` (optional, per stage) and ``inlet_destinations`` (the
  inlet zone) refine the three streams: the mass fractions of the rock tagged
  in a compartment that are found one characteristic time later in compartment
  0 (inlet zone, the feed chute included), 1..n or n + 1 (left through the
  outlet). They resolve jumps of more than one stage and the inlet zone's own
  dynamics (fresh feed enters the inlet zone); the ``dem_matrix`` transport of
  the mill model uses them (docs/model.md). ``kickback``, ``refeed`` and
  ``pass_through`` are their sums above, at and below the stage.
* ``filling_transport`` (optional, run level): how fast the transport runs
  while the mill fills. Tags taken before the measurement window are binned by
  the mill's hold-up as a share ``fill`` of its window mean; each bin's
  one-lag destinations (the window's for compartments without tags in the bin)
  make a chain whose mean residence, over the window chain's, is
  ``residence_ratio`` (``msmill.dem.mill.stats.filling_transport``; the
  ``dem_matrix_fill`` transport, docs/model.md).
* All quantities are SI (m, s, kg, m/s), except ``size_mm``, ``feed_tph``,
  ``speed_rpm`` and ``gate_deg`` which carry their unit in their name.

Schema version 2 (secondary-impact count families)
--------------------------------------------------
* ``secondary_count`` is a :class:`CountDistribution`: the count of secondary
  impacts per primary impact as a finite mixture of Poissons (``weights``,
  ``means``; a mean of 0 is a point mass at zero) together with the family it
  came from (``poisson``, ``negative_binomial``, ``zero_inflated_poisson``,
  ``poisson_mixture``) and that family's native parameters. A negative
  binomial is a Gamma mixture of Poissons; it is stored as the
  ``NB_QUADRATURE_NODES``-point Gauss rule of its mixing density in
  ``sqrt(lambda)`` (see :func:`negative_binomial_mixture`), which keeps its
  mean and variance exact.
* ``secondary_lambda`` stays and equals ``secondary_count.mean``.
* ``secondary_count_histogram[k]`` is the number of primary impacts followed by
  exactly ``k`` secondary impacts, so the count fits can be redone without the
  raw events; ``secondary_count_selection`` reports every candidate family's
  KL and information criteria and the chosen one.
* Version-1 documents still load: their stages get a one-component
  ``poisson`` ``secondary_count`` of mean ``secondary_lambda`` and the
  document is upgraded to version 2.
"""

from __future__ import annotations

import functools
import json
import math
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import ConfigDict, Field, ValidationError, field_validator, model_validator

from msmill.errors import MsmillInputError, from_validation_error
from msmill.validate import InputModel

SCHEMA_VERSION = 2
READABLE_SCHEMA_VERSIONS = (1, 2)
N_REGIONS = 6  # horizontal regions along the rotor axis (paper Section 3.1.2)
_SUM_TOL = 1e-6


class _Frozen(InputModel):
    model_config = ConfigDict(frozen=True, extra="forbid")


class _JsonDocument(_Frozen):
    """A frozen model that is written as one JSON document."""

    def to_json(self, path: str | Path | None = None) -> str:
        """Serialise to JSON text (and write it to ``path`` if given)."""
        text = self.model_dump_json(indent=2)
        if path is not None:
            Path(path).write_text(text + "\n", encoding="utf-8")
        return text


class GaussianMixture(_Frozen):
    """A 1-D Gaussian mixture of impact velocities (paper Eq. 14), in m/s.

    Parameters
    ----------
    weights : list of float
        Mixture weights ``phi_i`` (>= 0, summing to 1).
    means_m_s : list of float
        Component means ``mu_i`` (m/s).
    sigmas_m_s : list of float
        Component standard deviations ``sigma_i`` (m/s, > 0).
    """

    weights: list[float] = Field(min_length=1)
    means_m_s: list[float] = Field(min_length=1)
    sigmas_m_s: list[float] = Field(min_length=1)

    @model_validator(mode="after")
    def _check(self) -> GaussianMixture:
        n = len(self.weights)
        if len(self.means_m_s) != n or len(self.sigmas_m_s) != n:
            raise ValueError("weights, means_m_s and sigmas_m_s must have equal lengths")
        w = np.asarray(self.weights)
        if np.any(w < 0) or abs(w.sum() - 1.0) > _SUM_TOL:
            raise ValueError(f"weights must be >= 0 and sum to 1 (sum {w.sum():.6g})")
        if np.any(np.asarray(self.sigmas_m_s) <= 0):
            raise ValueError("sigmas_m_s must be > 0")
        if not np.all(np.isfinite(self.means_m_s)):
            raise ValueError("means_m_s must be finite")
        return self

    @property
    def n_components(self) -> int:
        """Number of mixture components ``K``."""
        return len(self.weights)

    def mean(self) -> float:
        """Mean velocity of the mixture (m/s)."""
        return float(np.dot(self.weights, self.means_m_s))

    def pdf(self, v_m_s: np.ndarray) -> np.ndarray:
        """Probability density at ``v_m_s`` (1/(m/s))."""
        v = np.asarray(v_m_s, dtype=float)[..., None]
        mu = np.asarray(self.means_m_s)
        sd = np.asarray(self.sigmas_m_s)
        z = (v - mu) / sd
        return np.sum(np.asarray(self.weights) * np.exp(-0.5 * z * z) / (sd * np.sqrt(2 * np.pi)), axis=-1)

    @classmethod
    def single(cls, mean_m_s: float, sigma_m_s: float) -> GaussianMixture:
        """A one-component mixture."""
        return cls(weights=[1.0], means_m_s=[mean_m_s], sigmas_m_s=[sigma_m_s])


#: Nodes of the Gauss rule that turns a negative binomial into a Poisson mixture. Total-variation
#: error of the pmf (table in ``docs/model.md``): <= 2e-7 for mean <= 2 and size >= 1, <= 1e-5 for
#: mean <= 2 and size >= 0.5, 7e-4 at mean 4, size 0.5; 2e-2 at mean 8, size 0.3 (the worst case
#: tabulated). Mean and variance are exact.
NB_QUADRATURE_NODES = 16
_NB_FINE_NODES = 200
COUNT_FAMILIES = ("poisson", "negative_binomial", "zero_inflated_poisson", "poisson_mixture")


def _gauss_rule(x: np.ndarray, w: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """``n``-point Gauss rule (nodes, weights) of the discrete measure ``sum w_i delta(x_i)`` (Lanczos)."""
    from scipy import linalg

    n = min(n, int(np.count_nonzero(w > 0)))
    total = float(w.sum())
    q = np.zeros((n, x.size))
    q[0] = np.sqrt(w / total)
    a, b = np.zeros(n), np.zeros(max(n - 1, 0))
    for j in range(n):  # short Lanczos recursion with full re-orthogonalisation (n <= ~30)
        v = x * q[j]
        a[j] = v @ q[j]
        v -= q[: j + 1].T @ (q[: j + 1] @ v)
        if j < n - 1:
            b[j] = np.linalg.norm(v)
            q[j + 1] = v / b[j]
    nodes, vec = linalg.eigh_tridiagonal(a, b)
    return nodes, total * vec[0] ** 2


@functools.cache
def _legendre_rule(n: int) -> tuple[np.ndarray, np.ndarray]:
    """The ``n``-point Gauss-Legendre rule on [-1, 1] (an eigenvalue problem: computed once per ``n``)."""
    x, w = np.polynomial.legendre.leggauss(n)
    x.flags.writeable = False
    w.flags.writeable = False
    return x, w


def negative_binomial_mixture(mean: float, size: float, n_nodes: int = NB_QUADRATURE_NODES
                              ) -> tuple[np.ndarray, np.ndarray]:
    """Poisson-mixture ``(weights, means)`` of a negative binomial by Gauss quadrature.

    ``NB(mean, size)`` is Poisson(``lambda``) with ``lambda ~ Gamma(size, mean/size)``.
    The Gamma is first discretised finely (200-point generalised Gauss-Laguerre
    rule for ``size < 1``, Gauss-Legendre in ``sqrt(lambda)`` between the
    1e-15 and 1 - 1e-15 quantiles otherwise), then reduced to the
    ``n_nodes``-point Gauss rule in ``s = sqrt(lambda)`` (the variable in which
    a Poisson kernel has constant width). The rule integrates polynomials in
    ``s`` up to degree ``2 n - 1`` exactly, so the mixture's mean and variance
    equal the negative binomial's.
    """
    from scipy import special, stats

    if mean <= 0:
        return np.array([1.0]), np.array([0.0])
    # the Gamma's shape depends on ``size`` only: build the rule at scale 1 and rescale to ``mean`` below
    # (at the scale mean/size itself, a tiny mean, e.g. 5e-324, underflowed the quantiles to an empty rule)
    theta = 1.0
    if size < 1:
        u, w = special.roots_genlaguerre(_NB_FINE_NODES, size - 1.0)
        s, w = np.sqrt(theta * u), w / special.gamma(size)
    else:
        lo, hi = np.sqrt(stats.gamma.ppf([1e-15, 1 - 1e-15], size, scale=theta))
        x, gw = _legendre_rule(_NB_FINE_NODES)
        s = 0.5 * (hi - lo) * x + 0.5 * (hi + lo)
        w = 0.5 * (hi - lo) * gw * 2 * s * stats.gamma.pdf(s * s, size, scale=theta)
    nodes, weights = _gauss_rule(s, w / w.sum(), n_nodes)
    lam = nodes**2 * (mean / float(np.dot(weights, nodes**2)))  # rounding of the fine rule only
    return weights / weights.sum(), lam


class CountDistribution(_Frozen):
    """Distribution of the number of secondary impacts per primary impact (schema version 2).

    Every family is stored as a finite mixture of Poissons: ``P(K = k) = sum_c
    weights[c] * Poisson(k; means[c])`` (a mean of 0 is a point mass at 0).

    Parameters
    ----------
    weights : list of float
        Component weights (>= 0, summing to 1).
    means : list of float
        Component Poisson means (>= 0; impacts per primary impact).
    family : str
        The fitted family: ``poisson``, ``negative_binomial``,
        ``zero_inflated_poisson`` or ``poisson_mixture``.
    params : dict of str to float
        The family's native parameters: ``lambda`` (Poisson); ``mean``,
        ``size`` (negative binomial, scipy's ``n``); ``pi`` (extra zero
        weight), ``lambda`` (zero-inflated Poisson); ``weight_i``, ``mean_i``
        (mixture, ``i = 1..K``, ascending means).
    """

    weights: list[float] = Field(min_length=1)
    means: list[float] = Field(min_length=1)
    family: Literal["poisson", "negative_binomial", "zero_inflated_poisson", "poisson_mixture"] = "poisson"
    params: dict[str, float] = Field(default_factory=dict)

    @model_validator(mode="after")
    def _check(self) -> CountDistribution:
        w, m = np.asarray(self.weights), np.asarray(self.means)
        if w.size != m.size:
            raise ValueError("weights and means must have equal lengths")
        if np.any(w < 0) or abs(w.sum() - 1.0) > _SUM_TOL:
            raise ValueError(f"count weights must be >= 0 and sum to 1 (sum {w.sum():.6g})")
        if not np.all(np.isfinite(m)) or np.any(m < 0):
            raise ValueError("count means must be finite and >= 0")
        return self

    @property
    def n_components(self) -> int:
        """Number of Poisson components."""
        return len(self.weights)

    @property
    def mean(self) -> float:
        """Mean count ``sum w_c m_c``."""
        return float(np.dot(self.weights, self.means))

    @property
    def variance(self) -> float:
        """Variance ``sum w_c (m_c + m_c^2) - mean^2``."""
        m = np.asarray(self.means)
        return float(np.dot(self.weights, m + m * m) - self.mean**2)

    @property
    def p_zero(self) -> float:
        """Probability of no secondary impact."""
        return float(np.dot(self.weights, np.exp(-np.asarray(self.means))))

    def pmf(self, k_max: int) -> np.ndarray:
        """Probabilities of ``k = 0..k_max`` (length ``k_max + 1``) of the stored mixture."""
        from scipy import stats

        k = np.arange(int(k_max) + 1)
        return np.asarray(self.weights) @ stats.poisson.pmf(k[None, :], np.asarray(self.means)[:, None])

    def native_pmf(self, k_max: int) -> np.ndarray:
        """Probabilities of ``k = 0..k_max`` from ``family`` and ``params`` (differs from
        :meth:`pmf` only by the quadrature error of a negative binomial)."""
        from scipy import stats

        if self.family != "negative_binomial":
            return self.pmf(k_max)
        m, r = self.params["mean"], self.params["size"]
        return stats.nbinom.pmf(np.arange(int(k_max) + 1), r, r / (r + m))

    # ---------------------------------------------------------------- builders
    @classmethod
    def poisson(cls, lam: float) -> CountDistribution:
        """Poisson of mean ``lam``."""
        return cls(weights=[1.0], means=[float(lam)], family="poisson", params={"lambda": float(lam)})

    @classmethod
    def negative_binomial(cls, mean: float, size: float, n_nodes: int = NB_QUADRATURE_NODES) -> CountDistribution:
        """Negative binomial (variance ``mean + mean^2 / size``) as a Gauss-quadrature Poisson mixture."""
        w, m = negative_binomial_mixture(float(mean), float(size), n_nodes)
        return cls(weights=[float(a) for a in w], means=[float(a) for a in m], family="negative_binomial",
                   params={"mean": float(mean), "size": float(size)})

    @classmethod
    def zero_inflated_poisson(cls, pi: float, lam: float) -> CountDistribution:
        """``pi`` point mass at zero plus ``(1 - pi)`` Poisson(``lam``): exactly a 2-component mixture."""
        return cls(weights=[float(pi), 1.0 - float(pi)], means=[0.0, float(lam)], family="zero_inflated_poisson",
                   params={"pi": float(pi), "lambda": float(lam)})

    @classmethod
    def poisson_mixture(cls, weights: Any, means: Any) -> CountDistribution:
        """Finite Poisson mixture (components sorted by mean)."""
        order = np.argsort(np.asarray(means, dtype=float), kind="stable")
        w = np.asarray(weights, dtype=float)[order]
        w = w / w.sum()
        m = np.asarray(means, dtype=float)[order]
        params = {f"{k}_{i + 1}": float(v) for i in range(w.size) for k, v in (("weight", w[i]), ("mean", m[i]))}
        return cls(weights=[float(a) for a in w], means=[float(a) for a in m], family="poisson_mixture",
                   params=params)


class CountCandidate(_Frozen):
    """One candidate family of a count-family selection."""

    family: str
    n_params: int = Field(ge=0)
    kl: float = Field(description="D_KL(empirical pmf || fitted family), nats")
    log_likelihood: float
    aic: float
    bic: float


class CountSelection(_Frozen):
    """Which count family was chosen for a stage, and how every candidate scored."""

    criterion: Literal["bic", "aic"] = "bic"
    chosen: str
    candidates: dict[str, CountCandidate]
    n_samples: int = Field(ge=0)

    @property
    def kl(self) -> float:
        """KL of the chosen candidate (nats)."""
        return self.candidates[self.chosen].kl


def _check_destinations(values: list[float] | None, name: str) -> None:
    if values is not None:
        d = np.asarray(values, dtype=float)
        if d.size < 3 or np.any(d < 0) or abs(d.sum() - 1.0) > _SUM_TOL:
            raise ValueError(f"{name} must be n + 2 fractions >= 0 summing to 1")


class StageStatistics(_Frozen):
    """Impact and transport statistics of one rotor stage at one design point."""

    stage: int = Field(ge=1, description="stage number, 1 = top")
    kickback: float = Field(ge=0, le=1, description="mass fraction moving up per characteristic time")
    refeed: float = Field(ge=0, le=1, description="mass fraction staying in the stage")
    pass_through: float = Field(ge=0, le=1, description="mass fraction moving down")
    region_weights: list[float] | None = Field(
        default=None, description="solid-fraction weights of the 6 regions along the rotor axis"
    )
    region_streams: list[list[float]] | None = Field(
        default=None, description="per region: [kickback, refeed, pass_through]"
    )
    primary_hit_probability: float = Field(ge=0, le=1)
    primary_velocity: GaussianMixture
    primary_velocity_kl: float | None = None
    secondary_lambda: float = Field(ge=0, description="mean secondary impacts per primary impact")
    secondary_lambda_kl: float | None = None
    secondary_velocity: GaussianMixture
    secondary_velocity_kl: float | None = None
    n_primary_impacts: int = Field(default=0, ge=0, description="sample size behind the primary stats")
    n_secondary_impacts: int = Field(default=0, ge=0)
    n_transport_samples: int = Field(default=0, ge=0, description="tagged rocks behind the streams")
    mean_holdup_kg: float | None = Field(default=None, ge=0)
    sampling_error: dict[str, float] = Field(
        default_factory=dict, description="standard errors of the estimates, keyed by field name"
    )
    secondary_count: CountDistribution | None = Field(
        default=None, description="count of secondary impacts per primary impact (Poisson of "
        "secondary_lambda when not given)")
    secondary_count_histogram: list[int] = Field(
        default_factory=list, description="number of primary impacts with k = 0, 1, 2, ... secondary impacts")
    secondary_count_selection: CountSelection | None = None

    @model_validator(mode="before")
    @classmethod
    def _default_count(cls, data: Any) -> Any:
        if isinstance(data, dict) and data.get("secondary_count") is None and "secondary_lambda" in data:
            data = {**data, "secondary_count": CountDistribution.poisson(float(data["secondary_lambda"]))}
        return data

    @model_validator(mode="after")
    def _check_count(self) -> StageStatistics:
        if self.secondary_count is not None:
            m = self.secondary_count.mean
            if abs(m - self.secondary_lambda) > 1e-6 * max(1.0, self.secondary_lambda):
                raise ValueError(f"secondary_lambda ({self.secondary_lambda:.6g}) must equal the mean of "
                                 f"secondary_count ({m:.6g})")
        if any(n < 0 for n in self.secondary_count_histogram):
            raise ValueError("secondary_count_histogram must hold counts >= 0")
        return self
    destinations: list[float] | None = Field(
        default=None, description="mass fractions found one characteristic time later in compartment "
        "0 (inlet zone), 1..n (stages) and n + 1 (left through the outlet)"
    )

    @model_validator(mode="after")
    def _check(self) -> StageStatistics:
        total = self.kickback + self.refeed + self.pass_through
        if abs(total - 1.0) > _SUM_TOL:
            raise ValueError(f"kickback + refeed + pass_through must be 1 (got {total:.6g})")
        _check_destinations(self.destinations, "destinations")
        if self.region_weights is not None:
            w = np.asarray(self.region_weights)
            if w.size != N_REGIONS or np.any(w < 0) or abs(w.sum() - 1) > _SUM_TOL:
                raise ValueError(f"region_weights must be {N_REGIONS} values >= 0 summing to 1")
        if self.region_streams is not None:
            s = np.asarray(self.region_streams, dtype=float)
            if s.shape != (N_REGIONS, 3) or np.any(s < 0) or np.any(np.abs(s.sum(axis=1) - 1) > _SUM_TOL):
                raise ValueError(f"region_streams must be {N_REGIONS} rows of 3 fractions summing to 1")
        return self

    @property
    def streams(self) -> np.ndarray:
        """``[kickback, refeed, pass_through]`` as an array."""
        return np.array([self.kickback, self.refeed, self.pass_through])


#: The four design inputs of a run, in the column order every design matrix uses.
DESIGN_INPUTS = ("size_mm", "feed_tph", "speed_rpm", "gate_deg")


def design_inputs(points) -> np.ndarray:
    """The ``(n, 4)`` matrix of :data:`DESIGN_INPUTS` of ``points``.

    Parameters
    ----------
    points : iterable
        Objects with the four attributes (:class:`DesignPoint`, capacity envelope points, ...).

    Returns
    -------
    ndarray
        Row ``i`` is ``(size_mm, feed_tph, speed_rpm, gate_deg)`` of point ``i`` (mm, t/h, rpm, deg);
        shape ``(0, 4)`` for no points.
    """
    return np.array([[getattr(p, k) for k in DESIGN_INPUTS] for p in points], dtype=float).reshape(-1, 4)


class DesignPoint(_Frozen):
    """The operating point of one DEM run (paper Table 2 design space)."""

    size_mm: float = Field(gt=0, description="rock (sphere) diameter, mm")
    feed_tph: float = Field(gt=0, description="feed rate, t/h")
    speed_rpm: float = Field(ge=0, description="upper-stage shaft speed, rpm")
    gate_deg: float = Field(ge=0, le=90, description="outlet gate angle, deg")
    stage_speeds_rpm: list[float] = Field(min_length=1, description="shaft speed of every stage, rpm")

    @field_validator("stage_speeds_rpm")
    @classmethod
    def _speeds(cls, v: list[float]) -> list[float]:
        if any(s < 0 for s in v):
            raise ValueError("stage speeds must be >= 0")
        return v

    def inputs(self) -> tuple[float, float, float, float]:
        """The point's :data:`DESIGN_INPUTS` (mm, t/h, rpm, deg), in that order."""
        return tuple(getattr(self, k) for k in DESIGN_INPUTS)


class FillingTransport(_Frozen):
    """The DEM's transport while the mill fills (optional part of :class:`RunStatistics`).

    Attributes
    ----------
    fill : list of float
        Mill hold-up at the bin's tags, as a share of the measurement window's mean (0-1, ascending).
    residence_ratio : list of float
        Mean residence of the chain made by the bin's one-lag destinations over that of the
        window's destinations (> 0; below 1: the transport runs faster than at steady state).
    tag_mass_kg : list of float
        Tagged rock mass of the bin (its weight).
    window_residence_steps, window_holdup_kg : float or None
        The two references of the curve: the mean residence (steps of the lag) of the
        window's chain and the window's mean hold-up (kg). One short window measures
        both to 10-20 % for coarse rock; with them, runs of one point (other feed seeds)
        pool against a common reference (:func:`msmill.model.providers.pool_filling_curves`).
        None in curves measured before 2026-12-02.
    lag_s : float or None
        The lag (s) whose steps ``window_residence_steps`` counts: the run's characteristic
        time, which is a whole number of snapshot intervals and so differs between runs of
        one point (30 mm: 0.025 or 0.030 s). None in curves measured before 2026-12-03
        (taken to be on the lag of the curves they are pooled with).
    """

    fill: list[float] = Field(min_length=1)
    residence_ratio: list[float] = Field(min_length=1)
    tag_mass_kg: list[float] = Field(min_length=1)
    window_residence_steps: float | None = Field(default=None, gt=0)
    window_holdup_kg: float | None = Field(default=None, gt=0)
    lag_s: float | None = Field(default=None, gt=0)

    @model_validator(mode="after")
    def _check(self) -> FillingTransport:
        if not len(self.fill) == len(self.residence_ratio) == len(self.tag_mass_kg):
            raise ValueError("fill, residence_ratio and tag_mass_kg must have the same length")
        if any(not 0.0 <= h < 1.0 for h in self.fill) or list(self.fill) != sorted(self.fill):
            raise ValueError("fill must be ascending shares in [0, 1)")
        if any(not (r > 0.0 and math.isfinite(r)) for r in self.residence_ratio):
            raise ValueError("residence_ratio must be finite and > 0")
        if any(m <= 0.0 for m in self.tag_mass_kg):
            raise ValueError("tag_mass_kg must be > 0")
        return self

    def ratio_at(self, fill: np.ndarray) -> np.ndarray:
        """Residence ratio at mill fills ``fill``: linear between the bins and ``(1, 1)``, 1 above, the first below."""
        return np.interp(np.minimum(np.asarray(fill, dtype=float), 1.0), [*self.fill, 1.0],
                         [*self.residence_ratio, 1.0])


#: Mill-fill bin edges (share of the reference hold-up) of a filling curve.
FILLING_BINS = (0.0, 0.2, 0.4, 0.6, 0.8, 1.0)
#: Fewest tags of a compartment in a fill bin for its destinations to replace the reference's.
FILLING_MIN_TAGS = 20


class FillingTags(_Frozen):
    """The tags a run took while its mill filled, binned finely by fill: what runs of one point pool.

    A filling curve (:class:`FillingTransport`) computed per run keeps a compartment's own
    destinations in a fill bin only where the run tagged it at least ``min_tags`` times,
    else the window's: at 30 mm (about 80 rocks in the mill at steady state) most
    compartments of the emptiest bins fall back, which pulls the run's ratio towards 1
    however many runs' curves are averaged. Tags summed over runs first
    (:func:`filling_curve_from_tags`) clear the threshold.

    Attributes
    ----------
    lag_s : float
        The lag (s) of the one-lag destinations (the tag's compartment ``lag_s`` later).
    window_holdup_kg : float
        The run's measurement-window mean hold-up (kg), which ``fill`` is relative to.
    fill : list of float
        Tag-mass-weighted mean fill of each bin (hold-up at the tag over ``window_holdup_kg``),
        bins of tags taken before the window, ascending.
    destination_kg : list of list of list of float
        Per bin (K, C, C + 1): tagged mass in compartment ``c`` (0 inlet zone, 1..n stages)
        found one lag later in ``0..n`` or gone through the outlet (last column).
    tag_count : list of list of int
        Per bin (K, C): number of tags in each compartment.
    """

    lag_s: float = Field(gt=0)
    window_holdup_kg: float = Field(gt=0)
    fill: list[float] = Field(min_length=1)
    destination_kg: list[list[list[float]]]
    tag_count: list[list[int]]

    @model_validator(mode="after")
    def _check(self) -> FillingTags:
        k = len(self.fill)
        c = len(self.tag_count[0]) if self.tag_count else 0
        shapes = ({len(row) for row in self.tag_count}, {len(b) for b in self.destination_kg},
                  {len(row) for b in self.destination_kg for row in b})
        if len(self.tag_count) != k or len(self.destination_kg) != k or shapes != ({c}, {c}, {c + 1}) or c < 1:
            raise ValueError("fill, destination_kg (K, C, C + 1) and tag_count (K, C) must agree in shape")
        d, n = np.asarray(self.destination_kg, dtype=float), np.asarray(self.tag_count, dtype=float)
        if (d < 0).any() or (n < 0).any() or any(h < 0 or not math.isfinite(h) for h in self.fill):
            raise ValueError("fill, destination_kg and tag_count must be finite and >= 0")
        return self


def filling_curve_from_tags(tags: list[FillingTags], reference: tuple[float, np.ndarray],
                            bins: tuple[float, ...] = FILLING_BINS,
                            min_tags: int = FILLING_MIN_TAGS) -> FillingTransport | None:
    """One filling curve from the tags of one or more runs of one point, against a steady reference.

    Parameters
    ----------
    tags : list of FillingTags
        The runs' tags, all at the lag of ``reference``'s matrix.
    reference : (holdup_kg, matrix)
        The steady state the curve is relative to: hold-up (kg, inlet zone and stages) and the
        one-lag destinations ``(C, C + 1)`` (last column out), e.g. a long window's
        (:meth:`RunStatistics.window_reference`, :meth:`RunStatistics.destination_matrix`) or
        the run's own window.
    bins : tuple of float
        Edges of the fill bins (shares of the reference hold-up).
    min_tags : int
        Fewest tags (summed over the runs) of a compartment in a bin for its destinations to
        replace the reference's.

    Each run's fills go on the reference (``fill * window_holdup_kg / holdup_kg``), its fine
    bins into ``bins``; in each bin the runs' tagged masses and counts are summed, every
    compartment with at least ``min_tags`` tags gets the bin's destinations and the others
    keep the reference's, and ``residence_ratio`` is that chain's mean residence
    (:func:`chain_residence_steps`) over the reference chain's. Bins whose chain never
    empties are left out. None when no bin has tags.
    """
    hold, p_ref = float(reference[0]), np.asarray(reference[1], dtype=float)
    c = p_ref.shape[0]
    lags = np.array([t.lag_s for t in tags])
    if lags.size and np.ptp(lags) > 1e-3 * lags.min():
        raise ValueError(f"tags: lags {sorted(set(np.round(lags, 6)))} s; allowed: one lag (pool destinations of one lag)")
    base = chain_residence_steps(p_ref)
    if not (hold > 0 and np.isfinite(base) and p_ref.shape == (c, c + 1)):
        raise ValueError(f"reference: hold-up {hold} kg, chain residence {base} steps; allowed: positive and finite")
    k = len(bins) - 1
    mass, count, fill_mass = np.zeros((k, c, c + 1)), np.zeros((k, c)), np.zeros(k)
    for t in tags:
        d = np.asarray(t.destination_kg, dtype=float).reshape(len(t.fill), c, c + 1)
        n = np.asarray(t.tag_count, dtype=float).reshape(len(t.fill), c)
        h = np.asarray(t.fill) * t.window_holdup_kg / hold
        b = np.searchsorted(np.asarray(bins), h, side="right") - 1
        ok = (b >= 0) & (b < k)
        np.add.at(mass, b[ok], d[ok])
        np.add.at(count, b[ok], n[ok])
        np.add.at(fill_mass, b[ok], h[ok] * d[ok].sum(axis=(1, 2)))
    out: dict[str, list[float]] = {"fill": [], "residence_ratio": [], "tag_mass_kg": []}
    for j in range(k):
        total = mass[j].sum()
        if total <= 0:
            continue
        p = p_ref.copy()
        row = mass[j].sum(axis=1)
        use = (count[j] >= min_tags) & (row > 0)
        p[use] = mass[j][use] / row[use, None]
        r = chain_residence_steps(p) / base
        if not np.isfinite(r):
            continue
        out["fill"].append(float(fill_mass[j] / total))
        out["residence_ratio"].append(float(r))
        out["tag_mass_kg"].append(float(total))
    if not out["fill"]:
        return None
    return FillingTransport(**out, window_residence_steps=float(base), window_holdup_kg=hold, lag_s=float(lags[0]))


def chain_visits(p: np.ndarray) -> np.ndarray:
    """Expected steps rock fed to compartment 0 spends in each compartment of the chain ``p`` (C,).

    ``p`` (C, C+1): one-step destinations, last column out; the result is
    ``e0 (I - Q)^-1``. Raises :class:`numpy.linalg.LinAlgError` when some rock
    never leaves (a singular ``I - Q``).
    """
    q = np.asarray(p, dtype=float)[:, :-1]
    c = q.shape[0]
    return np.linalg.solve((np.eye(c) - q).T, np.eye(c)[0])


def chain_residence_steps(p: np.ndarray) -> float:
    """Mean number of steps rock fed to compartment 0 spends in the chain ``p`` (C, C+1; last column out).

    The sum of :func:`chain_visits`; ``inf`` when some rock never leaves (a singular ``I - Q``).
    """
    try:
        v = float(chain_visits(p).sum())
    except np.linalg.LinAlgError:
        return float("inf")
    return v if np.isfinite(v) and v > 0 else float("inf")


class RunStatistics(_JsonDocument):
    """All per-stage statistics of one DEM run, with run-level figures and provenance."""

    schema_version: Literal[2] = SCHEMA_VERSION
    design: DesignPoint
    mode: Literal["full", "slice"] = "slice"
    characteristic_time_s: float = Field(gt=0)
    stages: list[StageStatistics] = Field(min_length=1)
    steady_state_time_s: float | None = Field(default=None, ge=0)
    measurement_window_s: float | None = Field(default=None, ge=0)
    mass_out_rate_kg_s: float | None = Field(default=None, ge=0)
    residence_time_s: float | None = Field(default=None, ge=0)
    mean_centre_velocity_m_s: float | None = None
    inlet_destinations: list[float] | None = Field(
        default=None, description="as StageStatistics.destinations, for rock tagged in the inlet zone "
        "(everything above stage 1, the feed chute included)"
    )
    inlet_holdup_kg: float | None = Field(default=None, ge=0, description="mean mass in the inlet zone")
    provenance: dict[str, Any] = Field(default_factory=dict)
    # operating envelope (issue 20): how the run ended and what the mill passed; None = not recorded
    outcome: Literal["steady", "not_steady", "choked"] | None = Field(
        default=None, description="steady-state outcome of the run (msmill.steadystate); None: not recorded")
    throughput_tph: float | None = Field(
        default=None, ge=0, description="measured product rate in the window, full-mill equivalent, t/h")
    # adaptive measurement window (issue 12): largest sampling error reached per statistic family
    # (msmill.dem.mill.run.sampling_errors_reached); None: some stage had no sample of that family
    sampling_error_reached: dict[str, float | None] = Field(default_factory=dict)
    # transport while the mill fills (issue 15): None = not measured
    filling_transport: FillingTransport | None = Field(
        default=None, description="residence ratio of the one-lag transport by mill fill, before the window")

    def require_steady(self, allow_not_steady: bool = False, source: str = "statistics") -> RunStatistics:
        """Return self if the run reached steady state; else raise (unless ``allow_not_steady``).

        Statistics from a filling or choked mill are wrong training data: ingest
        and the stage-parameter table refuse them. ``outcome`` None (files from
        before outcomes were recorded) passes.
        """
        if self.outcome in (None, "steady") or allow_not_steady:
            return self
        raise MsmillInputError(f"{source}.outcome", self.outcome,
                               "'steady' (a not-steady or choked run; allow it explicitly to use it)")

    @model_validator(mode="before")
    @classmethod
    def _upgrade(cls, data: Any) -> Any:
        return _upgraded(data)

    @model_validator(mode="after")
    def _check(self) -> RunStatistics:
        numbers = [s.stage for s in self.stages]
        if numbers != list(range(1, len(numbers) + 1)):
            raise ValueError(f"stages must be numbered 1..n in order (got {numbers})")
        if len(self.design.stage_speeds_rpm) != len(self.stages):
            raise ValueError("design.stage_speeds_rpm must have one speed per stage")
        _check_destinations(self.inlet_destinations, "inlet_destinations")
        lengths = {len(d) for d in [self.inlet_destinations] + [s.destinations for s in self.stages] if d is not None}
        if lengths - {len(self.stages) + 2}:
            raise ValueError(f"destinations must have n_stages + 2 = {len(self.stages) + 2} entries")
        return self

    @property
    def n_stages(self) -> int:
        """Number of rotor stages."""
        return len(self.stages)

    def destination_matrix(self) -> np.ndarray | None:
        """One-lag destinations (n + 1, n + 2): rows inlet zone then stages 1..n, last column out; None if absent."""
        if self.inlet_destinations is None or any(s.destinations is None for s in self.stages):
            return None
        return np.array([self.inlet_destinations] + [s.destinations for s in self.stages], dtype=float)

    def compartment_residence_s(self) -> list[float] | None:
        """Steady residence (mean hold-up / mass rate out, s) of the inlet zone and stages 1..n.

        What a table start near this point places (``RunSettings.start_residence_s``): the hold-up is
        this times the new point's feed. None when the run lacks the hold-ups or the rate.
        """
        rate = self.mass_out_rate_kg_s
        hold = [self.inlet_holdup_kg] + [s.mean_holdup_kg for s in self.stages]
        if not rate or any(h is None for h in hold):
            return None
        return [float(h) / float(rate) for h in hold]

    def window_reference(self) -> tuple[float, float] | None:
        """``(holdup_kg, residence_steps)`` of the measurement window: what a filling curve is relative to.

        The window's mean hold-up (inlet zone and stages, ``provenance["stats"]["mean_holdup_kg"]``)
        and the mean residence, in characteristic times, of the chain of the window's one-lag
        destinations (:func:`chain_residence_steps`): the references of
        :func:`msmill.dem.mill.stats.filling_transport`. None when the run lacks either.
        """
        hold = ((self.provenance or {}).get("stats") or {}).get("mean_holdup_kg")
        p = self.destination_matrix()
        if hold is None or p is None:
            return None
        steps = chain_residence_steps(p)
        return (float(hold), steps) if np.isfinite(steps) and float(hold) > 0 else None

    @classmethod
    def from_json(cls, path_or_text: str | Path) -> RunStatistics:
        """Read from a JSON file path or JSON text; errors are one line."""
        from msmill.validate import read_text

        p = Path(path_or_text) if not str(path_or_text).lstrip().startswith("{") else None
        text = read_text(p, str(p), "JSON file") if p is not None else str(path_or_text)
        try:
            data = json.loads(text)
        except json.JSONDecodeError as exc:
            raise MsmillInputError(str(p or "json"), f"line {exc.lineno}", "valid JSON") from None
        return cls.from_dict(data, source=str(p) if p else "statistics")

    @classmethod
    def from_dict(cls, data: dict[str, Any], source: str = "statistics") -> RunStatistics:
        """Validate a plain dict; errors are one line naming the field."""
        version = data.get("schema_version", SCHEMA_VERSION) if isinstance(data, dict) else None
        if version not in READABLE_SCHEMA_VERSIONS:
            raise MsmillInputError(f"{source}.schema_version", version, "1 or 2")
        try:
            return cls.model_validate(data)
        except ValidationError as exc:
            raise from_validation_error(exc, prefix=source) from None


class StageParameterTable(_JsonDocument):
    """Statistics of several DEM runs at one operating point, differing in rock size.

    This is the shipped default source of stage parameters for the mill model
    (``src/msmill/data/stage_parameters/*.json``) until the surrogate exists. The
    model interpolates between runs in (log) rock size and extrapolates outside the
    sizes covered (docs/model.md section 9), reporting the mass share concerned.
    """

    schema_version: Literal[2] = SCHEMA_VERSION
    kind: Literal["stage_parameter_table"] = "stage_parameter_table"
    runs: list[RunStatistics] = Field(min_length=1)
    provenance: dict[str, Any] = Field(default_factory=dict)
    allow_not_steady: bool = False  # accept runs whose outcome is not "steady" (issue 20)

    @model_validator(mode="before")
    @classmethod
    def _upgrade(cls, data: Any) -> Any:
        return _upgraded(data)

    @model_validator(mode="after")
    def _check(self) -> StageParameterTable:
        for r in self.runs:
            if r.outcome not in (None, "steady") and not self.allow_not_steady:
                raise ValueError(f"run at {r.design.size_mm:g} mm is {r.outcome}: not-steady statistics are "
                                 "refused (set allow_not_steady to use them)")
        sizes = [r.design.size_mm for r in self.runs]
        if sizes != sorted(sizes) or len(set(sizes)) != len(sizes):
            raise ValueError(f"runs must have distinct rock sizes in ascending order (got {sizes})")
        n = {r.n_stages for r in self.runs}
        if len(n) != 1:
            raise ValueError(f"all runs must have the same number of stages (got {sorted(n)})")
        return self

    @property
    def sizes_mm(self) -> np.ndarray:
        """Rock sizes of the runs (mm), ascending."""
        return np.array([r.design.size_mm for r in self.runs])

    def run_at(self, size_mm: float) -> RunStatistics | None:
        """The run at rock size ``size_mm`` (to a relative 1e-6), or None."""
        for r in self.runs:
            if abs(r.design.size_mm - size_mm) < 1e-6 * size_mm:
                return r
        return None

    @classmethod
    def from_json(cls, path: str | Path) -> StageParameterTable:
        """Read and validate a table file; errors are one line naming the field."""
        from msmill.validate import read_text

        p = Path(path)
        try:
            data = json.loads(read_text(p, "stage_parameters", "JSON stage-parameter table"))
        except json.JSONDecodeError as exc:
            raise MsmillInputError(str(p), f"line {exc.lineno}", "valid JSON") from None
        if not isinstance(data, dict) or data.get("schema_version") not in READABLE_SCHEMA_VERSIONS:
            got = data.get("schema_version") if isinstance(data, dict) else type(data).__name__
            raise MsmillInputError(f"{p.name}.schema_version", got, "1 or 2")
        try:
            return cls.model_validate(data)
        except ValidationError as exc:
            raise from_validation_error(exc, prefix=p.name) from None


def _upgraded(data: Any) -> Any:
    """A version-1 document as version 2 (stages gain a Poisson ``secondary_count`` on validation)."""
    if isinstance(data, dict) and data.get("schema_version") == 1:
        return {**data, "schema_version": SCHEMA_VERSION}
    return data


@functools.cache
def default_stage_table() -> StageParameterTable:
    """The packaged default stage-parameter table (``msmill/data/stage_parameters/default.json``), read once.

    The DEM's table start and time limits and the model's table provider all read this one file.
    """
    from importlib import resources

    return StageParameterTable.from_json(str(resources.files("msmill") / "data" / "stage_parameters" / "default.json"))

