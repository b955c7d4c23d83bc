"""Batched GP prediction, posterior draws, decoding and band equal the one-at-a-time paths.

References: each target's own scikit-learn estimator (``predict``,
``return_cov``), one decode per sample, one ``assemble`` + sparse solve per
sample. The surrogate is fitted to the shipped table's DEM runs (``fitted``).
"""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import pytest
from threadpoolctl import threadpool_info

from msmill.machine import OperatingPoint
from msmill.model import Mill
from msmill.model import submodels as sm
from msmill.model.expected_value import assemble
from msmill.psd import PSD, SizeGrid
from msmill.surrogate.gp import sqrt_factor
from msmill.surrogate.provider import SurrogateProvider
from msmill.threadpools import single_threaded

SPEEDS = [1500.0] * 4 + [3000.0]
SIZES = np.geomspace(0.5, 40.0, 12)


@pytest.fixture(scope="module")
def provider(fitted):
    return SurrogateProvider(fitted)


@pytest.fixture(scope="module")
def points(fitted):
    return fitted.stage_inputs(SIZES, SPEEDS, 30.0, 40.0)[0]  # stage 1's points (P, 4)


def test_predict_equals_each_estimator(fitted, points):
    gp = fitted.gp_
    U = gp.design_space.to_unit(points)
    mean, std = gp.predict(points, return_std=True)
    for j, e in enumerate(gp.estimators_):
        m, s = e.predict(U, return_std=True)
        np.testing.assert_allclose(mean[:, j], m * gp.y_std_[j] + gp.y_mean_[j], rtol=1e-11, atol=1e-11)
        want = np.sqrt(np.maximum(s * s - gp.white_[j], 0.0)) * gp.y_std_[j]
        np.testing.assert_allclose(std[:, j], want, rtol=1e-6, atol=1e-7)


@pytest.mark.parametrize("nu", [1.5, 2.5])
def test_in_place_matern_is_bitwise_the_closed_form(nu):
    """The in-place Matern (speed, issue 42) does the closed form's operations in its order: bitwise equal."""
    from msmill.surrogate.gp import _matern

    d = np.random.default_rng(3).exponential(1.0, (7, 5, 11))
    d[0, 0, :3] = [0.0, 1e-300, 50.0]
    k = d * np.sqrt(3.0 if nu == 1.5 else 5.0)
    want = (1.0 + k) * np.exp(-k) if nu == 1.5 else (1.0 + k + k**2 / 3.0) * np.exp(-k)
    got = _matern(d.copy(), nu)
    assert np.array_equal(got, want)


def test_stacked_kernel_is_bitwise_the_two_matern_sum(fitted, points):
    """The stacked latent kernel equals c32 M32(d32) + c52 M52(d52) written out, bit for bit."""
    gp = fitted.gp_
    st = gp._stacked()
    U, B = gp.design_space.to_unit(points), st.X_train
    want = 0.0
    for c, ls, nu in ((st.c32, st.ls32, 1.5), (st.c52, st.ls52, 2.5)):
        a, b = U[None] / ls[:, None, :], B[None] / ls[:, None, :]
        d2 = (np.einsum("tpk,tpk->tp", a, a)[:, :, None] + np.einsum("tqk,tqk->tq", b, b)[:, None, :]
              - 2.0 * (a @ np.swapaxes(b, 1, 2)))
        k = np.sqrt(np.maximum(d2, 0.0)) * np.sqrt(3.0 if nu == 1.5 else 5.0)
        m = (1.0 + k) * np.exp(-k) if nu == 1.5 else (1.0 + k + k**2 / 3.0) * np.exp(-k)
        want = want + c[:, None, None] * m
    assert np.array_equal(st.latent(U, B), want)


def test_joint_draws_equal_each_estimators_covariance(fitted, points):
    gp = fitted.gp_
    U = gp.design_space.to_unit(points)
    got = gp.sample(points, 16, rng=np.random.default_rng(3))
    rng = np.random.default_rng(3)
    for j, e in enumerate(gp.estimators_):  # the previous path: one estimator, one draw at a time
        m, cov = e.predict(U, return_cov=True)
        a = sqrt_factor(cov - gp.white_[j] * np.eye(U.shape[0]))
        want = (m + rng.standard_normal((16, U.shape[0])) @ a.T) * gp.y_std_[j] + gp.y_mean_[j]
        scale = max(float(np.sqrt(np.max(np.diag(cov)))) * gp.y_std_[j], 1e-12)
        np.testing.assert_allclose(got[:, :, j], want, rtol=0, atol=1e-7 * scale)


def test_sqrt_factor_factorises_and_fixes_the_signs():
    rng = np.random.default_rng(0)
    B = rng.normal(size=(3, 6, 6))
    cov = B @ np.swapaxes(B, 1, 2)
    A = sqrt_factor(cov)
    np.testing.assert_allclose(A @ np.swapaxes(A, 1, 2), cov, atol=1e-12)
    g = 2.0 + np.cos(np.sqrt(2.0) * np.arange(6) + 0.5)
    assert np.all(np.einsum("p,bpk->bk", g, A) >= 0.0)
    # continuity: a rounding-level change of cov (and -cov's eigenvectors from LAPACK) moves A by rounding
    E = rng.normal(size=(3, 6, 6)) * 1e-15
    np.testing.assert_allclose(sqrt_factor(cov + E + np.swapaxes(E, 1, 2)), A, atol=1e-11)
    w, v = np.linalg.eigh(cov)
    np.testing.assert_allclose(sqrt_factor((v * -1.0) * w[:, None, :] @ np.swapaxes(-v, 1, 2)), A, atol=1e-11)


def _fields_close(a, b, path=""):
    if dataclasses.is_dataclass(a):
        for f in dataclasses.fields(a):
            _fields_close(getattr(a, f.name), getattr(b, f.name), f"{path}.{f.name}")
    elif isinstance(a, np.ndarray):
        np.testing.assert_allclose(a, b, rtol=1e-13, atol=0, err_msg=path)
    else:
        assert a == b, path


def test_batched_decode_equals_one_sample_at_a_time(provider, monkeypatch):
    import msmill.surrogate.provider as prov

    monkeypatch.setattr(prov, "DECODE_CHUNK_SETS", 3)  # 5 sets: batches of 3 and 2
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        X = provider._inputs(SIZES, SPEEDS, 30.0, 40.0)
        Z = provider.surrogate.sample_targets(X, 5, rng=np.random.default_rng(1))
    batch = provider._params(Z, SIZES, X)
    assert batch[0].secondary_count is not None and batch[0].transition is not None
    for i, p in enumerate(batch):
        _fields_close(p, provider._params(Z[i:i + 1], SIZES, X)[0])
    assert not np.allclose(batch[0].streams, batch[1].streams)  # the samples differ


def test_band_equals_each_sample_through_assemble(provider):
    grid = SizeGrid.geometric(0.3, 45.0, ratio=2.0)
    feed = PSD.from_passing([9.5, 19.0, 37.5, 45.0], [10.0, 45.0, 92.0, 100.0], grid=grid)
    op = OperatingPoint(feed_tph=30.0, speed_rpm=1500.0, gate_deg=40.0)
    mill = Mill("UG2", provider, grid=grid, band_samples=6, impacts="dem")  # dem: the count mixtures are used
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        passing, p80 = mill.product_band(feed, op, grid)
        samples = provider.sample_stage_parameters(grid.mids_mm, 6, op.stage_speeds(5), 30.0, 40.0, seed=0)
    for i, p in enumerate(samples):
        stats = mill.impacts.impacts(p, np.array(op.stage_speeds(5)))
        lm = assemble(grid.edges_mm, sm.transition_of(mill.transport, p), stats, mill.breakage, mill.damage,
                      mill.band_damage_classes, mill.band_quadrature_nodes)
        product = lm.out_op @ lm.steady_state(lm.feed_vector(feed.fractions, 30.0 * p.characteristic_time_s / 3600))
        psd = PSD(grid, product / product.sum(), validate=False)
        np.testing.assert_allclose(passing[i], psd.passing_pct, rtol=1e-9, atol=1e-9)
        assert p80[i] == pytest.approx(psd.p80_mm, rel=1e-9)


def test_single_threaded_limits_and_restores():
    def blas_threads():
        return {d["filepath"]: d["num_threads"] for d in threadpool_info() if d["user_api"] == "blas"}

    before = blas_threads()
    with single_threaded("blas"):
        assert set(blas_threads().values()) == {1}
    assert blas_threads() == before
