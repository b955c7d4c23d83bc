"""Vogel-Peukert + Swebrec sub-model, power / wear estimates, sweeps and the optimiser."""

from __future__ import annotations

import warnings

import numpy as np
import pandas as pd
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from msmill.errors import MsmillInputError, OutOfDomainWarning
from msmill.model import Mill
from msmill.model.breakage_swebrec import VogelSwebrecBreakage, swebrec_passing
from msmill.model.mill import breakage_parameters
from msmill.model.operating import optimize, optimize_settings, pareto_front
from msmill.model.power import fit_no_load, power_estimate
from msmill.psd import PSD, SizeGrid

GRID = SizeGrid.geometric(0.038, 45.0)


# ------------------------------------------------------------------ Vogel-Peukert + Swebrec
def test_selection_reduces_to_eq11_without_threshold_and_has_a_threshold():
    bp = breakage_parameters("UG2")
    vp = VogelSwebrecBreakage.from_ore(bp)
    e, L = np.array([0.05, 0.2, 0.5]), np.array([5.0, 20.0, 40.0])
    expect = 1 - np.exp(-bp.b_t_per_kwh * e * L / bp.l_ref_mm)
    assert np.allclose(vp.probability(e, L, 0.0), expect)
    th = VogelSwebrecBreakage.from_ore(bp, e_min_kwh_t=0.1)
    # threshold at L is E_min L_ref / L: zero below, positive above
    assert th.probability(0.1 * bp.l_ref_mm / 10.0 * 0.99, 10.0, 0.0) == 0.0
    assert th.probability(0.1 * bp.l_ref_mm / 10.0 * 1.01, 10.0, 0.0) > 0.0
    assert th.probability(0.3, 10.0, 0.5) > th.probability(0.3, 10.0, 0.0)  # damage weakens


@settings(max_examples=30, deadline=None)
@given(t10=st.floats(0.5, 95.0), beta=st.floats(0.5, 6.0))
def test_swebrec_curve_passes_t10_at_a_tenth(t10, beta):
    assert swebrec_passing(np.array(0.1), t10, beta) == pytest.approx(t10, rel=1e-9)
    p = swebrec_passing(np.geomspace(1e-4, 0.999, 50), t10, beta)
    assert np.all(np.diff(p) >= -1e-12) and p.max() <= 100.0


@settings(max_examples=20, deadline=None)
@given(pb=st.floats(0.0, 1.0), beta=st.floats(0.5, 6.0), parent=st.integers(0, GRID.n_classes - 1))
def test_swebrec_columns_conserve_mass_and_stay_below_the_parent(pb, beta, parent):
    vp = VogelSwebrecBreakage.from_ore(breakage_parameters("UG2"), swebrec_b=beta)
    col = vp.fragments(GRID.edges_mm, np.array(parent), np.array(pb))
    assert col.sum() == pytest.approx(1.0, abs=1e-12)
    assert np.all(col >= 0) and np.all(col[parent + 1:] == 0)


def test_swebrec_runs_in_the_mill_and_conserves_mass():
    feed = PSD.from_passing([2, 4.75, 9.5, 19, 31.5], [2, 6, 18, 58, 100])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", OutOfDomainWarning)
        res = Mill("UG2", "default", breakage="vogel_swebrec").run(feed, {"feed_tph": 30, "speed_rpm": 1500})
    assert res.mass_balance_error < 1e-9
    assert res.p80_mm < res.f80_mm


# ------------------------------------------------------------------ power and wear
def test_power_is_impact_energy_rate_plus_stated_no_load():
    feed = PSD.from_passing([2, 4.75, 9.5, 19, 31.5], [2, 6, 18, 58, 100])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", OutOfDomainWarning)
        res = Mill("UG2", "default").run(feed, {"feed_tph": 30, "speed_rpm": 1500}, timeseries=False)
    p = power_estimate(res)
    assert p.impact_kw == pytest.approx(res.specific_impact_energy_kwh_t * 30.0)  # kWh/t * t/h = kW
    assert p.stages["impact_kw"].sum() == pytest.approx(p.impact_kw)
    assert np.all(p.stages["flinger_kw"] <= p.stages["impact_kw"] + 1e-12)
    q = power_estimate(res, no_load_kw=10.0, drive_efficiency=0.9)
    assert q.total_kw == pytest.approx((p.impact_kw + 10.0) / 0.9)
    assert any("lower bound" in a for a in p.assumptions)
    with pytest.raises(MsmillInputError):
        power_estimate(res, no_load_kw=-1.0)


def test_fit_no_load_recovers_intercept():
    x = np.array([20.0, 30.0, 40.0, 50.0])
    icpt, slope, rmse = fit_no_load(x, 12.0 + 1.1 * x)
    assert (icpt, slope, rmse) == pytest.approx((12.0, 1.1, 0.0), abs=1e-9)
    with pytest.raises(MsmillInputError):
        fit_no_load(x[:2], x[:2])


# ------------------------------------------------------------------ optimiser
def analytic(s):
    """Monotone SYNTHETIC case: P80 rises with feed, falls with speed; energy rises with speed."""
    speed, feed = s.get("speed_rpm", 1500.0), s.get("feed_tph", 30.0)
    return {"p80_mm": 10 + 0.2 * feed - 0.004 * speed, "specific_energy_kwh_t": speed / 1000.0,
            "throughput_tph": feed, "feasible": True}


def test_optimizer_finds_known_max_feed():
    r = optimize_settings(analytic, {"speed_rpm": (1200, 1900), "feed_tph": (10, 60)}, "max_feed",
                          target_p80_mm=12.0)
    # P80 = 12 at feed = 10 + 0.02 speed, largest at 1900 rpm: 48 t/h
    assert r.settings["speed_rpm"] == pytest.approx(1900.0)
    assert r.settings["feed_tph"] == pytest.approx(48.0, rel=2e-3)
    assert r.row["p80_mm"] <= 12.0
    assert r.at_bounds() == {"speed_rpm": "high"}  # the speed is the range's, the feed the mill's
    assert r.closest is None


def test_optimizer_respects_the_feasibility_hook():
    def capped(s):
        return {**analytic(s), "feasible": s["feed_tph"] <= 40.0}

    r = optimize_settings(capped, {"speed_rpm": (1200, 1900), "feed_tph": (10, 60)}, "max_feed",
                          target_p80_mm=12.0)
    assert r.settings["feed_tph"] == pytest.approx(40.0, rel=2e-3)


def test_optimizer_finds_known_min_energy():
    r = optimize_settings(analytic, {"speed_rpm": (1200, 1900)}, "min_energy", target_p80_mm=9.0)
    assert r.settings["speed_rpm"] == pytest.approx(1750.0, rel=2e-3)  # 16 - 0.004 s = 9
    assert r.at_bounds() == {}  # an interior optimum
    none = optimize_settings(analytic, {"speed_rpm": (1200, 1900)}, "min_energy", target_p80_mm=5.0)
    assert none.settings is None
    # what the bounds can reach: the finest product, at the top speed (P80 16 - 0.004 * 1900 = 8.4 mm)
    assert none.closest["speed_rpm"] == pytest.approx(1900.0) and none.closest["p80_mm"] == pytest.approx(8.4)


def test_optimizer_on_the_mill_meets_the_target_at_the_lowest_speed():
    feed = PSD.from_passing([2, 4.75, 9.5, 19, 31.5], [2, 6, 18, 58, 100])
    from msmill.machine import OperatingPoint

    op = OperatingPoint(feed_tph=30, speed_rpm=1500, gate_deg=40)
    mill = Mill("UG2", "table", grid=GRID)  # the single-point table (speed-scaled velocities)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", OutOfDomainWarning)
        # a target the speed range can reach: the product at 1650 rpm (P80 falls as speed rises)
        target = mill.run(feed, op.model_copy(update={"speed_rpm": 1650.0}), timeseries=False).p80_mm
        r = optimize(mill, feed, op, {"speed_rpm": (1200, 1900)}, "min_energy", target_p80_mm=target, n_grid=4)
        slower = mill.run(feed, op.model_copy(update={"speed_rpm": r.settings["speed_rpm"] * 0.99}),
                          timeseries=False)
    assert r.settings["speed_rpm"] == pytest.approx(1650.0, rel=0.01)  # the least energy: the lowest speed
    assert target - 0.05 < r.row["p80_mm"] <= target
    assert slower.p80_mm > target


@settings(max_examples=30, deadline=None)
@given(st.lists(st.tuples(st.floats(0, 10), st.floats(0, 10)), min_size=1, max_size=30))
def test_pareto_front_is_not_dominated(points):
    t = pd.DataFrame(points, columns=["specific_energy_kwh_t", "p80_mm"])
    f = pareto_front(t)
    for _, a in f.iterrows():
        dom = (t["specific_energy_kwh_t"] <= a["specific_energy_kwh_t"]) & (t["p80_mm"] <= a["p80_mm"]) & (
            (t["specific_energy_kwh_t"] < a["specific_energy_kwh_t"]) | (t["p80_mm"] < a["p80_mm"]))
        assert not dom.any()
    assert f["p80_mm"].min() == t["p80_mm"].min()
