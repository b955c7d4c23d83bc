"""Per-slice series of every statistic (issue 36): their ratios are the run's statistics, and the errors the run
reports are the chosen estimator on them plus the between-run deviation (batch means on request)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from msmill.dem.mill.run import RunSettings, _compute, run_mill
from msmill.dem.mill.stats import StatsSettings
from msmill.errors import MsmillInputError, OutOfDomainWarning
from msmill.machine import Machine, OperatingPoint
from msmill.sampling import (
    AutocorrelationTime,
    BatchMeans,
    SamplingError,
    default_between_run,
    statistic_kind,
)

MACHINE = Machine.default().model_copy(update={"n_stages": 2})
SETTINGS = RunSettings(max_time_s=0.55, chunk_s=0.05, steady_window_s=0.1, rel_tol=0.5, trend_tol=5.0,
                       balance_tol=5.0, snapshot_every_s=0.005, adaptive=True, min_measure_s=0.1, max_measure_s=0.25,
                       check_every_s=0.05)


@pytest.fixture(scope="module")
def run():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", OutOfDomainWarning)
        op = OperatingPoint(feed_tph=60, speed_rpm=700, bottom_speed_factor=1.0, gate_deg=40)
        return run_mill(MACHINE, op, size_mm=20.0, mode="slice", settings=SETTINGS,
                        stats_settings=StatsSettings(series_slices=20))


def test_series_ratios_are_the_statistics(run):
    series = run.stats.series
    assert series is not None and set(series) >= {"holdup", "s1.kickback", "s2.secondary_lambda"}
    for st in run.stats.run.stages:
        for key in ("kickback", "refeed", "pass_through", "primary_hit_probability", "secondary_lambda"):
            d = series[f"s{st.stage}.{key}"]
            assert len(d["num"]) == len(d["den"]) == 20
            assert sum(d["num"]) / sum(d["den"]) == pytest.approx(getattr(st, key), rel=1e-12)
        v = run.stats.samples[st.stage]["primary_velocity_m_s"]
        d = series[f"s{st.stage}.primary_velocity_mean_m_s"]
        assert sum(d["den"]) == v.size and sum(d["num"]) == pytest.approx(v.sum(), rel=1e-12)
    ts = run.timeseries
    inside = (ts["time_s"] >= run.window_s[0]) & (ts["time_s"] <= run.window_s[1])
    h = series["holdup"]
    assert sum(h["num"]) / sum(h["den"]) == pytest.approx(ts["mass_kg"][inside].mean(), rel=1e-12)
    assert h["window_s"] == pytest.approx(list(run.window_s))


def test_reported_errors_are_the_autocorrelation_estimate_plus_the_between_run_deviation(run):
    within = run.stats.run.provenance["stats"]["sampling_error_within"]
    between = default_between_run()
    n = 0
    for st in run.stats.run.stages:
        for key in ("kickback", "refeed", "pass_through", "primary_hit_probability", "secondary_lambda",
                    "primary_velocity_mean_m_s"):
            d = run.stats.series[f"s{st.stage}.{key}"]
            num, den = np.array(d["num"]), np.array(d["den"])
            e = AutocorrelationTime().standard_error(num, den)
            assert within[f"s{st.stage}.{key}"] == pytest.approx([e.se, e.dof], rel=1e-12)
            sb = between.sigma(statistic_kind(key), 20.0, num.sum() / den.sum())
            assert sb > 0
            assert st.sampling_error[key] == pytest.approx(np.hypot(e.se, sb), rel=1e-12), (st.stage, key)
            n += 1
    assert n == 12
    h = run.stats.series["holdup"]
    mean = sum(h["num"]) / sum(h["den"])
    tot = between.total("holdup", 20.0, mean, SamplingError(*within["holdup"]))
    assert run.stats.holdup_rel_se == pytest.approx(tot.se / mean, rel=1e-12)


def test_batch_means_on_request_are_the_old_errors(run):
    # the streams' batches split the tag times, the series' the window: with evenly spaced tags and 20
    # slices in 5 batches they agree to within the few tags at a batch's edge
    old = _compute(run, StatsSettings(series_slices=20, error_estimator="batch_means"))
    assert "sampling_error_within" not in old.run.provenance["stats"]
    for st in old.run.stages:
        for key in ("kickback", "refeed", "pass_through", "secondary_lambda"):
            d = old.series[f"s{st.stage}.{key}"]
            se = BatchMeans(5).standard_error(np.array(d["num"]), np.array(d["den"])).se
            assert se == pytest.approx(st.sampling_error[key], rel=0.35), (st.stage, key)


def test_series_by_default_and_bad_settings():
    assert StatsSettings().series_slices == 64 and StatsSettings().error_estimator == "autocorrelation_time"
    with pytest.raises(MsmillInputError, match="error_estimator"):
        StatsSettings(error_estimator="jackknife")
    with pytest.raises(MsmillInputError, match="series_slices"):
        StatsSettings(series_slices=0)
    StatsSettings(series_slices=0, error_estimator="batch_means")
