"""Physical behaviour of the mill model (all stage parameters SYNTHETIC)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from synthetic import synthetic_run, synthetic_table

from msmill import breakage as bk
from msmill.errors import ExtrapolationWarning, OutOfDomainWarning
from msmill.machine import OperatingPoint
from msmill.model import Mill, RunProvider, TableProvider
from msmill.model.expected_value import assemble
from msmill.model.mill import EXTRAPOLATED_WARN_PCT
from msmill.model.submodels import BreakageParameters, resolve
from msmill.psd import PSD, SizeGrid, ks_statistic

pytestmark = pytest.mark.filterwarnings("ignore::msmill.errors.OutOfDomainWarning")


def test_no_speed_means_no_breakage(provider, feed, grid):
    op = OperatingPoint(feed_tph=30.0, stage_speeds_rpm=[0.0] * 5, gate_deg=40.0)
    res = Mill("UG2", provider).run(feed, op)
    assert np.allclose(res.product_psd.fractions, feed.fractions, atol=1e-12, rtol=0)
    assert res.specific_impact_energy_kwh_t == pytest.approx(0.0, abs=1e-15)
    # Monte Carlo: no parcel changes class (a finite window only samples the feed)
    mc = Mill("UG2", provider, solver="monte_carlo", seed=1, parcels_per_step=500, mc_steps=90).run(feed, op)
    assert np.all(mc.product_psd.fractions[feed.fractions == 0] == 0)
    assert ks_statistic(mc.product_psd, feed) < 0.03
    assert mc.specific_impact_energy_kwh_t == 0.0


def test_zero_hit_probability_means_unchanged_psd(feed, op):
    table = synthetic_table(hit=0.0, lam=0.0)
    res = Mill("UG2", TableProvider(table), impacts="dem").run(feed, op)
    assert np.allclose(res.product_psd.fractions, feed.fractions, atol=1e-12, rtol=0)
    assert res.primary_impacts_per_t == 0.0


def test_direct_steady_state_equals_time_marched_limit(provider, feed, op):
    mill = Mill("UG2", provider)
    grid = mill.model_grid(feed)
    _, _, _, lm, _ = mill.prepare(grid, op)
    f = lm.feed_vector(feed.rebin(grid).fractions, 0.5)
    x_direct = lm.steady_state(f)
    x = np.zeros_like(f)
    for _ in range(3000):
        x = lm.M @ x + f
    assert np.max(np.abs(x - x_direct)) < 1e-12 * max(1.0, x_direct.max()) + 1e-13
    res = mill.run(feed, op)
    assert res.timeseries["product_tph"].iloc[-1] == pytest.approx(30.0, rel=1e-4)


def test_solvers_agree(provider, feed, op):
    ev = Mill("UG2", provider).run(feed, op)
    mc = Mill("UG2", provider, solver="monte_carlo", seed=2024, parcels_per_step=1000).run(feed, op)
    ks = ks_statistic(ev.product_psd, mc.product_psd)
    assert ks < 0.01, ks
    assert mc.primary_impacts_per_t == pytest.approx(ev.primary_impacts_per_t, rel=0.03)
    assert mc.secondary_impacts_per_t == pytest.approx(ev.secondary_impacts_per_t, rel=0.03)
    assert mc.stages["holdup_t"].sum() == pytest.approx(ev.stages["holdup_t"].sum(), rel=0.03)


def _one_impact_provider(n_stages: int, v: float) -> RunProvider:
    run = synthetic_run(10.0, n_stages=n_stages, hit=1.0, lam=0.0, kick=0.0, refeed=0.0)
    stages = []
    for s in run.stages:
        stages.append(s.model_copy(update={
            "primary_velocity": s.primary_velocity.single(v, 1e-6)}))
    return RunProvider(run.model_copy(update={"stages": stages}), source="SYNTHETIC")


@pytest.mark.parametrize("breakage", ["ab_t10", "jk_t10"])
def test_one_stage_one_impact_matches_hand_calculation(op, breakage):
    """All mass passes straight through one stage and is hit exactly once at 40 m/s.

    Broken rock's t10: ``A P_b`` (paper Eq. 12, ``ab_t10``) or ``A`` (JK convention, ``jk_t10``).
    """
    grid = SizeGrid.geometric(0.038, 45.0)
    j = grid.n_classes - 2
    feed = PSD(grid, np.eye(grid.n_classes)[j])
    op1 = OperatingPoint(feed_tph=30.0, stage_speeds_rpm=[1500.0], gate_deg=40.0)
    res = Mill("UG2", _one_impact_provider(1, 40.0), impacts="dem", damage="none", breakage=breakage,
               impacted="all").run(feed, op1)
    ore = BreakageParameters.from_ore(__import__("msmill.ore", fromlist=["get_ore"]).get_ore("UG2"))
    e = 0.5 * 40.0**2 / 3600.0  # kWh/t
    L = grid.mids_mm[j]
    pb = 1.0 - np.exp(-ore.b_t_per_kwh * e * L / ore.l_ref_mm)  # Eq. 11 by hand
    t10 = ore.A_pct * pb if breakage == "ab_t10" else ore.A_pct
    B = bk.appearance_matrix(grid, t10, ore.tn)
    expected = pb * B[:, j]
    expected[j] += 1.0 - pb
    assert np.allclose(res.product_psd.fractions, expected, atol=5e-4, rtol=0)
    assert res.primary_impacts_per_t == pytest.approx(1.0)
    assert res.specific_impact_energy_kwh_t == pytest.approx(e, rel=1e-6)


def test_damage_makes_repeated_impacts_break_more():
    """Two stages, every rock hit once in each: damage breaks more than independent impacts."""
    grid = SizeGrid.geometric(0.038, 45.0)
    j = grid.n_classes - 2
    feed = PSD(grid, np.eye(grid.n_classes)[j])
    op2 = OperatingPoint(feed_tph=30.0, stage_speeds_rpm=[1500.0, 1500.0], gate_deg=40.0)
    prov = _one_impact_provider(2, 40.0)
    kw = dict(impacts="dem", impacted="all", damage_classes=16)
    indep = Mill("UG2", prov, damage="none", **kw).run(feed, op2)
    damaged = Mill("UG2", prov, damage="tavares", **kw).run(feed, op2)
    surv_indep = indep.product_psd.fractions[j]
    surv_dam = damaged.product_psd.fractions[j]
    ore = BreakageParameters.from_ore(__import__("msmill.ore", fromlist=["get_ore"]).get_ore("UG2"))
    pb = 1.0 - np.exp(-ore.b_t_per_kwh * (0.5 * 40.0**2 / 3600.0) * grid.mids_mm[j] / ore.l_ref_mm)
    # independent impacts: survivors (1 - P_b)^2 (plus fragments staying in class j)
    assert surv_indep >= (1 - pb) ** 2
    assert surv_dam < surv_indep - 1e-3
    assert damaged.product_psd.p80_mm < indep.product_psd.p80_mm


def test_higher_speed_never_coarsens(provider, feed):
    prev = None
    for speed in (0.0, 600.0, 1200.0, 1500.0, 1900.0, 2500.0):
        op = OperatingPoint(feed_tph=30.0, speed_rpm=speed, gate_deg=40.0)
        res = Mill("UG2", provider).run(feed, op, timeseries=False)
        passing = res.product_psd.passing_pct
        if prev is not None:
            assert np.all(passing >= prev - 1e-9)
        prev = passing
    assert prev[10] > feed.passing_pct[10] + 1.0


def test_out_of_range_sizes_reported_and_operating_point_warns(feed):
    prov = TableProvider(synthetic_table(sizes_mm=(2.0, 30.0)), source="SYNTHETIC")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        res = Mill("UG2", prov).run(feed, OperatingPoint(feed_tph=30.0, speed_rpm=1500.0, gate_deg=40.0))
    mids = res.feed_psd.grid.mids_mm
    out = (mids < 2.0) | (mids > 30.0)
    assert res.extrapolated_feed_pct == pytest.approx(100 * feed.fractions[out].sum())
    assert res.extrapolated_product_pct == pytest.approx(100 * res.product_psd.fractions[out].sum())
    assert 0 < res.extrapolated_feed_pct < 100
    # extrapolated sizes are reported, and warned only as a share above EXTRAPOLATED_WARN_PCT of the product
    domain = [w for w in caught if issubclass(w.category, OutOfDomainWarning)]
    share = [w for w in domain if issubclass(w.category, ExtrapolationWarning)]
    assert len(domain) == len(share) == (1 if res.extrapolated_product_pct > EXTRAPOLATED_WARN_PCT else 0)
    with pytest.warns(OutOfDomainWarning, match="another operating point"):
        Mill("UG2", prov).run(feed, OperatingPoint(feed_tph=45.0, speed_rpm=1700.0, gate_deg=40.0))
    grid = SizeGrid.geometric(2.0, 30.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error", OutOfDomainWarning)
        Mill("UG2", prov, grid=SizeGrid(np.sqrt(grid.edges_mm[:-1] * grid.edges_mm[1:]).clip(2.0, 30.0)[[0, -1]])
             ).provider.stage_parameters(np.array([2.0, 10.0, 30.0]), [1500.0] * 4 + [3000.0], 30.0, 40.0)


def test_region_weighted_streams(run_stats):
    w = [0.1, 0.2, 0.2, 0.2, 0.2, 0.1]
    rs = [[0.0, 0.5, 0.5]] * 3 + [[0.2, 0.2, 0.6]] * 3
    stages = [s.model_copy(update={"region_weights": w, "region_streams": rs}) for s in run_stats.stages]
    prov = RunProvider(run_stats.model_copy(update={"stages": stages}))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        params = prov.stage_parameters(np.array([10.0]))
    s = resolve("transport", "regions", None).streams(params)
    assert np.allclose(s[0, 0], [0.1, 0.35, 0.55])
    assert np.allclose(resolve("transport", "bulk", None).streams(params)[0, 0], run_stats.stages[0].streams)


def test_ev_operator_columns_are_probabilities(provider, grid, op):
    mill = Mill("UG2", provider)
    _, streams, stats, _, _ = mill.prepare(grid, op)
    with __import__("threadpoolctl").threadpool_limits(1, user_api="blas"):
        lm = assemble(grid.edges_mm, streams, stats, mill.breakage, mill.damage, 4, 8)
    for st in lm.stages:
        assert np.allclose(st.G.sum(axis=0), 1.0, atol=1e-12)
        assert st.G.min() >= -1e-14


def test_solvers_agree_all_impacted_with_damage_threshold(provider, feed, op):
    """The other semantics and threshold breakage: still K-S < 0.01 (continuous MC damage)."""
    from msmill.ore import get_ore

    ore = BreakageParameters.from_ore(get_ore("UG2").with_l_ref(5.0, "test"))
    ore = BreakageParameters(**{**ore.__dict__, "damage_threshold": 0.3})
    kw = dict(impacted="all", damage_classes=12)
    ev = Mill(ore, provider, **kw).run(feed, op)
    mc = Mill(ore, provider, solver="monte_carlo", seed=11, parcels_per_step=1000, **kw).run(feed, op)
    assert ev.reduction_ratio > 1.2
    assert ks_statistic(ev.product_psd, mc.product_psd) < 0.01
