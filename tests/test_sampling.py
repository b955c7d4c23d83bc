"""Standard errors of correlated time averages (msmill.sampling) against AR(1) series of known variance."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from msmill.errors import MsmillInputError
from msmill.sampling import (
    RUN_ERROR_ESTIMATOR,
    AutocorrelationTime,
    BatchMeans,
    BetweenRunVariance,
    BlockBootstrap,
    OverlappingBatchMeans,
    ReplicaSet,
    SamplingError,
    default_between_run,
    error_estimator,
    fit_between_run,
    replica_set_z_scores,
    replica_z_scores,
    slice_sums,
    t_quantile,
)
from msmill.stageparams import RunStatistics

PHI, N, REPS = 0.6, 512, 300


def ar1(rng: np.random.Generator, n: int, phi: float) -> np.ndarray:
    """Stationary AR(1) with unit innovations."""
    e = rng.standard_normal(n)
    x = np.empty(n)
    x[0] = e[0] / math.sqrt(1 - phi**2)
    for i in range(1, n):  # small test series
        x[i] = phi * x[i - 1] + e[i]
    return x


@pytest.fixture(scope="module")
def replicas():
    """REPS independent ratio series: num = den * (1 + 0.3 x), den = 5 + AR(1) noise (the ratio's truth is 1)."""
    rng = np.random.default_rng(1)
    out = []
    for _ in range(REPS):
        den = 5.0 + 0.5 * ar1(rng, N, PHI)
        num = den * (1.0 + 0.3 * ar1(rng, N, PHI))
        out.append((num, den))
    return out


def _z(est, replicas):
    z, cover = [], []
    for num, den in replicas:
        e = est.standard_error(num, den)
        r = num.sum() / den.sum()
        z.append((r - 1.0) / e.se)
        cover.append(abs(r - 1.0) <= e.half_width(0.90))
    return np.sqrt(np.mean(np.square(z))), float(np.mean(cover))


@pytest.mark.parametrize("est,lo,hi", [
    (BatchMeans(20), 0.9, 1.2),                 # t with 19 dof: rms 1.06
    (OverlappingBatchMeans(), 0.85, 1.2),
    (AutocorrelationTime(), 0.85, 1.2),
    (BlockBootstrap(block_slices=16, n_boot=200), 0.85, 1.25),
])
def test_errors_match_the_scatter_of_independent_replicas(replicas, est, lo, hi):
    rms, cover = _z(est, replicas)
    assert lo <= rms <= hi, (type(est).__name__, rms)
    assert 0.84 <= cover <= 0.96, (type(est).__name__, cover)  # the t interval of its dof covers 90 %


def test_five_batch_means_are_honest_only_with_their_t_quantile(replicas):
    rms, cover = _z(BatchMeans(5), replicas)
    # z of five batch means is t with 4 dof: rms sqrt(4 / 2) = 1.41, the excess; its 90 % t interval
    # (2.13 se, not 1.64 se) still covers
    assert 1.2 <= rms <= 1.7
    assert 0.84 <= cover <= 0.96
    assert t_quantile(0.90, 4) == pytest.approx(2.132, abs=1e-3)
    assert t_quantile(0.90, math.inf) == pytest.approx(1.645, abs=1e-3)


def test_correlation_is_not_ignored():
    # independent-sample errors of an AR(1) mean are too small by sqrt(tau) = sqrt((1 + phi) / (1 - phi)) = 2
    rng = np.random.default_rng(3)
    x = 1.0 + 0.3 * ar1(rng, 20000, PHI)
    tau = AutocorrelationTime().tau(x - x.mean())
    assert tau == pytest.approx((1 + PHI) / (1 - PHI), rel=0.15)
    se = AutocorrelationTime().standard_error(x, np.ones_like(x)).se
    naive = x.std() / math.sqrt(x.size)
    assert se / naive == pytest.approx(2.0, rel=0.1)


@settings(max_examples=40, deadline=None)
@given(scale=st.floats(0.01, 100.0), seed=st.integers(0, 10_000))
def test_scale_invariance(scale, seed):
    rng = np.random.default_rng(seed)
    den = rng.uniform(1.0, 2.0, 64)
    num = den * rng.uniform(0.2, 0.8, 64)
    for est in (BatchMeans(5), OverlappingBatchMeans(), AutocorrelationTime(), BlockBootstrap(n_boot=50)):
        a = est.standard_error(num, den)
        b = est.standard_error(scale * num, scale * den)  # units of mass cancel in a ratio
        c = est.standard_error(scale * num, den)  # the ratio scales
        assert b.se == pytest.approx(a.se, rel=1e-9) and b.dof == pytest.approx(a.dof, rel=1e-9)
        assert c.se == pytest.approx(scale * a.se, rel=1e-9)


def test_slices_and_bad_input():
    t = np.array([0.0, 0.1, 0.5, 0.99, 1.0, 1.5])
    assert slice_sums(t, 1.0, (0.0, 1.0), 4).tolist() == [2.0, 0.0, 1.0, 2.0]
    with pytest.raises(MsmillInputError, match="error_estimator"):
        error_estimator("jackknife")
    assert isinstance(error_estimator("batch_means", n_batches=10), BatchMeans)
    assert math.isnan(BatchMeans(5).standard_error(np.ones(3), np.ones(3)).se)
    with pytest.raises(MsmillInputError, match="window_s"):
        slice_sums(t, 1.0, (1.0, 1.0), 4)


def test_replica_z_scores_are_unit_with_honest_errors_and_not_with_halved_ones():
    rng = np.random.default_rng(5)
    se = rng.uniform(0.5, 2.0, size=(4000, 6))
    x = rng.standard_normal(se.shape) * se
    z = np.concatenate([replica_z_scores(xi, ei) for xi, ei in zip(x, se, strict=True)])
    assert np.sqrt(np.mean(z**2)) == pytest.approx(1.0, abs=0.03)
    z_half = np.concatenate([replica_z_scores(xi, ei / 2) for xi, ei in zip(x, se, strict=True)])
    assert np.sqrt(np.mean(z_half**2)) == pytest.approx(2.0, abs=0.06)
    assert replica_z_scores(np.array([1.0, np.nan]), np.array([1.0, 1.0])).size == 0


def _random_effect_sets(rng, a, beta, relative, n_sets=40, m=6):
    """Replica sets ``x = mu + b + e`` with ``sd(b) = a (size / 20)^beta`` (times mu if relative)."""
    sets = []
    for k in range(n_sets):
        size = (5.0, 10.0, 20.0, 30.0)[k % 4]
        mu = 2.0 + k % 3
        sb = a * (size / 20.0) ** beta * (mu if relative else 1.0)
        se = rng.uniform(0.5, 1.5, m) * sb
        x = mu + rng.standard_normal(m) * sb + rng.standard_normal(m) * se
        sets.append(ReplicaSet("holdup" if relative else "streams", size, x, se, np.full(m, 50.0)))
    return sets


@pytest.mark.parametrize("relative", [False, True])
def test_between_run_fit_recovers_its_law_and_makes_z_unit(relative):
    rng = np.random.default_rng(11)
    a, beta = 0.02, 1.5
    sets = _random_effect_sets(rng, a, beta, relative)
    fit = fit_between_run(sets)
    kind = sets[0].kind
    la, b = fit.params[kind]
    c = fit.cov[kind]
    assert abs(la - np.log(a)) < 3 * np.sqrt(c[0][0]) + 0.05
    assert abs(b - beta) < 3 * np.sqrt(c[1][1]) + 0.05
    assert fit.size_range_mm == (5.0, 30.0)
    # fresh sets scored with the fit: rms z near 1; with the within errors alone: well above
    fresh = _random_effect_sets(np.random.default_rng(12), a, beta, relative, n_sets=200)
    z = np.concatenate([replica_set_z_scores(r, fit) for r in fresh])
    z0 = np.concatenate([replica_set_z_scores(r) for r in fresh])
    assert np.sqrt(np.mean(z**2)) == pytest.approx(1.0, abs=0.08)
    assert np.sqrt(np.mean(z0**2)) > 1.3


def test_between_run_total_dof_and_round_trip(tmp_path):
    fit = BetweenRunVariance({"streams": (np.log(0.01), 1.0), "holdup": (np.log(0.05), 2.0)},
                             cov={"streams": ((0.01, 0.0), (0.0, 0.1))})
    assert fit.sigma("streams", 40.0) == pytest.approx(0.02)
    assert fit.sigma("holdup", 10.0, value=4.0) == pytest.approx(0.05 * 0.25 * 4.0)
    assert fit.sigma("velocity", 10.0) == 0.0
    w = SamplingError(0.01, 50.0)
    t = fit.total("streams", 20.0, 0.3, w)
    assert t.se == pytest.approx(np.hypot(0.01, 0.01))
    assert t.dof == pytest.approx(4e-8 / (1e-8 / 50 + 1e-8 / 50))  # 1 / (2 * 0.01) = 50 dof for sigma_b^2
    assert fit.total(None, 20.0, 0.3, w) == w
    p = tmp_path / "b.json"
    p.write_text(json.dumps(fit.to_dict()))
    back = BetweenRunVariance.read(p)
    assert back.sigma("holdup", 10.0, 4.0) == pytest.approx(fit.sigma("holdup", 10.0, 4.0))
    with pytest.raises(MsmillInputError, match="kind"):
        BetweenRunVariance.from_dict({"kind": "other"})


def test_the_packaged_between_run_fit_is_read():
    fit = default_between_run()
    assert set(fit.params) == {"streams", "hit", "velocity", "count", "holdup"}
    assert fit.provenance["within_estimator"] == RUN_ERROR_ESTIMATOR
    assert all(len(v) == 2 for v in fit.params.values())


# --------------------------------------------------------------------------- run against run
def _run_doc(kick: float, se: float | None, n_stages: int = 2) -> RunStatistics:
    stages = [{"stage": i, "kickback": kick, "refeed": 0.5, "pass_through": 0.5 - kick,
               "primary_hit_probability": 0.3, "secondary_lambda": 2.0,
               "primary_velocity": {"weights": [1.0], "means_m_s": [30.0], "sigmas_m_s": [3.0]},
               "secondary_velocity": {"weights": [1.0], "means_m_s": [5.0], "sigmas_m_s": [1.0]},
               "sampling_error": {} if se is None else {"kickback": se, "primary_velocity_mean_m_s": 0.5}}
              for i in range(1, n_stages + 1)]
    return RunStatistics.from_dict({"design": {"size_mm": 10, "feed_tph": 30, "speed_rpm": 1500, "gate_deg": 40,
                                               "stage_speeds_rpm": [1500] * n_stages},
                                    "characteristic_time_s": 0.03, "stages": stages})


def test_paired_deviation_is_the_difference_over_the_combined_error():
    from msmill.sampling import paired_deviations

    a, b = _run_doc(0.10, 0.003), _run_doc(0.14, 0.004)
    devs = dict((name, d) for d, name in paired_deviations(a, b))
    assert devs["stage 1 kickback"] == pytest.approx(0.04 / 0.005)
    assert devs["stage 2 primary_velocity_mean_m_s"] == pytest.approx(0.0)
    assert len(devs) == 4  # only statistics with both errors: kickback and the primary velocity per stage
    assert paired_deviations(a, _run_doc(0.14, None)) == []
    # with 5 batches a batch-means t is less surprising than a normal deviate of the same size
    ne = dict((name, d) for d, name in paired_deviations(a, b, normal_equivalent=True))
    assert 0 < ne["stage 1 kickback"] < devs["stage 1 kickback"]
    assert ne["stage 1 primary_velocity_mean_m_s"] == devs["stage 1 primary_velocity_mean_m_s"]


def test_seed_error_ratio_is_the_scatter_over_the_reported_error():
    from msmill.sampling import seed_error_ratios, statistics_by_name

    kicks = [0.10, 0.12, 0.14, 0.16]  # sd 0.0258 over the seeds
    runs = [_run_doc(k, 0.0129) for k in kicks]
    x, e = statistics_by_name(runs)["stage 2 kickback"]
    assert x.tolist() == kicks and np.all(e == 0.0129)
    per_family, median, pooled = seed_error_ratios(runs)
    assert per_family["kickback"] == pytest.approx([np.std(kicks, ddof=1) / 0.0129] * 2)
    assert pooled == pytest.approx(np.std(kicks, ddof=1) / 0.0129)
    assert per_family["primary_velocity_mean_m_s"] == [0.0, 0.0]  # identical seeds: no scatter
    assert median == pytest.approx(np.median([*per_family["kickback"], 0.0, 0.0]))
    assert seed_error_ratios(runs[:2])[0] == {}  # fewer than three errors per statistic: nothing
