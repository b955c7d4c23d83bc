"""Adaptive measurement window: stops at the minimum when targets are met, runs to the maximum when not."""

import math
import warnings

import pytest

from msmill.dem.mill.run import RunSettings, run_mill
from msmill.errors import OutOfDomainWarning
from msmill.machine import Machine, OperatingPoint
from msmill.stageparams import RunStatistics

MACHINE = Machine.default().model_copy(update={"n_stages": 2})
BASE = dict(max_time_s=0.55, chunk_s=0.05, steady_window_s=0.1, rel_tol=0.5, trend_tol=5.0, balance_tol=5.0,
            snapshot_every_s=0.005, adaptive=True, min_measure_s=0.1, max_measure_s=0.25, check_every_s=0.05)


def _run(**targets):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", OutOfDomainWarning)
        op = OperatingPoint(feed_tph=60, speed_rpm=700, bottom_speed_factor=1.0, gate_deg=40)
        return run_mill(MACHINE, op, size_mm=20.0, mode="slice", settings=RunSettings(**{**BASE, **targets}))


@pytest.mark.parametrize("target,length_s", [(math.inf, 0.1), (1e-9, 0.25)])
def test_window_length_follows_the_targets(target, length_s):
    run = _run(target_streams_se=target, target_hit_probability_se=target, target_velocity_rel_se=target,
               target_count_mean_rel_se=target, target_velocity_sampling_kl=target, target_holdup_rel_se=target)
    assert run.outcome == "steady"
    t0, t1 = run.window_s
    assert t1 - t0 == pytest.approx(length_s, abs=0.011)  # whole chunks and steps
    reached = run.stats.run.sampling_error_reached
    assert set(reached) == set(RunSettings().targets())
    assert all(v is None or v > 1e-9 for v in reached.values())  # a real, positive figure or no sample
    assert RunStatistics.from_json(run.stats.run.to_json()).sampling_error_reached == reached
    assert run.stats.run.provenance["adaptive_targets"]["streams"] == target
    # every check records the targets it found missed: none at the first check with infinite targets,
    # all of them at every check with unreachable ones (the run then ends at the maximum window)
    checks = run.stats.run.provenance["window_checks"]
    if math.isinf(target):
        assert [c["above_target"] for c in checks] == [{}]
    else:
        assert len(checks) >= 2 and all(set(c["above_target"]) == set(RunSettings().targets()) for c in checks)
        assert checks[-1]["window_end_s"] <= t1 + 1e-9


def test_sampling_kl_follows_the_fewest_impacts():
    """The expected sampling KL is p / (2 n) at the fewest velocity samples of any stage and kind."""
    from msmill.dem.mill.run import VELOCITY_FIT_PARAMETERS

    run = _run(target_streams_se=math.inf, target_hit_probability_se=math.inf, target_velocity_rel_se=math.inf,
               target_count_mean_rel_se=math.inf, target_velocity_sampling_kl=math.inf, target_holdup_rel_se=math.inf)
    n = min(len(run.stats.samples[st.stage][key]) for st in run.stats.run.stages
            for key in ("primary_velocity_m_s", "secondary_velocity_m_s"))
    assert n >= 3
    reached = run.stats.run.sampling_error_reached["velocity_sampling_kl"]
    assert reached == pytest.approx(VELOCITY_FIT_PARAMETERS / (2 * n))


def test_window_start_rule():
    """Detection: now; onset: the onset, not before settle_s nor after now; not steady: the last measure_s."""
    from msmill.dem.mill.run import window_start_s

    onset = RunSettings(window_from="onset", settle_s=0.3, measure_s=0.5)
    assert window_start_s(RunSettings(), (0.8, 2.1), 2.15) == 2.15
    assert window_start_s(onset, (0.8, 2.1), 2.15) == 0.8
    assert window_start_s(onset, (0.05, 1.35), 1.4) == 0.3  # placed rock settles first
    assert window_start_s(RunSettings(window_from="onset", settle_s=5.0), (0.0, 1.3), 1.4) == 1.4
    assert window_start_s(onset, None, 3.0) == 2.5
    assert window_start_s(onset, None, 0.2) == 0.0


def test_check_schedule_grows_with_the_window():
    """The next check: at least check_every_s later, a quarter of the window so far once that is longer
    (the stop replay of benchmarks/stop_study.py checks where run_mill does, through this rule)."""
    rs = RunSettings(check_every_s=0.2)
    assert rs.next_check_s(0.6, 1.4) == pytest.approx(1.6)  # window 0.8 s: a quarter is 0.2 s
    assert rs.next_check_s(0.6, 1.0) == pytest.approx(1.2)  # window 0.4 s: the floor
    assert rs.next_check_s(0.6, 3.0) == pytest.approx(3.6)  # window 2.4 s: 0.6 s later
    assert rs.check_due(1.6, 1.6) and rs.check_due(1.6, 1.56)  # due within half a chunk (0.05 s)
    assert not rs.check_due(1.6, 1.5)


@pytest.mark.parametrize("target", [math.inf, 1e-9])
def test_window_from_onset_reuses_the_steady_windows(target):
    """From the onset the two steady windows are measured, not simulated again: met targets stop the run
    at the chunk that detected steady state; unmet ones run to max_measure_s of window counted from the onset."""
    run = _run(window_from="onset", settle_s=0.0, max_measure_s=0.6, target_streams_se=target,
               target_hit_probability_se=target, target_velocity_rel_se=target, target_count_mean_rel_se=target,
               target_velocity_sampling_kl=target, target_holdup_rel_se=target)
    assert run.outcome == "steady"
    t0, t1 = run.window_s
    assert t0 == run.steady_state_time_s < run.steady_state_detected_s
    if math.isinf(target):  # detection is tested at chunk ends
        assert run.steady_state_detected_s - 1e-9 <= t1 <= run.steady_state_detected_s + BASE["chunk_s"] + 1e-9
    else:
        assert t1 - t0 == pytest.approx(0.6, abs=0.011)


@pytest.mark.parametrize("target,length_s", [(math.inf, 0.1), (1e-9, 0.25)])
def test_hold_up_target_alone_sets_the_window(target, length_s):
    """Every other target met at once: the hold-up's error target alone decides when the window stops, and
    the error reached is that of the window's mass series as the runs report it (issue 36: the
    autocorrelation-time error of its slices plus the between-run deviation), over its mean."""
    import numpy as np

    from msmill.sampling import AutocorrelationTime, default_between_run

    run = _run(target_streams_se=math.inf, target_hit_probability_se=math.inf, target_velocity_rel_se=math.inf,
               target_count_mean_rel_se=math.inf, target_velocity_sampling_kl=math.inf, target_holdup_rel_se=target)
    t0, t1 = run.window_s
    assert t1 - t0 == pytest.approx(length_s, abs=0.011)
    ts = run.timeseries[(run.timeseries["time_s"] >= t0) & (run.timeseries["time_s"] <= t1)]
    h = run.stats.series["holdup"]
    num, den = np.asarray(h["num"]), np.asarray(h["den"])
    mean = num.sum() / den.sum()
    assert mean == pytest.approx(ts["mass_kg"].mean(), rel=1e-12)
    within = AutocorrelationTime().standard_error(num, den)
    want = default_between_run().total("holdup", run.stats.run.design.size_mm, mean, within).se / mean
    assert run.stats.run.sampling_error_reached["holdup_rel"] == pytest.approx(want, rel=1e-9)
    assert run.stats.run.provenance["stats"]["holdup_rel_se"] == pytest.approx(want, rel=1e-9)


def test_between_run_deviations_stay_below_the_adaptive_targets():
    # a target below the between-run deviation could never be met by a longer window (issue 36)
    from msmill.sampling import default_between_run

    cal = default_between_run()
    rs = RunSettings()
    for size_mm in (2.0, 5.0, 10.0, 20.0, 30.0):
        assert cal.sigma("streams", size_mm) < rs.target_streams_se
        assert cal.sigma("hit", size_mm) < rs.target_hit_probability_se
        assert cal.sigma("velocity", size_mm) < rs.target_velocity_rel_se
        assert cal.sigma("count", size_mm) < rs.target_count_mean_rel_se
