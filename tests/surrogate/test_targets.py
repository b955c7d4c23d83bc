"""Target transforms round-trip; the rebuilt distributions stay close to the fitted ones."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import stats

from msmill.errors import MsmillInputError
from msmill.surrogate import targets as tg
from msmill.surrogate.accuracy import mixture_kl, poisson_kl

fractions = st.lists(st.floats(0.01, 1.0), min_size=3, max_size=3).map(lambda v: np.array(v) / sum(v))


@given(fractions)
def test_alr_round_trip(parts):
    np.testing.assert_allclose(tg.alr_inverse(tg.alr(parts)), parts, rtol=1e-9, atol=1e-12)


@given(st.floats(1e-3, 1 - 1e-3))
def test_logit_round_trip(p):
    from scipy.special import expit

    assert expit(tg.logit(p)) == pytest.approx(p, rel=1e-9)


@given(st.lists(st.floats(-20, 80), min_size=tg.N_LEVELS, max_size=tg.N_LEVELS, unique=True))
def test_quantile_vector_round_trip_and_monotone(values):
    q = np.sort(values)
    if np.min(np.diff(q)) < 1e-6:
        return
    z = tg.quantile_vector(q)
    np.testing.assert_allclose(tg.quantiles_from_vector(z), q, rtol=1e-9, atol=1e-9)
    # any vector decodes to ascending quantiles
    assert np.all(np.diff(tg.quantiles_from_vector(z + 0.3 * np.sin(np.arange(z.size)))) > 0)


def test_normal_survives_the_quantile_representation():
    q = tg.mixture_quantiles([1.0], [20.0], [4.0])
    np.testing.assert_allclose(q, stats.norm.ppf(tg.LEVELS, 20.0, 4.0), atol=1e-6)
    rebuilt = tg.mixture_from_quantiles(q)
    assert mixture_kl(([1.0], [20.0], [4.0]), rebuilt) < 0.01
    q2 = tg.mixture_quantiles(*rebuilt)
    np.testing.assert_allclose(q2[1:-1], q[1:-1], atol=0.04 * 4.0)  # interior: 4 % of a sigma
    np.testing.assert_allclose(q2, q, atol=0.1 * 4.0)  # outermost levels: 10 % of a sigma


def test_bimodal_mixture_survives_the_quantile_representation():
    g = ([0.6, 0.4], [10.0, 30.0], [3.0, 5.0])
    assert mixture_kl(g, tg.mixture_from_quantiles(tg.mixture_quantiles(*g))) < 0.03


def _moments(w, m):
    k = np.arange(600)
    pmf = np.sum(w * stats.poisson.pmf(k[:, None], m), axis=1)
    mu = float(pmf @ k)
    return mu, float(pmf @ k**2 - mu**2), float(pmf[0])


@settings(deadline=None, max_examples=40)
@given(st.floats(0.3, 8.0), st.floats(1.05, 3.0), st.floats(0.0, 1.0))
def test_count_from_summary_reproduces_mean_variance_zero_fraction(mean, ratio, frac):
    # the reachable zero fractions: the two ends of the search (targets 0 and 1 are out of reach)
    lo, hi = (_moments(*tg.count_from_summary(mean, ratio, t))[2] for t in (0.0, 1.0))
    p0 = lo + (0.02 + 0.96 * frac) * (hi - lo)
    mu, var, got_p0 = _moments(*tg.count_from_summary(mean, ratio, p0))
    assert mu == pytest.approx(mean, rel=1e-6)
    assert var / mu == pytest.approx(ratio, rel=1e-5)
    assert got_p0 == pytest.approx(p0, abs=1e-6)


def test_count_without_overdispersion_is_poisson():
    w, m = tg.count_from_summary(2.5, 0.9, 0.1)
    assert list(w) == [1.0] and m[0] == pytest.approx(2.5)


def test_encode_decode_run_round_trip(table_runs):
    layout = tg.TargetLayout(table_runs[0].n_stages)
    for run in table_runs[::2]:
        y, nv = tg.encode_run(run, layout)
        assert y.shape == nv.shape == (layout.n_targets,) and np.all(nv >= 0)
        for st_ in run.stages:
            d = tg.decode_stage(y, layout, st_.stage)
            np.testing.assert_allclose(d.streams[0], st_.streams, atol=1e-3)
            assert d.hit_probability[0] == pytest.approx(st_.primary_hit_probability, rel=1e-9)
            assert d.secondary_lambda[0] == pytest.approx(st_.secondary_lambda, rel=1e-9)
            q = tg.mixture_quantiles(st_.primary_velocity.weights, st_.primary_velocity.means_m_s,
                                     st_.primary_velocity.sigmas_m_s)
            np.testing.assert_allclose(d.primary_quantiles_m_s[0], q, rtol=1e-9)
        assert np.exp(y[-1]) == pytest.approx(run.characteristic_time_s)


def test_noise_grows_as_samples_shrink():
    a = tg.quantile_noise_var([1.0], [20.0], [4.0], 1000)
    b = tg.quantile_noise_var([1.0], [20.0], [4.0], 100)
    np.testing.assert_allclose(b, 10 * a, rtol=1e-9)
    # the first quantile's variance is the textbook p(1-p)/(n f^2)
    p = tg.LEVELS[0]
    f = stats.norm.pdf(stats.norm.ppf(p, 20.0, 4.0), 20.0, 4.0)
    assert a[0] == pytest.approx(p * (1 - p) / (1000 * f * f), rel=1e-6)


def test_poisson_kl_closed_form():
    k = np.arange(200)
    p, q = stats.poisson.pmf(k, 3.0), stats.poisson.pmf(k, 4.5)
    assert poisson_kl(3.0, 4.5) == pytest.approx(float(np.sum(p * np.log(p / q))), rel=1e-9)


class _Count:
    """Duck-typed stand-in for issue 10's CountDistribution: a 50/50 Poisson mixture."""

    def __init__(self, lam: float) -> None:
        self.weights, self.means = [0.5, 0.5], [0.5 * lam, 1.5 * lam]
        self.mean = lam
        self.variance = lam + 0.25 * lam**2
        self.p_zero = 0.5 * (np.exp(-0.5 * lam) + np.exp(-1.5 * lam))


class _WithCount:
    """A stage (or run) with a ``secondary_count`` added; everything else delegated."""

    def __init__(self, inner, **extra) -> None:
        self._inner, self._extra = inner, extra

    def __getattr__(self, name):
        return self._extra[name] if name in self._extra else getattr(self._inner, name)


def test_dispersion_targets_when_runs_carry_a_count_distribution(table_runs):
    run = table_runs[0]
    stages = [_WithCount(s, secondary_count=_Count(s.secondary_lambda)) for s in run.stages]
    layout = tg.TargetLayout(run.n_stages, with_dispersion=True)
    y, nv = tg.encode_run(_WithCount(run, stages=stages), layout)
    assert np.all(np.isfinite(nv))
    for s in stages:
        d = tg.decode_stage(y, layout, s.stage)
        c = s.secondary_count
        assert d.count_var_ratio[0] == pytest.approx(c.variance / c.mean, rel=1e-9)
        assert d.count_p_zero[0] == pytest.approx(c.p_zero, rel=1e-9)
        dist = d.count_distribution(0)
        m = np.asarray(dist["means"] if isinstance(dist, dict) else dist.means)
        np.testing.assert_allclose(np.sort(m), np.sort(c.means), rtol=1e-5)


def test_vectorised_count_rebuild_matches_scalar() -> None:
    """The provider's array rebuild keeps mean and variance exactly and the scalar zero fraction."""
    from msmill.surrogate.targets import count_arrays_from_summary, count_from_summary

    rng = np.random.default_rng(3)
    m, r, pz = rng.uniform(0.5, 8, 40), rng.uniform(0.8, 6, 40), rng.uniform(0.05, 0.7, 40)
    W, M = count_arrays_from_summary(m.reshape(5, 8), r.reshape(5, 8), pz.reshape(5, 8))
    W, M = W.reshape(40, 2), M.reshape(40, 2)
    mean = (W * M).sum(-1)
    var = (W * (M + M**2)).sum(-1) - mean**2
    np.testing.assert_allclose(mean, m, rtol=1e-12)
    np.testing.assert_allclose(var / mean, np.maximum(r, 1.0), rtol=1e-9)
    for i in range(40):
        w, mu = count_from_summary(m[i], r[i], pz[i])
        assert (W[i] * np.exp(-M[i])).sum() == pytest.approx((w * np.exp(-mu)).sum(), abs=1e-4)


def test_provider_passes_count_distributions(fitted) -> None:
    """Runs with fitted count families (schema v2) give the model a Poisson mixture, not a bare mean."""
    from msmill.surrogate.provider import SurrogateProvider

    assert fitted.training_.layout.with_dispersion
    sp = SurrogateProvider(fitted).stage_parameters(np.array([8.0, 12.0, 20.0]), [1500.0] * 4 + [3000.0], 30.0, 40.0)
    c = sp.secondary_count
    assert c is not None and c.weights.shape == (5, 3, 2)
    np.testing.assert_allclose(c.mean(), sp.secondary_lambda, rtol=1e-9)
    var = (c.weights * (c.means + c.means**2)).sum(-1) - c.mean() ** 2
    assert np.all(var > 1.05 * c.mean())  # over-dispersed, as the DEM counts are


def test_destinations_are_regressed_and_reach_the_dem_matrix_transport(fitted, table_runs) -> None:
    """Runs with one-lag destinations: the surrogate predicts the transition matrix the model's transport uses."""
    from msmill.surrogate.provider import SurrogateProvider

    assert fitted.training_.layout.with_destinations
    r = table_runs[2]
    sp = SurrogateProvider(fitted).stage_parameters(np.array([r.design.size_mm]), r.design.stage_speeds_rpm,
                                                    r.design.feed_tph, r.design.gate_deg)
    T = sp.transition
    assert T.shape == (r.n_stages + 1, 1, r.n_stages + 2)
    np.testing.assert_allclose(T.sum(axis=-1), 1.0, rtol=1e-12)
    want = np.array([r.inlet_destinations] + [s.destinations for s in r.stages])
    se = 3 * np.sqrt(want * (1 - want) / r.stages[0].n_transport_samples) + 0.05  # at a training run
    assert np.all(np.abs(T[:, 0] - want) <= se)
    assert sp.transition_lag_s[0] == pytest.approx(r.characteristic_time_s, rel=0.1)


def test_a_layout_with_other_quantile_levels_is_refused_in_one_line():
    """A surrogate file written with another number of levels (12 before 2026-12-02) fails with a clear error."""
    from msmill.errors import MsmillInputError

    doc = tg.TargetLayout(5, True, True).to_dict()
    assert tg.TargetLayout.from_dict(doc).to_dict() == doc
    doc["levels"] = [(j + 0.5) / 12 for j in range(12)]
    with pytest.raises(MsmillInputError, match=r"12 quantile levels.*retrain"):
        tg.TargetLayout.from_dict(doc)


def test_stored_sigma_factor_is_the_least_kl_width():
    """The stored width factor is the float the KL search returns (exactly: the shipped surrogate's
    predictions stay bitwise those of the search) and is a minimum: widths 2 % either side lose more."""
    c = tg.least_kl_sigma_factor()
    assert tg.SIGMA_FACTOR == c and tg.sigma_factor() == c
    q = stats.norm.ppf(tg.LEVELS)

    def round_trip_kl(factor: float) -> float:
        v = np.linspace(-8, 8, 4001)
        sd = factor * tg._spacing(q)
        r = np.mean(stats.norm.pdf((v[:, None] - q) / sd) / sd, axis=1)
        p = stats.norm.pdf(v)
        return float(np.trapezoid(p * np.log(p / r), v))

    assert round_trip_kl(c) < min(round_trip_kl(0.98 * c), round_trip_kl(1.02 * c))


@pytest.mark.parametrize("n_levels", sorted(tg.SIGMA_FACTORS))
def test_every_stored_sigma_factor_is_the_least_kl_width_of_its_levels(n_levels):
    """Each stored factor (a surrogate may be built with another number of quantile levels) is the float the
    KL search returns for its levels, and more levels survive the round trip of a normal with less KL."""
    assert tg.SIGMA_FACTORS[n_levels] == tg.least_kl_sigma_factor(n_levels) == tg.sigma_factor(n_levels)
    assert len(tg.quantile_levels(n_levels)) == n_levels


def test_a_layout_carries_its_levels_through_encoding_decoding_and_its_file(table_runs):
    """A 36-level layout encodes 36 quantiles per velocity distribution, rebuilds mixtures with 36 components
    and the factor of 36 levels, and its dict (the surrogate file) reads back as 36 levels; a 28-level file
    still reads as 28; levels that are not (j - 1/2)/M are refused in one line."""
    run = table_runs[0]
    lay = tg.TargetLayout(run.n_stages, n_levels=36)
    assert lay.slices(1)["primary_velocity"].stop - lay.slices(1)["primary_velocity"].start == 36
    y, nv = tg.encode_run(run, lay)
    assert y.shape == nv.shape == (lay.n_targets,)
    pred = tg.decode_stage(y[None], lay, 1)
    w, mu, sd = pred.primary_velocity
    assert w.shape == (1, 36) and np.allclose(w, 1 / 36)
    q = tg.mixture_quantiles(*(np.asarray(a) for a in (run.stages[0].primary_velocity.weights,
                                                      run.stages[0].primary_velocity.means_m_s,
                                                      run.stages[0].primary_velocity.sigmas_m_s)),
                             levels=tg.quantile_levels(36))
    np.testing.assert_allclose(mu[0], q, rtol=1e-9)
    np.testing.assert_allclose(sd[0], np.maximum(tg.SIGMA_FACTORS[36] * tg._spacing(q), 1e-6), rtol=1e-9)
    assert tg.TargetLayout.from_dict(lay.to_dict()) == lay
    assert tg.TargetLayout.from_dict(tg.TargetLayout(run.n_stages).to_dict()).n_levels == tg.N_LEVELS
    bad = lay.to_dict() | {"levels": [0.1, 0.3, 0.6, 0.9]}
    with pytest.raises(MsmillInputError, match="levels"):
        tg.TargetLayout.from_dict(bad)
    ts = tg.TrainingSet.from_runs(table_runs[:2], n_levels=36)
    sl = ts.layout.slices(2)["secondary_velocity"]
    assert ts.layout.n_levels == 36 and sl.stop - sl.start == 36 and ts.Y.shape[1] == ts.layout.n_targets
    with pytest.raises(MsmillInputError, match="n_levels"):
        tg.TargetLayout(run.n_stages, n_levels=12)
