import numpy as np
import pytest

from msmill.distributions import GaussianMixtureKLFit, PoissonKLFit, kl_divergence
from msmill.errors import MsmillInputError
from msmill.stageparams import GaussianMixture


def test_poisson_recovers_lambda_with_small_kl():
    rng = np.random.default_rng(1)
    k = rng.poisson(3.7, 20000)
    fit = PoissonKLFit().fit(k)
    assert fit is not None and fit.lambda_ == pytest.approx(3.7, abs=0.05)
    assert fit.kl_ < 0.01
    assert fit.lambda_stderr_ == pytest.approx(np.sqrt(3.7 / 20000), rel=0.1)


def test_poisson_lambda_minimises_kl():
    rng = np.random.default_rng(2)
    fit = PoissonKLFit().fit(rng.poisson(1.3, 500))
    from scipy import stats

    for lam in (fit.lambda_ * 0.95, fit.lambda_ * 1.05):
        assert kl_divergence(fit.empirical_pmf_, stats.poisson.pmf(fit.support_, lam)) > fit.kl_


def test_poisson_rejects_bad_counts():
    with pytest.raises(MsmillInputError, match="counts"):
        PoissonKLFit().fit([1, -2, 3])
    with pytest.raises(MsmillInputError, match="counts"):
        PoissonKLFit().fit([])


def test_mixture_recovers_two_components():
    rng = np.random.default_rng(3)
    n = 30000
    a = rng.normal(3.0, 1.0, int(0.6 * n))
    b = rng.normal(12.0, 2.5, n - a.size)
    fit = GaussianMixtureKLFit(k_max=4).fit(np.concatenate([a, b]))
    assert fit.n_components_ == 2
    assert fit.weights_ == pytest.approx([0.6, 0.4], abs=0.02)
    assert fit.means_ == pytest.approx([3.0, 12.0], abs=0.15)
    assert fit.sigmas_ == pytest.approx([1.0, 2.5], rel=0.06)
    assert fit.kl_ < 0.01
    assert fit.kl_ <= fit.kl_em_ + 1e-12
    gm = fit.to_stageparams()
    assert isinstance(gm, GaussianMixture) and gm.n_components == 2


def test_mixture_single_component_chosen_by_bic():
    rng = np.random.default_rng(4)
    fit = GaussianMixtureKLFit(k_max=4).fit(rng.normal(25.0, 4.0, 20000))
    assert fit.n_components_ == 1
    assert fit.means_[0] == pytest.approx(25.0, abs=0.1)
    assert fit.sigmas_[0] == pytest.approx(4.0, rel=0.03)
    assert fit.kl_ < 0.01


def test_mixture_three_components_and_degenerate_sample():
    rng = np.random.default_rng(5)
    x = np.concatenate([rng.normal(2, 0.5, 8000), rng.normal(8, 1.0, 8000), rng.normal(20, 2.0, 4000)])
    fit = GaussianMixtureKLFit(k_max=5).fit(x)
    assert fit.n_components_ == 3
    assert fit.means_ == pytest.approx([2, 8, 20], abs=0.2)
    assert fit.weights_ == pytest.approx([0.4, 0.4, 0.2], abs=0.02)
    assert fit.kl_ < 0.01
    one = GaussianMixtureKLFit().fit([5.0, 5.0, 5.0])
    assert one.n_components_ == 1 and one.means_[0] == 5.0
    with pytest.raises(MsmillInputError):
        GaussianMixtureKLFit().fit([1.0])
