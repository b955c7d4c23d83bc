"""Count families of secondary impacts: fits, selection, the Poisson-mixture schema, v1 files."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import stats

from msmill.distributions import (
    CountFamilySelection,
    NegativeBinomialKLFit,
    PoissonKLFit,
    PoissonMixtureKLFit,
    ZeroInflatedPoissonKLFit,
    count_batch_stderr,
    counts_from_histogram,
    kl_divergence,
)
from msmill.errors import MsmillInputError
from msmill.stageparams import CountDistribution, RunStatistics, StageParameterTable

N = 4000
K = np.arange(200)


def _samples(name: str, rng: np.random.Generator, n: int = N) -> tuple[np.ndarray, CountDistribution]:
    """SYNTHETIC samples of clearly separated families with their true distribution."""
    if name == "poisson":
        return rng.poisson(2.5, n), CountDistribution.poisson(2.5)
    if name == "negative_binomial":
        return stats.nbinom.rvs(1.5, 1.5 / 4.5, size=n, random_state=rng), CountDistribution.negative_binomial(3.0, 1.5)
    if name == "zero_inflated_poisson":
        return (np.where(rng.random(n) < 0.4, 0, rng.poisson(4.0, n)),
                CountDistribution.zero_inflated_poisson(0.4, 4.0))
    if name == "poisson_mixture_2":
        return (np.where(rng.random(n) < 0.5, rng.poisson(1.0, n), rng.poisson(9.0, n)),
                CountDistribution.poisson_mixture([0.5, 0.5], [1.0, 9.0]))
    c = rng.choice(3, size=n, p=[0.3, 0.35, 0.35])
    means = np.array([0.5, 6.0, 18.0])
    return rng.poisson(means[c]), CountDistribution.poisson_mixture([0.3, 0.35, 0.35], means)


FITS = {
    "poisson": PoissonKLFit,
    "negative_binomial": NegativeBinomialKLFit,
    "zero_inflated_poisson": ZeroInflatedPoissonKLFit,
    "poisson_mixture_2": lambda: PoissonMixtureKLFit(2),
    "poisson_mixture_3": lambda: PoissonMixtureKLFit(3),
}


@pytest.mark.parametrize("name", list(FITS))
def test_each_family_recovers_its_parameters(name):
    x, true = _samples(name, np.random.default_rng(7))
    fit = FITS[name]().fit(x)
    got = fit.to_count_distribution()
    assert fit.kl_ < 0.01  # to the empirical pmf
    assert kl_divergence(true.native_pmf(K[-1]), got.native_pmf(K[-1])) < 0.01  # to the truth
    assert got.mean == pytest.approx(true.mean, rel=0.05)
    assert got.variance == pytest.approx(true.variance, rel=0.1)
    assert got.p_zero == pytest.approx(true.p_zero, abs=0.02)
    for key, want in true.params.items():
        assert got.params[key] == pytest.approx(want, rel=0.15, abs=0.03), key


@pytest.mark.parametrize("name", [n for n in FITS if n != "poisson"])
def test_selection_picks_the_true_family(name):
    x, _ = _samples(name, np.random.default_rng(11))
    sel = CountFamilySelection().fit(x)
    assert sel.chosen_ == name
    rep = sel.to_selection()
    assert rep.chosen == name and set(rep.candidates) == set(FITS)
    assert rep.kl == pytest.approx(sel.kl_)
    assert all(rep.candidates[name].bic <= c.bic for c in rep.candidates.values())


@pytest.mark.parametrize("seed", range(5))
def test_poisson_sample_selects_poisson(seed):
    x, _ = _samples("poisson", np.random.default_rng(seed))
    assert CountFamilySelection().fit(x).chosen_ == "poisson"
    assert CountFamilySelection(criterion="aic").fit(x).chosen_ in ("poisson", "negative_binomial",
                                                                    "zero_inflated_poisson")


def test_likelihood_equations_hold_exactly():
    x, _ = _samples("zero_inflated_poisson", np.random.default_rng(3))
    nb = NegativeBinomialKLFit().fit(x)
    assert nb.mean_ == pytest.approx(x.mean(), rel=1e-12)
    z = ZeroInflatedPoissonKLFit().fit(x)
    assert (1 - z.pi_) * z.lambda_ == pytest.approx(x.mean(), rel=1e-10)
    assert z.pmf(0) == pytest.approx(np.mean(x == 0), rel=1e-10)
    # no excess of zeros: the ZIP is the Poisson; an under-dispersed sample: NB at the Poisson limit
    under = np.random.default_rng(0).binomial(6, 0.5, 3000)
    assert ZeroInflatedPoissonKLFit().fit(under).pi_ == 0.0
    assert NegativeBinomialKLFit().fit(under).size_ == pytest.approx(1e4, rel=1e-3)


@settings(max_examples=25, deadline=None)
@given(st.lists(st.integers(0, 40), min_size=2, max_size=300))
def test_richer_families_never_fit_worse(counts):
    x = np.asarray(counts)
    sel = CountFamilySelection().fit(x)
    kl = {n: f.kl_ for n, f in sel.fits_.items()}
    assert all(v >= -1e-12 for v in kl.values())
    assert kl["poisson_mixture_2"] <= kl["poisson"] + 1e-7  # nested families
    # the NB contains the Poisson only as size -> inf; at its bound 1e4 the gap is O(mean^2 / 1e4)
    assert kl["negative_binomial"] <= kl["poisson"] + 1e-4 * max(1.0, x.mean()) ** 2
    assert kl["zero_inflated_poisson"] <= kl["poisson"] + 1e-7
    assert sel.to_count_distribution().mean == pytest.approx(x.mean(), rel=1e-4, abs=1e-9)


def test_histogram_and_samples_give_the_same_fit():
    x, _ = _samples("negative_binomial", np.random.default_rng(5), 500)
    a = CountFamilySelection().fit(x)
    b = CountFamilySelection().fit_histogram(np.bincount(x))
    assert a.chosen_ == b.chosen_ and a.kl_ == b.kl_
    assert np.array_equal(np.sort(counts_from_histogram(np.bincount(x))), np.sort(x))
    with pytest.raises(MsmillInputError, match="histogram"):
        CountFamilySelection().fit_histogram([0, 0])
    with pytest.raises(MsmillInputError, match="counts"):
        PoissonKLFit().fit([1, -2])


def test_batch_standard_errors_match_the_sampling_spread():
    rng = np.random.default_rng(2)
    x = rng.poisson(3.0, 20_000)
    se = count_batch_stderr("poisson", np.array_split(x, 20))
    assert se["lambda"] == pytest.approx(np.sqrt(3.0 / x.size), rel=0.5)
    assert se["mean"] == pytest.approx(se["lambda"])
    se_nb = count_batch_stderr("negative_binomial", np.array_split(_samples("negative_binomial", rng)[0], 5))
    assert {"mean", "size", "variance", "p_zero"} <= set(se_nb)


# ---------------------------------------------------------------- schema
def test_count_distribution_moments_match_its_pmf():
    for d in (CountDistribution.poisson(2.0), CountDistribution.zero_inflated_poisson(0.3, 5.0),
              CountDistribution.poisson_mixture([0.2, 0.8], [7.0, 1.0]), CountDistribution.negative_binomial(3.0, 0.8)):
        p = d.pmf(400)
        k = np.arange(401)
        assert p.sum() == pytest.approx(1.0, abs=1e-12)
        assert k @ p == pytest.approx(d.mean, rel=1e-10)
        assert (k * k) @ p - d.mean**2 == pytest.approx(d.variance, rel=1e-9)
        assert p[0] == pytest.approx(d.p_zero, rel=1e-12)
    zip_ = CountDistribution.zero_inflated_poisson(0.3, 5.0)
    assert zip_.means == [0.0, 5.0] and zip_.p_zero == pytest.approx(0.3 + 0.7 * np.exp(-5.0))
    mix = CountDistribution.poisson_mixture([0.2, 0.8], [7.0, 1.0])
    assert mix.means == [1.0, 7.0] and mix.params["weight_1"] == pytest.approx(0.8)


@pytest.mark.parametrize(("mean", "size", "tv_max"), [(2.0, 0.5, 2e-5), (4.0, 0.5, 1e-3), (2.0, 1.0, 5e-7),
                                                      (4.0, 3.0, 1e-7), (1.5, 1e4, 1e-12)])
def test_negative_binomial_quadrature(mean, size, tv_max):
    """Errors as documented in docs/model.md (16 nodes)."""
    d = CountDistribution.negative_binomial(mean, size)
    assert d.n_components == 16
    assert d.mean == pytest.approx(mean, rel=1e-12)
    assert d.variance == pytest.approx(mean + mean**2 / size, rel=1e-8)
    tv = 0.5 * np.abs(d.pmf(3000) - d.native_pmf(3000)).sum()
    assert tv < tv_max


def _v1_run() -> dict:
    stage = {"kickback": 0.1, "refeed": 0.5, "pass_through": 0.4, "primary_hit_probability": 0.3,
             "primary_velocity": {"weights": [1.0], "means_m_s": [30.0], "sigmas_m_s": [3.0]},
             "secondary_lambda": 1.7, "secondary_lambda_kl": 0.2,
             "secondary_velocity": {"weights": [1.0], "means_m_s": [5.0], "sigmas_m_s": [2.0]}}
    return {"schema_version": 1, "characteristic_time_s": 0.05,
            "design": {"size_mm": 10, "feed_tph": 30, "speed_rpm": 1500, "gate_deg": 40,
                       "stage_speeds_rpm": [1500, 3000]},
            "stages": [{"stage": 1, **stage}, {"stage": 2, **stage}]}


def test_version_1_files_load_as_one_component_mixtures(tmp_path):
    p = tmp_path / "v1.json"
    p.write_text(json.dumps(_v1_run()))
    run = RunStatistics.from_json(p)
    assert run.schema_version == 2
    c = run.stages[0].secondary_count
    assert c.family == "poisson" and c.weights == [1.0] and c.means == [1.7] and c.mean == 1.7
    assert run.stages[0].secondary_count_histogram == [] and run.stages[0].secondary_count_selection is None
    t = tmp_path / "t1.json"
    t.write_text(json.dumps({"schema_version": 1, "kind": "stage_parameter_table", "runs": [_v1_run()]}))
    table = StageParameterTable.from_json(t)
    assert table.schema_version == 2 and table.runs[0].stages[1].secondary_count.mean == 1.7
    again = tmp_path / "t2.json"
    table.to_json(again)
    assert StageParameterTable.from_json(again) == table


def test_count_must_match_lambda_and_round_trips(tmp_path):
    d = _v1_run()
    nb = CountDistribution.negative_binomial(1.7, 0.9).model_dump()
    d["stages"][0] = {**d["stages"][0], "secondary_count": nb, "secondary_count_histogram": [5, 3, 1]}
    run = RunStatistics.from_dict(d)
    assert run.stages[0].secondary_count.family == "negative_binomial"
    assert RunStatistics.from_json(run.to_json()) == run
    d["stages"][0]["secondary_lambda"] = 2.5
    with pytest.raises(MsmillInputError, match="secondary_lambda"):
        RunStatistics.from_dict(d)
    d["stages"][0]["secondary_lambda"] = 1.7
    d["stages"][0]["secondary_count_histogram"] = [5, -1]
    with pytest.raises(MsmillInputError, match="histogram"):
        RunStatistics.from_dict(d)


def test_negative_binomial_of_a_vanishing_mean_is_a_mixture():
    # hypothesis found mean = 5e-324: the quadrature's Gamma quantiles underflowed to an empty rule
    from msmill.stageparams import CountDistribution

    for mean in (5e-324, 1e-300, 1e-12):
        d = CountDistribution.negative_binomial(mean, 1.3)
        assert np.isclose(sum(d.weights), 1.0) and min(d.means) >= 0.0
        assert np.dot(d.weights, d.means) == pytest.approx(mean, rel=1e-9, abs=1e-320)
