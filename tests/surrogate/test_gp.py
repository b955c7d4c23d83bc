"""The GP estimator recovers a known smooth 4-D function with calibrated uncertainty."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import qmc

from msmill.errors import MsmillInputError
from msmill.surrogate.gp import SurrogateGP
from msmill.surrogate.space import DesignSpace

SPACE = DesignSpace()
NOISE_SD = 0.03


def truth(X: np.ndarray) -> np.ndarray:
    """A smooth, anisotropic analytic function of the unit-cube coordinates (ln size)."""
    u = SPACE.to_unit(X)
    return np.sin(3.0 * u[:, 0]) + 0.5 * np.cos(2.5 * u[:, 1] + u[:, 2]) + 0.4 * u[:, 2] * u[:, 3] ** 2


@pytest.fixture(scope="module")
def data():
    rng = np.random.default_rng(1)
    X = SPACE.from_unit(qmc.Sobol(4, seed=3).random(64))
    y = truth(X) + NOISE_SD * rng.standard_normal(len(X))
    Xt = SPACE.from_unit(rng.random((400, 4)))
    gp = SurrogateGP(n_restarts=1).fit(X, y[:, None], np.full((len(X), 1), NOISE_SD**2))
    return gp, X, y, Xt


def test_recovers_function_and_is_calibrated(data):
    gp, _, _, Xt = data
    mean, std = gp.predict(Xt, return_std=True)
    f = truth(Xt)
    rmse = float(np.sqrt(np.mean((mean[:, 0] - f) ** 2)))
    assert rmse < 0.1 * f.std(), (rmse, f.std())
    # the mean's 90 % band holds ~90 % of the noise-free truth
    inside = np.abs(mean[:, 0] - f) <= 1.645 * std[:, 0]
    assert 0.8 <= inside.mean() <= 0.98, inside.mean()


def test_noisy_band_holds_new_observations(data):
    gp, _, _, Xt = data
    rng = np.random.default_rng(7)
    y_new = truth(Xt) + NOISE_SD * rng.standard_normal(len(Xt))
    mean, std = gp.predict(Xt, return_std=True, include_noise=True)
    # white noise (scatter the sampling errors do not explain) + the new run's own sampling error
    sd = np.sqrt(std[:, 0] ** 2 + NOISE_SD**2)
    inside = np.abs(mean[:, 0] - y_new) <= 1.645 * sd
    assert 0.8 <= inside.mean() <= 0.98, inside.mean()


def test_sklearn_style_state_and_shapes(data):
    gp, _, _, Xt = data
    assert not hasattr(SurrogateGP(), "estimators_")
    for name in ("estimators_", "X_train_", "Y_train_", "y_mean_", "y_std_", "white_"):
        assert hasattr(gp, name)
    assert gp.predict(Xt[:5]).shape == (5, 1)
    s = gp.sample(Xt[:7], 3, rng=0)
    assert s.shape == (3, 7, 1)


def test_closed_form_loo_matches_brute_force_with_fixed_hyperparameters(data):
    from sklearn.gaussian_process import GaussianProcessRegressor

    gp, X, _, _ = data
    mean, var = gp.loo()
    e = gp.estimators_[0]
    alpha = np.broadcast_to(e.alpha, (len(X),))
    for i in (0, 17, 40):
        keep = np.arange(len(X)) != i
        sub = GaussianProcessRegressor(e.kernel_, alpha=alpha[keep], optimizer=None)
        sub.fit(e.X_train_[keep], e.y_train_[keep])
        m, s = sub.predict(e.X_train_[i:i + 1], return_std=True)
        assert m[0] * gp.y_std_[0] + gp.y_mean_[0] == pytest.approx(mean[i, 0], rel=1e-7, abs=1e-9)
        assert (s[0] ** 2 + alpha[i]) * gp.y_std_[0] ** 2 == pytest.approx(var[i, 0], rel=1e-6)


def test_bad_input_is_one_line():
    with pytest.raises(MsmillInputError, match="Y"):
        SurrogateGP().fit(np.ones((3, 4)) * [5, 20, 1500, 40], np.ones((2, 1)))
    with pytest.raises(MsmillInputError, match="size_mm"):
        SPACE.to_unit(np.array([[-1.0, 20, 1500, 40]]))
