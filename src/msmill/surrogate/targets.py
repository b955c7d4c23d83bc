"""Stage statistics <-> fixed-length target vectors a Gaussian process can regress.

Every :class:`msmill.stageparams.RunStatistics` becomes one row of targets
(and one row of per-target sampling variances, used as per-point GP noise).
Per stage ``s`` (names ``s<s>.<group>.<i>``):

``streams`` (2)
    ``[kickback, refeed, pass_through]`` is a composition: additive log-ratio
    ``ln(kickback / pass_through), ln(refeed / pass_through)``; parts below
    :data:`ZERO_FRACTION` are replaced by it (multiplicative replacement)
    before the log. Inverse: softmax of ``[y0, y1, 0]``.
``hit`` (1)
    Logit of the primary hit probability (clipped to
    ``[ZERO_FRACTION, 1 - ZERO_FRACTION]``).
``primary_velocity``, ``secondary_velocity`` (``M`` each)
    The fitted Gaussian mixture's quantiles at the fixed probability levels
    :data:`LEVELS` (``(j - 1/2) / M``), as ``q_1`` and ``ln(q_{j+1} - q_j)``
    (monotone by construction). Why not the mixture itself: the DEM fits
    choose ``K`` = 1-4 components by BIC run by run, so mixture parameters are
    not a fixed-length vector, and even with a fixed ``K`` the labelling
    (components sorted by mean) jumps where components cross; quantiles are a
    smooth, fixed-length function of the distribution whatever its ``K``. The
    model's mixture is rebuilt from the quantiles (:func:`mixture_from_quantiles`):
    ``M`` equal-weight components at the quantiles, widths proportional to the
    local quantile spacing.
``count`` (1, or 3 with a count distribution)
    ``ln`` of the mean number of secondary impacts per primary impact. When the
    run carries a ``secondary_count`` distribution (schema v2) also
    ``ln(variance / mean)`` and ``logit(p_zero)``; the count distribution is
    rebuilt from the three (:func:`count_from_summary`).
``region_weights`` (5) and ``region_streams`` (12), only when every run has them
    Additive log-ratios of the 6 region weights and of each region's streams.

Run level (stage ``0``): ``run.log_time.0`` = ``ln(characteristic_time_s)``.

Sampling variances come from the DEM's standard errors by the delta method
(``var(ln x) = (se / x)^2``, ``var(logit p) = (se / (p (1 - p)))^2``,
quantiles ``var(q_p) = p (1 - p) / (n f(q_p)^2)`` with their covariance for
the increments); targets without a standard error get 0 (the GP's white
noise then absorbs their scatter).
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import numpy as np
from scipy import special  # scipy.optimize (0.1 s to import) only in the functions that solve

from msmill.errors import MsmillInputError
from msmill.sampling import default_between_run, statistic_kind
from msmill.stageparams import N_REGIONS, GaussianMixture, RunStatistics, design_inputs

#: Number of quantile levels per velocity distribution.
N_LEVELS = 28


def quantile_levels(n_levels: int = N_LEVELS) -> np.ndarray:
    """The probability levels ``(j - 1/2) / M`` of ``M`` velocity quantiles."""
    return (np.arange(int(n_levels)) + 0.5) / int(n_levels)


#: Probability levels of the velocity quantiles, ``(j - 1/2) / M``.
LEVELS = quantile_levels(N_LEVELS)
#: Floor of fractions and probabilities before log-ratio / logit transforms.
ZERO_FRACTION = 1e-4
#: Floor of the mean secondary count before the log.
MIN_COUNT = 1e-3
#: Largest weight of the lower part of a rebuilt count mixture (keeps the upper part's mean finite).
MAX_COUNT_WEIGHT = 0.99


# ------------------------------------------------------------------ elementary transforms
def alr(parts: np.ndarray) -> np.ndarray:
    """Additive log-ratio of compositions (last axis, last part as divisor), zeros replaced."""
    x = np.maximum(np.asarray(parts, dtype=float), ZERO_FRACTION)
    x = x / x.sum(axis=-1, keepdims=True)
    return np.log(x[..., :-1] / x[..., -1:])


def alr_inverse(y: np.ndarray) -> np.ndarray:
    """Inverse of :func:`alr`: softmax of ``[y, 0]`` (rows sum to 1)."""
    y = np.asarray(y, dtype=float)
    z = np.concatenate([y, np.zeros((*y.shape[:-1], 1))], axis=-1)
    return special.softmax(z, axis=-1)


def logit(p: np.ndarray) -> np.ndarray:
    """Logit of a probability clipped to ``[ZERO_FRACTION, 1 - ZERO_FRACTION]``."""
    return special.logit(np.clip(np.asarray(p, dtype=float), ZERO_FRACTION, 1 - ZERO_FRACTION))


def mixture_quantiles(weights, means, sigmas, levels=LEVELS) -> np.ndarray:
    """Quantiles of a 1-D Gaussian mixture at ``levels`` (same unit as ``means``)."""
    w, mu, sd = (np.asarray(a, dtype=float) for a in (weights, means, sigmas))
    m = w > 0
    w, mu, sd = w[m] / w[m].sum(), mu[m], sd[m]
    lo, hi = float(np.min(mu - 8 * sd)), float(np.max(mu + 8 * sd))

    def cdf(v: float) -> float:
        return float(np.dot(w, special.ndtr((v - mu) / sd)))

    from scipy import optimize

    return np.array([optimize.brentq(lambda v, p=p: cdf(v) - p, lo, hi, xtol=1e-10) for p in levels])


def quantile_vector(q: np.ndarray) -> np.ndarray:
    """Quantiles (..., M) -> ``[q_1, ln(q_2 - q_1), ...]`` (increments floored at 1e-9)."""
    q = np.asarray(q, dtype=float)
    return np.concatenate([q[..., :1], np.log(np.maximum(np.diff(q, axis=-1), 1e-9))], axis=-1)


def quantiles_from_vector(z: np.ndarray) -> np.ndarray:
    """Inverse of :func:`quantile_vector` (monotone quantiles)."""
    z = np.asarray(z, dtype=float)
    return np.concatenate([z[..., :1], z[..., :1] + np.cumsum(np.exp(z[..., 1:]), axis=-1)], axis=-1)


def _spacing(q: np.ndarray) -> np.ndarray:
    d = np.diff(q, axis=-1)
    h = np.empty_like(q)
    h[..., 1:-1] = 0.5 * (d[..., 1:] + d[..., :-1])
    h[..., 0] = d[..., 0]
    h[..., -1] = d[..., -1]
    return h


def normal_pdf(x: np.ndarray) -> np.ndarray:
    """The standard normal density, as ``scipy.stats.norm.pdf`` computes it (without importing scipy.stats,
    about a second of every command's start; ``norm.cdf`` and ``norm.ppf`` are ``special.ndtr`` and
    ``special.ndtri``)."""
    return np.exp(-x**2 / 2.0) / np.sqrt(2 * np.pi)


#: Width factor ``c`` of :func:`mixture_from_quantiles` (``sigma_j = c * spacing_j``) at
#: :data:`N_LEVELS` levels: the value :func:`least_kl_sigma_factor` returns, stored so that a command
#: does not solve for it (and import ``scipy.optimize``, 0.13 s together) on every start;
#: ``tests/surrogate/test_targets.py`` checks the two are the same float.
SIGMA_FACTOR = 0.9756139131749254
#: :data:`SIGMA_FACTOR` for other numbers of levels a surrogate may be built with (``TargetLayout.n_levels``),
#: the same stored floats (``tests/surrogate/test_targets.py`` recomputes each)
SIGMA_FACTORS = {N_LEVELS: SIGMA_FACTOR, 36: 0.9875837017566196}


def least_kl_sigma_factor(n_levels: int = N_LEVELS) -> float:
    """Width factor ``c`` with which a normal distribution survives the quantile round trip
    (:func:`mixture_from_quantiles` of its quantiles at ``n_levels`` levels, :func:`quantile_levels`) with
    the least KL divergence (quadrature on a grid; bounded Brent search over 0.2-2)."""
    q = special.ndtri(quantile_levels(n_levels))
    h = _spacing(q)
    v = np.linspace(-8, 8, 4001)
    p = normal_pdf(v)

    def kl(c: float) -> float:
        r = np.mean(normal_pdf((v[:, None] - q) / (c * h)) / (c * h), axis=1)
        return float(np.trapezoid(p * np.log(p / np.maximum(r, 1e-300)), v))

    from scipy import optimize

    return float(optimize.minimize_scalar(kl, bounds=(0.2, 2.0), method="bounded").x)


def sigma_factor(n_levels: int = N_LEVELS) -> float:
    """Width factor ``c`` of :func:`mixture_from_quantiles` at ``n_levels`` levels (:data:`SIGMA_FACTORS`;
    solved for when not stored: a study of other levels, no surrogate's)."""
    c = SIGMA_FACTORS.get(int(n_levels))
    if c is None:
        c = least_kl_sigma_factor(n_levels)
    return c


def mixture_from_quantiles(q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rebuild a Gaussian mixture from quantiles at :data:`LEVELS`.

    Parameters
    ----------
    q : ndarray, shape (..., M)
        Ascending quantiles (m/s).

    Returns
    -------
    weights, means_m_s, sigmas_m_s : ndarray, shape (..., M)
        Equal weights ``1/M``, means at the quantiles, sigmas
        ``sigma_factor(M) * local spacing`` (floored at 1e-6 m/s).
    """
    q = np.asarray(q, dtype=float)
    w = np.full(q.shape, 1.0 / q.shape[-1])
    sd = np.maximum(sigma_factor(q.shape[-1]) * _spacing(q), 1e-6)
    return w, q.copy(), sd


def quantile_noise_var(weights, means, sigmas, n: int, levels=LEVELS) -> np.ndarray:
    """Sampling variance of :func:`quantile_vector` of a mixture estimated from ``n`` draws."""
    if n <= 1:
        return np.zeros(len(levels))
    q = mixture_quantiles(weights, means, sigmas, levels)
    g = GaussianMixture(weights=list(np.asarray(weights) / np.sum(weights)), means_m_s=list(means),
                        sigmas_m_s=list(sigmas))
    f = np.maximum(g.pdf(q), 1e-12)
    p = np.asarray(levels)
    var_q = p * (1 - p) / (n * f * f)
    cov = p[:-1] * (1 - p[1:]) / (n * f[:-1] * f[1:])
    d = np.maximum(np.diff(q), 1e-9)
    var_d = np.maximum(var_q[:-1] + var_q[1:] - 2 * cov, 0.0) / d**2
    return np.concatenate([var_q[:1], var_d])


def count_from_summary(mean: float, var_ratio: float, p_zero: float) -> tuple[np.ndarray, np.ndarray]:
    """A Poisson mixture (<= 2 components) with a given mean, variance/mean and zero fraction.

    With ``var_ratio <= 1`` the answer is one Poisson of the mean. Otherwise
    the two-point mixing distribution with the requested mean and variance of
    the rate is searched over its weight (lower part up to
    :data:`MAX_COUNT_WEIGHT`) for the zero fraction (closest achievable value
    when the target is out of reach: mean and variance are always kept).

    Returns
    -------
    weights, means : ndarray
        Mixture weights and Poisson means.
    """
    m = max(float(mean), MIN_COUNT)
    s2 = (float(var_ratio) - 1.0) * m  # variance of the Poisson rate
    if s2 <= 1e-12:
        return np.array([1.0]), np.array([m])
    w_lo = s2 / (s2 + m * m) + 1e-12

    def parts(w: float) -> tuple[float, float]:
        return m - np.sqrt(s2 * (1 - w) / w), m + np.sqrt(s2 * w / (1 - w))

    def p0(w: float) -> float:
        a, b = parts(w)
        return w * np.exp(-max(a, 0.0)) + (1 - w) * np.exp(-b)

    grid = np.linspace(w_lo, MAX_COUNT_WEIGHT, 400)  # the upper part's weight >= 1 %
    err = np.array([p0(w) - p_zero for w in grid])
    sign = np.flatnonzero(np.sign(err[:-1]) != np.sign(err[1:]))
    if sign.size:
        i = int(sign[0])
        from scipy import optimize

        w = optimize.brentq(lambda x: p0(x) - p_zero, grid[i], grid[i + 1])
    else:
        w = float(grid[int(np.argmin(np.abs(err)))])
    a, b = parts(w)
    return np.array([w, 1 - w]), np.array([max(a, 0.0), b])


def count_arrays_from_summary(mean: np.ndarray, var_ratio: np.ndarray, p_zero: np.ndarray,
                              n_grid: int = 400) -> tuple[np.ndarray, np.ndarray]:
    """Vectorised :func:`count_from_summary` over arrays of any shape ``(...)``.

    The mixing weight is the grid point closest to the requested zero
    fraction, refined by linear interpolation where ``p0(w) - p_zero`` changes
    sign (the scalar version refines by Brent's method; they agree to the
    grid's interpolation error). Mean and variance are kept exactly.

    Returns
    -------
    weights, means : ndarray, shape (..., 2)
        Two-component Poisson mixtures (a one-Poisson case has weights (1, 0)).
    """
    m = np.maximum(np.asarray(mean, dtype=float), MIN_COUNT)[..., None]
    s2 = (np.asarray(var_ratio, dtype=float)[..., None] - 1.0) * m
    pz = np.asarray(p_zero, dtype=float)[..., None]
    over = s2 > 1e-12
    s2 = np.where(over, s2, 1e-12)
    w_lo = s2 / (s2 + m * m) + 1e-12
    t = np.linspace(0.0, 1.0, n_grid)
    w = w_lo + (MAX_COUNT_WEIGHT - w_lo) * t  # (..., G)
    a = m - np.sqrt(s2 * (1 - w) / w)
    b = m + np.sqrt(s2 * w / (1 - w))
    err = w * np.exp(-np.maximum(a, 0.0)) + (1 - w) * np.exp(-b) - pz
    change = np.sign(err[..., :-1]) != np.sign(err[..., 1:])
    first = np.argmax(change, axis=-1)
    has = change.any(axis=-1)
    i_best = np.argmin(np.abs(err), axis=-1)
    e0 = np.take_along_axis(err, first[..., None], -1)[..., 0]
    e1 = np.take_along_axis(err, first[..., None] + 1, -1)[..., 0]
    w0 = np.take_along_axis(w, first[..., None], -1)[..., 0]
    w1 = np.take_along_axis(w, first[..., None] + 1, -1)[..., 0]
    w_root = w0 + (w1 - w0) * e0 / np.where(e0 == e1, 1.0, e0 - e1)
    w_pick = np.where(has, w_root, np.take_along_axis(w, i_best[..., None], -1)[..., 0])
    m0, s20 = m[..., 0], s2[..., 0]
    lo = np.maximum(m0 - np.sqrt(s20 * (1 - w_pick) / w_pick), 0.0)
    hi = m0 + np.sqrt(s20 * w_pick / (1 - w_pick))
    one = ~over[..., 0]
    weights = np.stack([np.where(one, 1.0, w_pick), np.where(one, 0.0, 1 - w_pick)], axis=-1)
    means = np.stack([np.where(one, m0, lo), np.where(one, m0, hi)], axis=-1)
    return weights, means


def build_count_distribution(weights: np.ndarray, means: np.ndarray) -> Any:
    """A ``msmill.stageparams.CountDistribution`` when that class exists, else a plain dict.

    MERGE NOTE: issue 10 adds ``CountDistribution`` (``weights``, ``means``,
    ``family``, ``params``) to :mod:`msmill.stageparams`; this is the one place
    that constructs it.
    """
    import msmill.stageparams as sp

    cls = getattr(sp, "CountDistribution", None)
    d = {"weights": [float(x) for x in weights], "means": [float(x) for x in means]}
    if cls is None:
        return d
    return cls(**d, family="poisson_mixture", params={})


def _count_summary(stage: Any) -> tuple[float, float] | None:
    """``(variance / mean, p_zero)`` of a stage's count distribution, if it has one."""
    cd = getattr(stage, "secondary_count", None)
    if cd is None:
        return None
    mean = float(cd.mean() if callable(cd.mean) else cd.mean)
    var = float(cd.variance() if callable(cd.variance) else cd.variance)
    pz = float(cd.p_zero() if callable(cd.p_zero) else cd.p_zero)
    return var / max(mean, MIN_COUNT), pz


# ------------------------------------------------------------------ the target layout
@dataclass(frozen=True)
class TargetLayout:
    """Which targets exist and where they sit in a target row.

    Attributes
    ----------
    n_stages : int
        Number of rotor stages.
    with_dispersion : bool
        Count targets include ``ln(var/mean)`` and ``logit(p_zero)``.
    with_regions : bool
        Region weights and region streams are targets.
    with_destinations : bool
        One-lag destinations (the DEM transition matrix of the
        ``dem_matrix`` transport: every stage's row and the inlet zone's, as
        additive log-ratios of their ``n + 2`` fractions) are targets.
    """

    n_stages: int
    with_dispersion: bool = False
    with_regions: bool = False
    with_destinations: bool = False
    n_levels: int = N_LEVELS
    names: tuple[str, ...] = field(init=False)

    def __post_init__(self) -> None:
        if self.n_levels not in SIGMA_FACTORS:
            raise MsmillInputError("n_levels", self.n_levels, "one of " + ", ".join(map(str, sorted(SIGMA_FACTORS)))
                                   + " (quantile levels per velocity distribution with a stored width factor)")
        names = []
        for s in range(1, self.n_stages + 1):
            for group, n in self.groups():
                names += [f"s{s}.{group}.{i}" for i in range(n)]
        if self.with_destinations:
            names += [f"run.inlet_destinations.{i}" for i in range(self.n_stages + 1)]
        names.append("run.log_time.0")
        object.__setattr__(self, "names", tuple(names))

    @property
    def levels(self) -> np.ndarray:
        """Probability levels of the velocity quantiles (:func:`quantile_levels`)."""
        return quantile_levels(self.n_levels)

    @property
    def inlet_slice(self) -> slice:
        """Position of the inlet zone's destinations (run-level) in a target row."""
        start = self.n_stages * self.n_per_stage
        return slice(start, start + (self.n_stages + 1 if self.with_destinations else 0))

    def groups(self) -> list[tuple[str, int]]:
        """Per-stage target groups and their lengths."""
        g = [("streams", 2), ("hit", 1), ("primary_velocity", self.n_levels), ("secondary_velocity", self.n_levels),
             ("count", 3 if self.with_dispersion else 1)]
        if self.with_regions:
            g += [("region_weights", N_REGIONS - 1), ("region_streams", 2 * N_REGIONS)]
        if self.with_destinations:
            g += [("destinations", self.n_stages + 1)]
        return g

    @property
    def n_per_stage(self) -> int:
        """Targets per stage."""
        return sum(n for _, n in self.groups())

    @property
    def n_targets(self) -> int:
        """Length of a target row."""
        return len(self.names)

    @cached_property
    def stage_of(self) -> np.ndarray:
        """Stage of every target (0 for run-level targets; read-only, computed once)."""
        out = np.array([0 if n.startswith("run.") else int(n.split(".")[0][1:]) for n in self.names])
        out.setflags(write=False)
        return out

    def slices(self, stage: int) -> dict[str, slice]:
        """Position of each group of ``stage`` in a target row."""
        out, i = {}, (stage - 1) * self.n_per_stage
        for group, n in self.groups():
            out[group] = slice(i, i + n)
            i += n
        return out

    def to_dict(self) -> dict[str, Any]:
        """Plain dict for JSON."""
        return {"n_stages": self.n_stages, "with_dispersion": self.with_dispersion,
                "with_regions": self.with_regions, "with_destinations": self.with_destinations,
                "levels": [float(p) for p in self.levels]}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> TargetLayout:
        """Inverse of :meth:`to_dict` (the quantile levels must be ``(j - 1/2) / M`` for an ``M`` of
        :data:`SIGMA_FACTORS`)."""
        got = np.asarray(d.get("levels", LEVELS), dtype=float)
        if got.ndim != 1 or got.size not in SIGMA_FACTORS or not np.allclose(got, quantile_levels(got.size)):
            raise MsmillInputError("surrogate.targets.levels", f"{got.size} quantile levels",
                                   " or ".join(f"the {m} levels (j - 1/2)/{m}" for m in sorted(SIGMA_FACTORS))
                                   + " of this version (a surrogate file from another version: retrain it)")
        return cls(int(d["n_stages"]), bool(d["with_dispersion"]), bool(d["with_regions"]),
                   bool(d.get("with_destinations", False)), int(got.size))


def _composition_targets(parts: Any, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Additive log-ratios of a composition measured from ``n`` tags, with their (delta-method) variance.

    ``var(ln p_i) ~ (1 - p_i) / (n p_i)``; a log-ratio adds the divisor's; parts at
    zero count as ``ZERO_FRACTION``.
    """
    p = np.maximum(np.asarray(parts, dtype=float), ZERO_FRACTION)
    p = p / p.sum()
    v = (1.0 - p) / (max(int(n), 1) * p)
    return alr(p), v[:-1] + v[-1]


def _mixture_targets(g: GaussianMixture, n: int, levels: np.ndarray = LEVELS) -> tuple[np.ndarray, np.ndarray]:
    q = mixture_quantiles(g.weights, g.means_m_s, g.sigmas_m_s, levels)
    return quantile_vector(q), quantile_noise_var(g.weights, g.means_m_s, g.sigmas_m_s, n, levels)


def quantile_scatter(runs: list[RunStatistics]) -> tuple[float, int]:
    """Mean squared replica z-score of the velocity-quantile targets of feed-seed replicas of one point.

    Each replica's targets (:func:`_mixture_targets`) with their iid sampling variance: the mean of
    ``z^2`` (:func:`msmill.sampling.replica_z_scores`) is the factor by which the replicas actually scatter
    over that variance (1: the iid formula is right). Returns the factor and the number of z-scores.
    """
    from msmill.sampling import replica_z_scores

    z: list[np.ndarray] = []
    for s in range(len(runs[0].stages)):
        for grp, n_attr in (("primary_velocity", "n_primary_impacts"), ("secondary_velocity", "n_secondary_impacts")):
            ys, vs = zip(*(_mixture_targets(getattr(r.stages[s], grp), getattr(r.stages[s], n_attr)) for r in runs),
                         strict=True)
            ys, vs = np.array(ys), np.array(vs)
            z.extend(replica_z_scores(ys[:, j], np.sqrt(vs[:, j])) for j in range(ys.shape[1]))
    zz = np.concatenate(z) if z else np.zeros(0)
    return (float(np.mean(zz**2)) if zz.size else float("nan")), int(zz.size)


def honest_errors(run: RunStatistics) -> dict[int, dict[str, float]]:
    """Per stage, the sampling errors of a run as the runs report them since issue 36.

    A run whose statistics name their error estimator (``provenance.stats.error_estimator``) already has
    them. An older run has five batch means only (its series were not kept): each error of a kind with a
    between-run law becomes ``sqrt((f se)^2 + sigma_b^2)`` (:meth:`msmill.sampling.BetweenRunVariance.
    legacy_total`: ``f`` the replicas' mean ratio of the two estimators, ``sigma_b`` the between-run
    deviation at the run's rock size).
    """
    if "error_estimator" in ((run.provenance or {}).get("stats") or {}):
        return {st.stage: dict(st.sampling_error) for st in run.stages}
    cal = default_between_run()
    size = run.design.size_mm
    out = {}
    for st in run.stages:
        se = dict(st.sampling_error)
        for k, v in st.sampling_error.items():
            kind = statistic_kind(k)
            if kind is not None and k in STAT_VALUE:
                se[k] = cal.legacy_total(kind, size, STAT_VALUE[k](st), v)
        out[st.stage] = se
    return out


#: statistic name -> its value in a stage (the scale of a relative between-run deviation)
STAT_VALUE = {"kickback": lambda st: st.kickback, "refeed": lambda st: st.refeed,
              "pass_through": lambda st: st.pass_through,
              "primary_hit_probability": lambda st: st.primary_hit_probability,
              "primary_velocity_mean_m_s": lambda st: st.primary_velocity.mean(),
              "secondary_velocity_mean_m_s": lambda st: st.secondary_velocity.mean(),
              "secondary_lambda": lambda st: st.secondary_lambda}


def encode_run(run: RunStatistics, layout: TargetLayout) -> tuple[np.ndarray, np.ndarray]:
    """Target row and per-target sampling variance of one run.

    Returns
    -------
    y, noise_var : ndarray, shape (n_targets,)
    """
    y = np.zeros(layout.n_targets)
    nv = np.zeros(layout.n_targets)
    errors = honest_errors(run)
    q_factor = default_between_run().quantile_variance_factor(run.design.size_mm)
    for st in run.stages:
        sl = layout.slices(st.stage)
        se = errors[st.stage]
        parts = np.maximum(st.streams, ZERO_FRACTION)
        y[sl["streams"]] = alr(st.streams)
        rel = np.array([se.get(k, 0.0) for k in ("kickback", "refeed", "pass_through")]) / parts
        nv[sl["streams"]] = rel[:2] ** 2 + rel[2] ** 2
        p = float(np.clip(st.primary_hit_probability, ZERO_FRACTION, 1 - ZERO_FRACTION))
        y[sl["hit"]] = logit(p)
        nv[sl["hit"]] = (se.get("primary_hit_probability", 0.0) / (p * (1 - p))) ** 2
        for grp, n in (("primary_velocity", st.n_primary_impacts), ("secondary_velocity", st.n_secondary_impacts)):
            y[sl[grp]], nv[sl[grp]] = _mixture_targets(getattr(st, grp), n, layout.levels)
            nv[sl[grp]] *= q_factor
        lam = max(st.secondary_lambda, MIN_COUNT)
        c = sl["count"]
        y[c.start] = np.log(lam)
        nv[c.start] = (se.get("secondary_lambda", 0.0) / lam) ** 2
        if layout.with_dispersion:
            ratio, pz = _count_summary(st)
            pz = float(np.clip(pz, ZERO_FRACTION, 1 - ZERO_FRACTION))
            n = max(st.n_primary_impacts, 2)
            y[c.start + 1] = np.log(max(ratio, 1e-3))
            y[c.start + 2] = logit(pz)
            nv[c.start + 1] = 2.0 / (n - 1) + nv[c.start]
            nv[c.start + 2] = 1.0 / (n * pz * (1 - pz))
        if layout.with_regions:
            y[sl["region_weights"]] = alr(np.asarray(st.region_weights))
            y[sl["region_streams"]] = alr(np.asarray(st.region_streams)).ravel()
        if layout.with_destinations:
            y[sl["destinations"]], nv[sl["destinations"]] = _composition_targets(st.destinations,
                                                                                  st.n_transport_samples)
    if layout.with_destinations:
        n_inlet = max(int(run.stages[0].n_transport_samples), 1)  # the inlet zone's tags are not counted apart
        y[layout.inlet_slice], nv[layout.inlet_slice] = _composition_targets(run.inlet_destinations, n_inlet)
    y[-1] = np.log(run.characteristic_time_s)
    return y, nv


@dataclass(frozen=True)
class StagePrediction:
    """Decoded stage statistics at a set of points (arrays over leading axis ``P``).

    Attributes
    ----------
    streams : ndarray (P, 3)
    hit_probability : ndarray (P,)
    primary_velocity, secondary_velocity : tuple of ndarray (P, M)
        ``(weights, means_m_s, sigmas_m_s)`` of the rebuilt mixtures.
    primary_quantiles_m_s, secondary_quantiles_m_s : ndarray (P, M)
    secondary_lambda : ndarray (P,)
    count_var_ratio, count_p_zero : ndarray (P,) or None
    region_weights : ndarray (P, 6) or None
    region_streams : ndarray (P, 6, 3) or None
    """

    streams: np.ndarray
    hit_probability: np.ndarray
    primary_velocity: tuple[np.ndarray, np.ndarray, np.ndarray]
    secondary_velocity: tuple[np.ndarray, np.ndarray, np.ndarray]
    primary_quantiles_m_s: np.ndarray
    secondary_quantiles_m_s: np.ndarray
    secondary_lambda: np.ndarray
    count_var_ratio: np.ndarray | None = None
    count_p_zero: np.ndarray | None = None
    region_weights: np.ndarray | None = None
    region_streams: np.ndarray | None = None
    destinations: np.ndarray | None = None

    def count_distribution(self, i: int) -> Any:
        """The rebuilt count distribution at point ``i`` (needs the dispersion targets)."""
        if self.count_var_ratio is None:
            return build_count_distribution(np.array([1.0]), np.array([self.secondary_lambda[i]]))
        w, m = count_from_summary(self.secondary_lambda[i], self.count_var_ratio[i], self.count_p_zero[i])
        return build_count_distribution(w, m)


def decode_inlet_destinations(y: np.ndarray, layout: TargetLayout) -> np.ndarray | None:
    """The inlet zone's one-lag destinations (P, n + 2) from target rows ``y`` (P, n_targets), if regressed."""
    if not layout.with_destinations:
        return None
    return alr_inverse(np.atleast_2d(np.asarray(y, dtype=float))[:, layout.inlet_slice])


def decode_stage(y: np.ndarray, layout: TargetLayout, stage: int) -> StagePrediction:
    """Decode the targets of ``stage`` from target rows ``y`` (P, n_targets)."""
    y = np.atleast_2d(np.asarray(y, dtype=float))
    sl = layout.slices(stage)
    qp = quantiles_from_vector(y[:, sl["primary_velocity"]])
    qs = quantiles_from_vector(y[:, sl["secondary_velocity"]])
    c = sl["count"]
    kw: dict[str, Any] = {}
    if layout.with_dispersion:
        kw["count_var_ratio"] = np.exp(y[:, c.start + 1])
        kw["count_p_zero"] = special.expit(y[:, c.start + 2])
    if layout.with_regions:
        kw["region_weights"] = alr_inverse(y[:, sl["region_weights"]])
        kw["region_streams"] = alr_inverse(y[:, sl["region_streams"]].reshape(-1, N_REGIONS, 2))
    if layout.with_destinations:
        kw["destinations"] = alr_inverse(y[:, sl["destinations"]])
    return StagePrediction(
        streams=alr_inverse(y[:, sl["streams"]]),
        hit_probability=special.expit(y[:, sl["hit"]][:, 0]),
        primary_velocity=mixture_from_quantiles(qp), secondary_velocity=mixture_from_quantiles(qs),
        primary_quantiles_m_s=qp, secondary_quantiles_m_s=qs,
        secondary_lambda=np.exp(y[:, c.start]), **kw)


# ------------------------------------------------------------------ training set
class StoredRuns(Sequence):
    """The runs of a saved training set, read from their documents on first use.

    Prediction never looks at a surrogate's training runs (scoring and cost
    models do): parsing the shipped surrogate's 98 run documents took about a
    fifth of a second of every ``msmill predict``.

    Parameters
    ----------
    docs : list of dict
        The runs' ``RunStatistics`` documents.
    source : str
        Where they come from (named in an error).
    """

    def __init__(self, docs: list[dict[str, Any]], source: str) -> None:
        self._docs, self._source = docs, source
        self._runs: tuple[RunStatistics, ...] | None = None

    def _parsed(self) -> tuple[RunStatistics, ...]:
        if self._runs is None:
            self._runs = tuple(RunStatistics.from_dict(d, source=self._source) for d in self._docs)
        return self._runs

    def __len__(self) -> int:
        return len(self._docs)

    def __getitem__(self, i: Any) -> Any:
        return self._parsed()[i]

    def __iter__(self) -> Iterator[RunStatistics]:
        return iter(self._parsed())

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Sequence) and tuple(self) == tuple(other)

    __hash__ = None  # type: ignore[assignment]


def _design_label(run: RunStatistics) -> str:
    d = run.design
    return f"{d.size_mm:g}mm-{d.feed_tph:g}tph-{d.speed_rpm:g}rpm-{d.gate_deg:g}deg"


@dataclass(frozen=True)
class TrainingSet:
    """Design points, targets and sampling variances of a set of DEM runs.

    Attributes
    ----------
    X : ndarray (R, 4)
        ``size_mm, feed_tph, speed_rpm, gate_deg`` of every run.
    Y, noise_var : ndarray (R, T)
        Targets and their sampling variances (see the module docstring).
    layout : TargetLayout
    speed_factors : ndarray (S,)
        Stage speed / upper-stage speed of the training recipe (e.g. ``[1, 1, 1, 1, 2]``).
    run_ids : tuple of str
        Identifier of every run (from its provenance, else its design point).
    runs : sequence of RunStatistics
        The runs themselves (kept for accuracy scoring; a loaded surrogate's are
        :class:`StoredRuns`, parsed on first use).
    """

    X: np.ndarray
    Y: np.ndarray
    noise_var: np.ndarray
    layout: TargetLayout
    speed_factors: np.ndarray
    run_ids: tuple[str, ...]
    runs: Sequence[RunStatistics] = ()

    @property
    def n_runs(self) -> int:
        """Number of runs ``R``."""
        return int(self.X.shape[0])

    @classmethod
    def from_runs(cls, runs: Iterable[RunStatistics], n_levels: int = N_LEVELS) -> TrainingSet:
        """Encode runs (any iterable of :class:`RunStatistics`, e.g. a store query's result), with
        ``n_levels`` quantiles per velocity distribution."""
        runs = tuple(runs)
        if not runs:
            raise MsmillInputError("runs", 0, "at least one RunStatistics")
        n_st = {r.n_stages for r in runs}
        if len(n_st) != 1:
            raise MsmillInputError("runs.n_stages", sorted(n_st), "the same number of stages in every run")
        factors = np.array([np.asarray(r.design.stage_speeds_rpm) / max(r.design.speed_rpm, 1e-9) for r in runs])
        if np.ptp(factors, axis=0).max() > 0.01:
            raise MsmillInputError("runs.stage_speeds_rpm", "mixed speed recipes",
                                   "one recipe (stage speed / upper speed) for all runs")
        layout = TargetLayout(
            n_st.pop(),
            with_dispersion=all(getattr(s, "secondary_count", None) is not None for r in runs for s in r.stages),
            with_regions=all(s.region_weights is not None and s.region_streams is not None
                             for r in runs for s in r.stages),
            with_destinations=all(r.inlet_destinations is not None and all(s.destinations is not None
                                                                             for s in r.stages) for r in runs),
            n_levels=n_levels)
        rows = [encode_run(r, layout) for r in runs]
        X = design_inputs(r.design for r in runs)
        ids = tuple(str(r.provenance.get("run_id") or _design_label(r)) for r in runs)
        return cls(X, np.array([y for y, _ in rows]), np.array([v for _, v in rows]), layout,
                   factors.mean(axis=0), ids, runs)
