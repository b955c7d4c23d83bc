"""Model fidelity (issue 15): transport matrix, one t10 convention, sizes outside the data, stopped rotors."""

from __future__ import annotations

import warnings

import numpy as np
import pandas as pd
import pytest
from synthetic import synthetic_run, synthetic_table

from msmill.breakage import population_t10_pct
from msmill.calibration import calibrate
from msmill.errors import OutOfDomainWarning
from msmill.machine import OperatingPoint
from msmill.model import Mill, RunProvider, TableProvider
from msmill.model.expected_value import assemble
from msmill.model.montecarlo import MonteCarloSolver
from msmill.model.submodels import (
    SUBMODELS,
    BreakageParameters,
    NoDamage,
    Transition,
    lab_test,
    resolve,
    simulate_lab_test,
)
from msmill.psd import PSD, SizeGrid
from msmill.stageparams import StageParameterTable

OP = OperatingPoint(feed_tph=30.0, speed_rpm=1500.0, gate_deg=40.0)
JK_SIZES_MM = np.array([14.5, 20.6, 28.9, 41.1, 57.8])
ENERGIES_KWH_T = np.array([0.1, 0.25, 1.0])


# ------------------------------------------------------------------ transport
def _with_destinations(run, inlet, dests):
    stages = [s.model_copy(update={"destinations": d}) for s, d in zip(run.stages, dests, strict=True)]
    return run.model_copy(update={"stages": stages, "inlet_destinations": inlet})


def _three_stream_destinations(run):
    """Destinations that say exactly what the three streams say (one-stage moves)."""
    n = run.n_stages
    out = []
    for s in run.stages:
        d = np.zeros(n + 2)
        d[s.stage - 1], d[s.stage], d[s.stage + 1] = s.kickback, s.refeed, s.pass_through
        out.append(d.tolist())
    return out


def test_matrix_transport_with_one_stage_moves_is_the_streams_plus_one_step_in_the_inlet():
    """Inlet row 'all to stage 1' + one-stage destinations = the three-stream scheme, except that the
    fresh feed spends its first step in the inlet zone: same product, hold-up larger by one step's feed."""
    run = synthetic_run(10.0)
    inlet = [0.0, 1.0] + [0.0] * run.n_stages
    prov = RunProvider(_with_destinations(run, inlet, _three_stream_destinations(run)))
    grid = SizeGrid.geometric(0.5, 16.0)
    feed = PSD(grid, np.eye(grid.n_classes)[-2])
    op = OperatingPoint(feed_tph=30.0, stage_speeds_rpm=run.design.stage_speeds_rpm, gate_deg=40.0)
    a = Mill("UG2", prov, transport="bulk", grid=grid).run(feed, op)
    b = Mill("UG2", prov, transport="dem_matrix", grid=grid).run(feed, op)
    assert np.allclose(a.product_psd.fractions, b.product_psd.fractions, atol=1e-12)
    step_t = 30.0 * run.characteristic_time_s / 3600.0
    assert b.timeseries["holdup_t"].iloc[-1] == pytest.approx(a.timeseries["holdup_t"].iloc[-1] + step_t, rel=1e-4)
    assert b.mass_balance_error < 1e-12


def _random_transition(rng, n_stages, n):
    T = rng.dirichlet(np.ones(n_stages + 2), size=(n_stages + 1, n))
    T[0, :, n_stages + 1] = 0.0  # nothing leaves straight from the inlet zone
    T[-1, :, -1] += 0.1  # the bottom stage lets something out
    return Transition(T / T.sum(axis=-1, keepdims=True), feed_compartment=0)


def test_unbreakable_rock_residence_is_littles_law_of_the_matrix():
    """No breakage: steady hold-up = (I - Q^T)^-1 f for the compartment matrix Q (per size class)."""
    rng = np.random.default_rng(3)
    grid = SizeGrid.geometric(1.0, 8.0)
    n, n_st = grid.n_classes, 4
    tr = _random_transition(rng, n_st, n)
    stats = resolve("impacts", "dem", None).impacts(
        RunProvider(synthetic_run(5.0, n_stages=n_st)).stage_parameters(grid.mids_mm), None)
    lm = assemble(grid.edges_mm, tr, stats, SUBMODELS["breakage"]["none"](None), NoDamage(), 1, 4)
    feed = np.full(n, 1.0 / n)
    x = lm.steady_state(lm.feed_vector(feed, 1.0)).reshape(n_st + 1, n)
    for i in range(n):
        Q = tr.matrix[:, i, : n_st + 1]
        f = np.zeros(n_st + 1)
        f[0] = feed[i]
        assert np.allclose(x[:, i], np.linalg.solve(np.eye(n_st + 1) - Q.T, f), rtol=1e-10)


@pytest.mark.parametrize("impacted", ["refeed", "all"])
def test_matrix_transport_mass_balance_and_monte_carlo_agree(impacted):
    rng = np.random.default_rng(7)
    grid = SizeGrid.geometric(0.5, 16.0)
    n_st = 3
    tr = _random_transition(rng, n_st, grid.n_classes)
    mill = Mill("UG2", RunProvider(synthetic_run(8.0, n_stages=n_st)), grid=grid)
    op = OperatingPoint(feed_tph=30.0, stage_speeds_rpm=[1500.0] * 2 + [3000], gate_deg=40.0)
    _, _, stats, _, _ = mill.prepare(grid, op)
    lm = assemble(grid.edges_mm, tr, stats, mill.breakage, NoDamage(), 1, 6, impacted)
    colsum = np.asarray(lm.M.sum(axis=0)).ravel() + np.asarray(lm.out_op.sum(axis=0)).ravel()
    assert np.allclose(colsum, 1.0, atol=1e-12)
    feed = np.eye(grid.n_classes)[-1]
    x = lm.steady_state(lm.feed_vector(feed, 1.0))
    ev = np.asarray(lm.out_op @ x)
    mc = MonteCarloSolver(800, seed=5).run(grid.edges_mm, tr, stats, mill.breakage, NoDamage(), feed, 1.0,
                                           260, 60, impacted)
    prod = mc.product[60:].sum(axis=0)
    assert mc.mass_balance_error.max() < 1e-12
    assert np.abs(np.cumsum(prod / prod.sum()) - np.cumsum(ev / ev.sum())).max() < 0.02


# ------------------------------------------------------------------ t10 convention
@pytest.mark.parametrize("name", ["ab_t10", "jk_t10"])
def test_simulated_lab_test_is_the_convention_calibration_uses(name):
    """The drop-weight test simulated through the sub-model (probability and fragments) gives the
    population t10 of the sub-model's convention, which is what calibration fits."""
    factory = SUBMODELS["breakage"][name]
    ore = BreakageParameters("x", A_pct=62.0, b_t_per_kwh=1.3, l_ref_mm=24.0)
    size, e = np.meshgrid(JK_SIZES_MM, ENERGIES_KWH_T)
    sim = simulate_lab_test(factory(ore), size, e)
    closed = population_t10_pct(e, size, 62.0, 1.3, 24.0, factory.t10_convention)
    assert np.allclose(sim, closed, atol=2e-3)
    other = "jk" if factory.t10_convention == "paper" else "paper"
    assert not np.allclose(sim, population_t10_pct(e, size, 62.0, 1.3, 24.0, other), atol=1.0)


def _lab_data(name, A, b, l_ref, noise_pct, seed, repeats=2):
    size, e = (a.ravel() for a in np.meshgrid(JK_SIZES_MM, ENERGIES_KWH_T))
    size, e = np.repeat(size, repeats), np.repeat(e, repeats)
    t10 = lab_test(name)(size, e, A, b, l_ref)
    t10 = t10 + np.random.default_rng(seed).normal(0.0, noise_pct, t10.size)
    return pd.DataFrame({"size_mm": size, "ecs_kwh_t": e, "t10_pct": np.clip(t10, 0.0, 100.0)})


@pytest.mark.parametrize("name", ["ab_t10", "jk_t10"])
def test_calibration_round_trip_per_submodel(name):
    """Data made by simulating the lab test through a sub-model; calibrating that sub-model recovers A, L_ref."""
    data = _lab_data(name, 58.0, 1.67, 22.0, noise_pct=0.5, seed=1)
    res = calibrate(data, fit=("A_pct", "l_ref_mm"), b_t_per_kwh=1.67, A_pct=70.0, l_ref_mm=29.0,
                    lab_test=lab_test(name))
    for k, true in (("A_pct", 58.0), ("l_ref_mm", 22.0)):
        assert abs(res.params[k] - true) < 4 * res.std_errors[k] + 1e-9, (k, res.params[k], res.std_errors[k])
        assert res.params[k] == pytest.approx(true, rel=0.05)
    # the closed-form convention gives the same fit
    conv = SUBMODELS["breakage"][name].t10_convention
    res2 = calibrate(data, fit=("A_pct", "l_ref_mm"), b_t_per_kwh=1.67, A_pct=70.0, l_ref_mm=29.0, convention=conv)
    assert res2.params["A_pct"] == pytest.approx(res.params["A_pct"], rel=1e-3)


def _lab_mill_t10(ore, name, size_mm, ecs_kwh_t):
    """The drop-weight test run through the mill model: one stage, every rock hit exactly once at the test
    energy and passed straight out; t10 = product % passing a tenth of the rock size."""
    edges = size_mm * np.concatenate([0.1 * 2.0 ** (np.arange(-8, 7) / 2.0), [1.25]])
    grid = SizeGrid(edges)
    run = synthetic_run(size_mm, n_stages=1, hit=1.0, lam=0.0, kick=0.0, refeed=0.0)
    v = float(np.sqrt(2.0 * ecs_kwh_t * 3600.0))
    st = run.stages[0].model_copy(update={"primary_velocity": run.stages[0].primary_velocity.single(v, 1e-6)})
    prov = RunProvider(run.model_copy(update={"stages": [st]}))
    feed = PSD(grid, np.eye(grid.n_classes)[-1])
    op = OperatingPoint(feed_tph=30.0, stage_speeds_rpm=run.design.stage_speeds_rpm, gate_deg=40.0)
    res = Mill(ore, prov, breakage=name, impacts="dem", damage="none", grid=grid, impacted="all").run(feed, op)
    return float(res.product_psd.passing_at(size_mm / 10.0))


@pytest.mark.parametrize("name", ["ab_t10", "jk_t10"])
def test_calibrated_ore_reproduces_its_drop_weight_data_through_the_model(name):
    noise = 1.0
    data = _lab_data(name, 66.0, 1.5, 26.0, noise_pct=noise, seed=4)
    res = calibrate(data, fit=("A_pct", "l_ref_mm"), b_t_per_kwh=1.5, A_pct=70.0, l_ref_mm=29.0,
                    lab_test=lab_test(name))
    ore = BreakageParameters("calibrated", A_pct=res.params["A_pct"], b_t_per_kwh=1.5, l_ref_mm=res.params["l_ref_mm"])
    means = data.groupby(["size_mm", "ecs_kwh_t"])["t10_pct"].mean()
    for (size, e), t10_data in means.items():
        t10_model = _lab_mill_t10(ore, name, size, e)
        assert abs(t10_model - t10_data) < 3 * noise / np.sqrt(2), (size, e, t10_model, t10_data)


# ------------------------------------------------------------------ outside the data, stopped rotors
def test_extrapolation_continues_the_tables_trend_within_its_reach():
    """A quantity linear in ln(size) over the table is continued exactly, up to one table span, then held."""
    runs = []
    for size in (4.0, 8.0, 16.0):
        r = synthetic_run(size, hit=0.1 + 0.05 * np.log(size))
        runs.append(r)
    prov = TableProvider(StageParameterTable(runs=runs))
    sizes = np.array([0.25, 1.0, 2.0, 4.0, 32.0, 64.0, 500.0])
    with warnings.catch_warnings():
        warnings.simplefilter("error", OutOfDomainWarning)
        p = prov.stage_parameters(sizes)
    reach = np.clip(sizes, 1.0, 64.0)  # 4-16 mm covers ln 4; one span further each way
    assert np.allclose(p.hit_probability[0], 0.1 + 0.05 * np.log(reach), atol=1e-12)
    assert p.extrapolated.tolist() == [True, True, True, False, True, True, True]
    assert np.all(p.secondary_lambda >= 0) and np.allclose(p.streams.sum(axis=-1), 1.0)


def test_stopped_stage_breaks_nothing():
    prov = TableProvider(synthetic_table(), source="SYNTHETIC")
    feed = PSD.from_passing([2, 4.75, 9.5, 19, 31.5], [2, 6, 18, 58, 100])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", OutOfDomainWarning)  # measured at turning rotors
        for impacts in ("dem", "speed_scaled"):
            res = Mill("UG2", prov, impacts=impacts).run(feed, OperatingPoint(
                feed_tph=30.0, stage_speeds_rpm=[0.0] * 5, gate_deg=40.0))
            assert np.allclose(res.product_psd.fractions, res.feed_psd.fractions, atol=1e-12)
            assert res.primary_impacts_per_t == 0.0 and res.secondary_impacts_per_t == 0.0
        res = Mill("UG2", prov, impacts="dem").run(feed, OperatingPoint(
            feed_tph=30.0, stage_speeds_rpm=[1500.0, 0.0, 1500.0, 1500.0, 3000.0], gate_deg=40.0))
    s = res.stages.set_index("stage")
    assert s.loc[2, "primary_impacts_per_t"] == 0.0 and s.loc[2, "impact_energy_kwh_t"] == 0.0
    assert s.loc[1, "primary_impacts_per_t"] > 0.0


def test_matrix_measured_at_another_lag_is_converted_to_the_step():
    """A matrix measured at half the model step is applied twice per step: P(step) = P(lag)^2."""
    import dataclasses

    rng = np.random.default_rng(11)
    run = synthetic_run(10.0)
    n = run.n_stages
    inlet = rng.dirichlet(np.ones(2)).tolist() + [0.0] * n
    dests = [rng.dirichlet(np.ones(n + 2)).tolist() for _ in run.stages]
    prov = RunProvider(_with_destinations(run, inlet, dests))
    p = prov.stage_parameters(np.array([5.0, 10.0]))
    transport = resolve("transport", "dem_matrix", None)
    assert np.allclose(transport.transition(p).matrix, p.transition)  # measured at the step: as is
    half = dataclasses.replace(p, transition_lag_s=np.full(2, 0.5 * p.characteristic_time_s))
    Q = np.eye(n + 2)
    Q[: n + 1] = np.array([inlet, *dests])
    assert np.allclose(transport.transition(half).matrix[:, 0, :], (Q @ Q)[: n + 1], atol=1e-9)


def test_speed_scaled_impacts_keep_a_predicting_providers_count_mixture():
    """Parameters predicted at the requested speeds (the surrogate) are used as given, counts included."""
    import dataclasses

    from msmill.model.submodels import SpeedScaledImpacts

    p = TableProvider(synthetic_table(), source="SYNTHETIC").stage_parameters(np.array([10.0, 20.0]))
    assert p.secondary_count is not None  # the synthetic runs carry count mixtures
    at_speed = dataclasses.replace(p, velocities_at_requested_speeds=True)
    out = SpeedScaledImpacts().impacts(at_speed, np.array([1800.0] * 4 + [3600.0]))
    assert out.secondary_count is p.secondary_count
    assert np.array_equal(out.primary_velocity.means_m_s, p.primary_velocity.means_m_s)  # not rescaled again
