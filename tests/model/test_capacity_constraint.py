"""The DEM envelope as a check in Mill.run and a constraint in sweeps and the optimiser (HAND-MADE envelope)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from msmill.errors import OutOfDomainWarning
from msmill.machine import Machine, OperatingPoint
from msmill.model import Mill
from msmill.model.operating import capacity_feasible, evaluate_point, optimize, sweep
from msmill.psd import PSD, SizeGrid
from msmill.surrogate.capacity import AboveCapacityWarning, CapacityModel, EnvelopePoint

GRID = SizeGrid.geometric(0.038, 45.0)
FEED = PSD.from_passing([2, 4.75, 9.5, 19, 31.5], [2, 6, 18, 58, 100])  # F80 ~ 24 mm
#: HAND-MADE: at every size 10-30 mm (1500 rpm, gate 40) the mill passed 10 and 15 t/h and choked at 25 and
#: 40 t/h passing 20 t/h, so its capacity is 20-25 t/h
HAND = [EnvelopePoint(s, f, 1500.0, 40.0, "steady") for s in (10, 20, 30) for f in (10.0, 15.0)] + \
       [EnvelopePoint(s, f, 1500.0, 40.0, "choked", 20.0) for s in (10, 20, 30) for f in (25.0, 40.0)]


@pytest.fixture(scope="module")
def cap():
    return CapacityModel.fit(HAND)


@pytest.fixture(scope="module")
def mill(cap):
    return Mill("UG2", "table", grid=GRID, envelope=cap)


def run(mill, feed_tph):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", OutOfDomainWarning)
        return mill.run(FEED, OperatingPoint(feed_tph=feed_tph, speed_rpm=1500, gate_deg=40), timeseries=False)


def test_run_warns_above_capacity_and_not_below(mill, cap):
    c = cap.capacity_tph(FEED.p80_mm, 1500.0, 40.0)
    assert 19 < c < 26
    with pytest.warns(AboveCapacityWarning, match=r"above the predicted capacity .* probability of steady flow"):
        high = run(mill, 1.4 * c)
    assert high.capacity_tph == pytest.approx(c) and high.probability_steady < 0.5
    with warnings.catch_warnings():
        warnings.simplefilter("error", AboveCapacityWarning)
        low = run(mill, 0.6 * c)
    assert low.probability_steady > 0.5 and any("DEM envelope" in n for n in low.notes)


def test_envelope_off_and_the_default_only_for_the_default_machine(cap, monkeypatch):
    import msmill.surrogate.capacity

    # the hand-made envelope stands in for a shipped one (it stands in for the shipped one)
    monkeypatch.setattr(msmill.surrogate.capacity, "default_capacity_model", lambda: cap)
    with warnings.catch_warnings():
        warnings.simplefilter("error", AboveCapacityWarning)
        res = run(Mill("UG2", "table", grid=GRID, envelope=None), 1e3 / 3)
    assert res.capacity_tph is None
    other = Machine.default().model_copy(update={"chute_width_m": 0.2})
    assert Mill("UG2", "table", other, grid=GRID).capacity is None  # the shipped envelope is the default mill's
    assert Mill("UG2", "table", Machine.default(), grid=GRID).capacity is cap


def test_sweep_flags_points_above_capacity(mill, cap):
    op = OperatingPoint(feed_tph=15, speed_rpm=1500, gate_deg=40)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        t = sweep(mill, FEED, op, {"feed_tph": np.linspace(10, 40, 7)})
    c = cap.capacity_tph(FEED.p80_mm, 1500.0, 40.0)
    np.testing.assert_array_equal(t["above_capacity"], t["feed_tph"] > c)
    np.testing.assert_array_equal(t["feasible"], ~t["above_capacity"])
    assert t["p_steady"].is_monotonic_decreasing and np.allclose(t["capacity_tph"], c)


def test_optimiser_max_feed_stops_at_capacity(mill, cap):
    op = OperatingPoint(feed_tph=15, speed_rpm=1500, gate_deg=40)
    c = cap.capacity_tph(FEED.p80_mm, 1500.0, 40.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        r = optimize(mill, FEED, op, {"feed_tph": (10, 40)}, "max_feed", target_p80_mm=1e3, n_grid=4)
        free = optimize(Mill("UG2", "table", grid=GRID, envelope=None), FEED, op, {"feed_tph": (10, 40)},
                        "max_feed", target_p80_mm=1e3, n_grid=4)
    assert free.settings["feed_tph"] == pytest.approx(40.0)
    assert c * 0.99 < r.settings["feed_tph"] <= c  # refined up to the capacity, not past it


def test_capacity_feasible_hook_from_another_envelope(cap):
    m = Mill("UG2", "table", grid=GRID, envelope=None)
    op = OperatingPoint(feed_tph=15, speed_rpm=1500, gate_deg=40)
    hook = capacity_feasible(cap)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rows = [evaluate_point(m, FEED, op, {"feed_tph": f}, feasible=hook) for f in (12.0, 35.0)]
    assert [r["feasible"] for r in rows] == [True, False]


def test_sweep_with_lower_bounds_only():
    """HAND-MADE steady-only envelope (no choke): the bound at F80, 1500 rpm, gate 40 is 22 t/h halved per factor
    1.5 in size from the nearer of the 20 and 28 mm runs (their gate, 30 deg, is closed further: no cost); points
    above it are flagged and stay feasible (no run choked: the capacity there is unknown, not exceeded)."""
    steady = [EnvelopePoint(s, f, 1500.0, 30.0, "steady") for s in (20.0, 28.0) for f in (10.0, 22.0)]
    low = CapacityModel.fit(steady, method="demonstrated")
    m = Mill("UG2", "table", grid=GRID, envelope=low)
    op = OperatingPoint(feed_tph=15, speed_rpm=1500, gate_deg=40)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        t = sweep(m, FEED, op, {"feed_tph": np.array([10.0, 12.0, 30.0, 40.0])})
    f80 = float(t["f80_mm"].iloc[0])
    bound = max(22.0 * 2.0 ** (-abs(np.log(s / f80)) / np.log(1.5)) for s in (20.0, 28.0))
    assert 15.0 < bound < 22.0 and np.allclose(t["capacity_tph"], bound)
    np.testing.assert_array_equal(t["above_capacity"], [False, False, True, True])
    assert t["feasible"].all()
    assert t["capacity_is_lower_bound"].all()
    assert (t["p_steady"][:2] == 1.0).all() and t["p_steady"][2:].isna().all()  # unknown above the bound
    with pytest.warns(AboveCapacityWarning, match="feed the DEM has shown the mill to pass"):
        res = run(m, 30.0)
    assert res.capacity_is_lower_bound and res.capacity_tph == pytest.approx(bound)
    hook = capacity_feasible(low)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        row = evaluate_point(Mill("UG2", "table", grid=GRID), FEED, op, {"feed_tph": 40.0}, feasible=hook)
    assert row["feasible"]  # another envelope's lower bound does not exclude either
