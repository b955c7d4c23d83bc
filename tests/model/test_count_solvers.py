"""Secondary-impact count families in both solvers (all stage parameters SYNTHETIC)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy import stats as sps
from synthetic import synthetic_table
from test_mass_balance import BREAKAGE, DAMAGE, GRID, march_errors, random_parameters
from threadpoolctl import threadpool_limits

from msmill.model import Mill, TableProvider
from msmill.model.expected_value import assemble, impact_operator, secondary_series
from msmill.model.montecarlo import MonteCarloSolver, _sample_count
from msmill.model.parameters import CountArrays, MixtureArrays
from msmill.model.submodels import ImpactStatistics, NoDamage
from msmill.psd import ks_statistic
from msmill.stageparams import CountDistribution, StageParameterTable

pytestmark = pytest.mark.filterwarnings("ignore::msmill.errors.OutOfDomainWarning")


def _random_counts(rng: np.random.Generator, shape: tuple[int, int], c: int = 3) -> CountArrays:
    w = rng.dirichlet(np.ones(c), size=shape)
    m = rng.uniform(0, 8, (*shape, c))
    m[..., 0] = 0.0  # a point mass at zero (zero inflation) in every mixture
    return CountArrays(w, m)


@pytest.mark.parametrize("method", ["series", "expm"])
def test_secondary_series_equals_the_count_series(method):
    """E[S^K] = sum_k P(k) S^k and phi = sum_k P(k) sum_{j<k} S^j, for a mixture of 0, 1.3, 6.2."""
    rng = np.random.default_rng(4)
    nd, n = 4, 3
    S = np.tril(rng.uniform(0, 1, (n, nd, nd)))
    S *= rng.uniform(0.3, 0.95, (n, 1, nd)) / S.sum(axis=1, keepdims=True)  # columns: survival < 1
    w = np.array([[0.2, 0.5, 0.3]] * n)
    m = np.array([[0.0, 1.3, 6.2]] * n)
    eA, phi = secondary_series(S, w, m, method)
    k = np.arange(80)
    pk = w[0] @ sps.poisson.pmf(k[None], m[0][:, None])
    for i in range(n):
        powers = [np.linalg.matrix_power(S[i], j) for j in k]
        want_e = sum(p * P for p, P in zip(pk, powers, strict=True))
        cum = np.cumsum(powers, axis=0)  # sum_{j<=k} S^j
        want_phi = sum(pk[j] * cum[j - 1] for j in range(1, k.size))
        assert np.allclose(eA[i], want_e, atol=1e-12)
        assert np.allclose(phi[i], want_phi, atol=1e-11)


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), nd=st.integers(1, 6), size=st.floats(0.3, 50.0), mean=st.floats(0.0, 6.0))
def test_power_series_equals_expm(seed, nd, size, mean):
    """The two exact constructions agree to rounding (negative binomial + a random 3-mixture)."""
    rng = np.random.default_rng(seed)
    n = 4
    S = rng.uniform(0, 1, (n, nd, nd))
    S *= rng.uniform(0.0, 1.0, (n, 1, nd)) / S.sum(axis=1, keepdims=True)
    nb = CountDistribution.negative_binomial(mean, size)
    w = np.c_[np.tile(nb.weights, (n, 1)), rng.dirichlet(np.ones(3), n)] / 2
    m = np.c_[np.tile(nb.means, (n, 1)), rng.uniform(0, 10, (n, 3))]
    a, b = secondary_series(S, w, m, "series"), secondary_series(S, w, m, "expm")
    assert np.max(np.abs(a[0] - b[0])) < 1e-13
    assert np.max(np.abs(a[1] - b[1])) < 1e-12 * max(1.0, float(w[0] @ m[0]))


def test_one_component_equals_poisson_path():
    rng = np.random.default_rng(1)
    streams, stats = random_parameters(rng, 3)
    counts = CountArrays.poisson(stats.secondary_lambda)
    with_counts = ImpactStatistics(stats.hit_probability, stats.primary_velocity, stats.secondary_lambda,
                                   stats.secondary_velocity, counts)
    a = assemble(GRID.edges_mm, streams, stats, BREAKAGE, DAMAGE, 3, 6)
    b = assemble(GRID.edges_mm, streams, with_counts, BREAKAGE, DAMAGE, 3, 6)
    assert abs(a.M - b.M).max() == 0.0  # None means a one-component Poisson
    # and a ZIP with pi = 0.4 is 0.4 I + 0.6 x the Poisson operator on the survivors
    mix = _one_stage(stats)
    sec = impact_operator(GRID.edges_mm, mix, BREAKAGE, DAMAGE, 3, 6)
    lam = stats.secondary_lambda[0]
    e1, p1 = secondary_series(sec.survive, np.ones((lam.size, 1)), lam[:, None])
    e2, p2 = secondary_series(sec.survive, np.tile([0.4, 0.6], (lam.size, 1)), np.c_[0 * lam, lam])
    assert np.allclose(e2, 0.4 * np.eye(3)[None] + 0.6 * e1, atol=1e-14)
    assert np.allclose(p2, 0.6 * p1, atol=1e-14)


def _one_stage(stats: ImpactStatistics) -> MixtureArrays:
    m = stats.secondary_velocity
    return MixtureArrays(m.weights[0], m.means_m_s[0], m.sigmas_m_s[0])


@settings(max_examples=10, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**32 - 1), n_stages=st.integers(1, 4), impacted=st.sampled_from(["refeed", "all"]))
def test_ev_conserves_mass_with_count_mixtures(seed, n_stages, impacted):
    rng = np.random.default_rng(seed)
    streams, stats = random_parameters(rng, n_stages)
    counts = _random_counts(rng, stats.secondary_lambda.shape)
    stats = ImpactStatistics(stats.hit_probability, stats.primary_velocity, counts.mean(),
                             stats.secondary_velocity, counts)
    with threadpool_limits(1, user_api="blas"):
        lm = assemble(GRID.edges_mm, streams, stats, BREAKAGE, DAMAGE, 3, 6, impacted)
    cols = np.asarray(lm.M.sum(axis=0)).ravel() + np.asarray(lm.out_op.sum(axis=0)).ravel()
    assert np.max(np.abs(cols - 1.0)) < 1e-10
    assert lm.M.min() >= -1e-15
    f = lm.feed_vector(rng.dirichlet(np.ones(GRID.n_classes)), 0.5)
    assert march_errors(lm, f, 40).max() < 1e-10


def test_mc_conserves_mass_with_count_mixtures():
    rng = np.random.default_rng(8)
    streams, stats = random_parameters(rng, 3)
    counts = _random_counts(rng, stats.secondary_lambda.shape)
    stats = ImpactStatistics(stats.hit_probability, stats.primary_velocity, counts.mean(),
                             stats.secondary_velocity, counts)
    feed = rng.dirichlet(np.ones(GRID.n_classes))
    run = MonteCarloSolver(parcels_per_step=300, seed=5).run(GRID.edges_mm, streams, stats, BREAKAGE, NoDamage(),
                                                             feed, 0.5, 60, 30)
    assert run.mass_balance_error.max() < 1e-10


def test_mc_count_sampling_follows_the_mixture():
    rng = np.random.default_rng(0)
    d = CountDistribution.zero_inflated_poisson(0.35, 4.0)
    counts = CountArrays(np.array([[d.weights]]), np.array([[d.means]]))
    k = _sample_count(rng, counts, np.zeros(200_000, dtype=int), np.zeros(200_000, dtype=int))
    emp = np.bincount(k, minlength=30)[:30] / k.size
    assert np.max(np.abs(emp - d.pmf(29))) < 4e-3  # ~4 sigma of a 200k sample


def _table_with_counts(**kw) -> StageParameterTable:
    """The SYNTHETIC table with a different count family per stage (means kept)."""
    table = synthetic_table(**kw)
    runs = []
    for r in table.runs:
        stages = []
        for s in r.stages:
            lam = s.secondary_lambda
            fam = [CountDistribution.negative_binomial(lam, 0.6),
                   CountDistribution.zero_inflated_poisson(0.5, 2 * lam),
                   CountDistribution.poisson_mixture([0.3, 0.4, 0.3], [0.0, 0.5 * lam, 2.5 * lam]),
                   CountDistribution.poisson(lam)][s.stage % 4]
            stages.append(s.model_copy(update={"secondary_count": fam, "secondary_lambda": fam.mean}))
        runs.append(r.model_copy(update={"stages": stages}))
    return StageParameterTable.model_validate(table.model_copy(update={"runs": runs}).model_dump())


def test_solvers_agree_with_count_mixtures(feed, op):
    provider = TableProvider(_table_with_counts(v_secondary=25.0), source="SYNTHETIC counts")
    ev = Mill("UG2", provider).run(feed, op)
    mc = Mill("UG2", provider, solver="monte_carlo", seed=2024, parcels_per_step=1000).run(feed, op)
    assert ks_statistic(ev.product_psd, mc.product_psd) < 0.01
    assert mc.secondary_impacts_per_t == pytest.approx(ev.secondary_impacts_per_t, rel=0.03)
    # the shape matters: with the same means, over-dispersed counts break less (the survival
    # (1 - p)^k is convex in k, Jensen), so the product is coarser than with Poisson counts
    poisson = Mill("UG2", TableProvider(synthetic_table(v_secondary=25.0))).run(feed, op)
    assert ks_statistic(ev.product_psd, poisson.product_psd) > 2e-3
    assert ev.product_psd.p80_mm > poisson.product_psd.p80_mm


def test_provider_interpolates_count_pmfs(grid):
    table = _table_with_counts()
    params = TableProvider(table).stage_parameters(grid.mids_mm)
    c = params.secondary_count
    assert np.allclose(c.weights.sum(axis=-1), 1.0)
    assert np.allclose(c.mean(), params.secondary_lambda, rtol=1e-9)
    # at a run's own size the pmf is that run's
    j = int(np.argmin(np.abs(grid.mids_mm - 8.0)))
    params8 = TableProvider(table).stage_parameters(np.array([8.0]))
    want = table.runs[1].stages[0].secondary_count.pmf(20)
    got = params8.secondary_count.weights[0, 0] @ sps.poisson.pmf(np.arange(21)[None], params8.secondary_count.means[0, 0][:, None])
    assert np.allclose(got, want, atol=1e-12)
    assert j >= 0


def test_solvers_agree_on_the_shipped_table():
    """The UG2 example on the packaged DEM table (negative-binomial counts): K-S < 0.01, mass to rounding."""
    from pathlib import Path

    from msmill.model.providers import load_provider
    from msmill.model.runfile import RunFile

    table = load_provider("table").table
    assert any(s.secondary_count.n_components > 1 for r in table.runs for s in r.stages)
    rf = RunFile.from_toml(Path(__file__).parents[2] / "examples" / "ug2.toml")
    mill, feed, op = rf.build()
    ev = mill.run(feed, op)
    mc_rf = rf.model_copy(update={"model": rf.model.model_copy(update={"solver": "monte_carlo"})})
    mc_mill, _, _ = mc_rf.build()
    mc = mc_mill.run(feed, op)
    assert ks_statistic(ev.product_psd, mc.product_psd) < 0.01
    assert ev.mass_balance_error < 1e-12 and mc.mass_balance_error < 1e-12
    assert mc.secondary_impacts_per_t == pytest.approx(ev.secondary_impacts_per_t, rel=0.03)
