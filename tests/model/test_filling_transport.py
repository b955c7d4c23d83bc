"""The fill-dependent transport ``dem_matrix_fill`` (issue 15): its definition, its steady-state anchor,
mass conservation of the march, the filling measurement of the DEM statistics, and the schema field."""

from __future__ import annotations

import warnings

import numpy as np
import pandas as pd
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from synthetic import synthetic_run

from msmill.dem.mill.stats import filling_transport
from msmill.errors import MsmillInputError
from msmill.machine import Machine, OperatingPoint
from msmill.model import Mill, RunProvider
from msmill.model.expected_value import assemble
from msmill.model.providers import (
    TableProvider,
    WithFillingCurves,
    default_table_path,
    load_provider,
    pool_filling_curves,
    pooled_filling,
)
from msmill.model.submodels import (
    DEFAULTS,
    SUBMODELS,
    FillingMatrixTransport,
    MatrixTransport,
    NoDamage,
    Transition,
    resolve,
)
from msmill.psd import PSD, SizeGrid
from msmill.stageparams import (
    FillingTags,
    FillingTransport,
    RunStatistics,
    StageParameterTable,
    chain_residence_steps,
    filling_curve_from_tags,
)

N_ST = 3
DEFAULT_TRANSPORT = DEFAULTS["transport"]
OP = OperatingPoint(feed_tph=30.0, stage_speeds_rpm=[1500.0] * (N_ST - 1) + [3000.0], gate_deg=40.0)


def _destinations(n_stages: int) -> tuple[list[float], list[list[float]]]:
    """SYNTHETIC one-lag destinations: the inlet zone holds half, a stage keeps 40 % and passes most on."""
    inlet = [0.5, 0.5] + [0.0] * n_stages
    dests = []
    for s in range(1, n_stages + 1):
        d = np.zeros(n_stages + 2)
        d[s - 1], d[s], d[s + 1] = (0.0 if s == 1 else 0.1), 0.4, (0.6 if s == 1 else 0.5)
        dests.append(d.tolist())
    return inlet, dests


def _run(filling: FillingTransport | None, size_mm: float = 8.0) -> RunStatistics:
    run = synthetic_run(size_mm, n_stages=N_ST)
    inlet, dests = _destinations(N_ST)
    stages = [s.model_copy(update={"destinations": d}) for s, d in zip(run.stages, dests, strict=True)]
    return run.model_copy(update={"stages": stages, "inlet_destinations": inlet, "filling_transport": filling})


def _curve(fill, ratio) -> FillingTransport:
    return FillingTransport(fill=list(fill), residence_ratio=list(ratio), tag_mass_kg=[1.0] * len(fill))


def _mill_run(run: RunStatistics, transport: str, ore: str = "UG2"):
    grid = SizeGrid.geometric(1.0, 16.0)
    feed = PSD(grid, np.eye(grid.n_classes)[-1])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return Mill(ore, RunProvider(run), transport=transport, grid=grid, damage_classes=2).run(feed, OP)


def _assert_march_conserves_mass(lm, f: np.ndarray, n_steps: int) -> None:
    """March from empty with feed ``f`` per step: the state stays non-negative and fed = held + out."""
    steady = float(lm.steady_state(f).sum())
    x, fed, out = np.zeros(lm.n_state), 0.0, 0.0
    for _ in range(n_steps):
        x, o = lm.step(x, float(x.sum()) / steady)
        x = x + f
        fed, out = fed + 1.0, out + o
        assert np.all(x >= -1e-14)
        assert fed == pytest.approx(float(x.sum()) + out, rel=1e-12)


# ------------------------------------------------------------------ definition
def test_speed_is_the_inverse_ratio_linear_up_to_one_at_the_steady_hold_up():
    tr = Transition(np.zeros((1, 1, 2)), filling=(np.array([0.2, 0.6]), np.array([0.4, 0.8])))
    assert tr.speed_at(0.0) == pytest.approx(1 / 0.4)  # the first point's below it
    assert tr.speed_at(0.2) == pytest.approx(1 / 0.4)
    assert tr.speed_at(0.4) == pytest.approx(1 / 0.6)
    assert tr.speed_at(0.8) == pytest.approx(1 / 0.9)  # halfway from (0.6, 0.8) to (1, 1)
    assert tr.speed_at(1.0) == 1.0
    assert tr.speed_at(1.7) == 1.0
    assert Transition(np.zeros((1, 1, 2))).speed_at(0.1) == 1.0


def test_a_faster_step_divides_the_time_per_visit_and_keeps_the_destinations():
    rng = np.random.default_rng(1)
    T = rng.dirichlet(np.ones(5), size=(4, 3))
    tr = Transition(T, feed_compartment=0)
    c = np.arange(4)
    for g in (0.5, 1.3, 50.0):
        P = tr.at_speed(g)
        assert np.all(P >= -1e-15) and np.allclose(P.sum(axis=-1), 1.0)
        gs = np.minimum(g, tr.max_speed())[:, None]
        assert np.allclose(1.0 / (1.0 - P[c, :, c]), 1.0 / (gs * (1.0 - T[c, :, c])))  # visits g times shorter
        leave_t, leave_p = T.copy(), P.copy()
        leave_t[c, :, c] = leave_p[c, :, c] = 0.0
        assert np.allclose(leave_p / leave_p.sum(-1, keepdims=True), leave_t / leave_t.sum(-1, keepdims=True))
    assert np.allclose(tr.at_speed(50.0)[c, :, c].min(axis=1), 0.0)  # capped where nothing would stay


def test_hand_recursion_of_a_two_compartment_mill():
    """One stage, one size class, no breakage: the march is x' = x P(g(h)) + f, h = x.sum() / x_ss.sum()."""
    T = np.array([[[0.5, 0.5, 0.0]], [[0.1, 0.6, 0.3]]])
    curve = (np.array([0.1, 0.5]), np.array([0.3, 0.7]))
    tr = Transition(T, feed_compartment=0, filling=curve)
    grid = SizeGrid(np.array([9.0, 11.0]))
    params = RunProvider(synthetic_run(10.0, n_stages=1)).stage_parameters(grid.mids_mm)
    stats = resolve("impacts", "dem", None).impacts(params, None)
    lm = assemble(grid.edges_mm, tr, stats, SUBMODELS["breakage"]["none"](None), NoDamage(), 1, 4)
    f = lm.feed_vector(np.array([1.0]), 1.0)
    x_ss = lm.steady_state(f)
    q = T[:, 0, :2]
    assert np.allclose(x_ss, np.linalg.solve(np.eye(2) - q.T, [1.0, 0.0]))  # the steady chain's
    x, y = np.zeros(2), np.zeros(2)
    for _ in range(60):
        h = y.sum() / x_ss.sum()
        r = np.interp(min(h, 1.0), [0.1, 0.5, 1.0], [0.3, 0.7, 1.0])
        g = np.minimum(1.0 / r, 1.0 / (1.0 - np.array([0.5, 0.6])))  # one class: its own cap
        P = q + (g - 1.0)[:, None] * (q - np.eye(2))
        out_hand = float(y @ (g * T[:, 0, 2]))
        y = y @ P + np.array([1.0, 0.0])
        x, out = lm.step(x, float(x.sum()) / x_ss.sum())
        x = x + f
        assert out == pytest.approx(out_hand, rel=1e-12, abs=1e-15)
        assert np.allclose(x, y, rtol=1e-12)


@pytest.mark.parametrize("impacted", ["refeed", "all"])
@pytest.mark.parametrize("ratio", [0.3, 0.8, 1.5])
def test_a_step_at_speed_g_is_the_mill_assembled_from_the_matrix_at_speed_g(impacted, ratio):
    """Linearity in the transport: ``step`` at fill 0 (speed 1 / ratio) = the operator built from ``at_speed``."""
    rng = np.random.default_rng(11)
    grid = SizeGrid.geometric(1.0, 16.0)
    T = rng.dirichlet(np.ones(N_ST + 2), size=(N_ST + 1, grid.n_classes))
    tr = Transition(T, feed_compartment=0, filling=(np.array([0.5]), np.array([ratio])))
    mill = Mill("UG2", RunProvider(synthetic_run(8.0, n_stages=N_ST)), grid=grid)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        _, _, stats, _, _ = mill.prepare(grid, OP)
    lm = assemble(grid.edges_mm, tr, stats, mill.breakage, NoDamage(), 2, 4, impacted)
    ref = assemble(grid.edges_mm, Transition(tr.at_speed(1.0 / ratio), feed_compartment=0), stats, mill.breakage,
                   NoDamage(), 2, 4, impacted)
    x = rng.random(lm.n_state)
    y, out = lm.step(x, 0.0)
    assert np.allclose(y, ref.M @ x, rtol=1e-12, atol=1e-15)
    assert out == pytest.approx(float((ref.out_op @ x).sum()), rel=1e-12)


def test_per_class_curves_move_each_class_at_its_own_speed():
    """Curves per size class (N, K): the speed is per class, and a step at fill ``h`` is the mill assembled
    from the matrix whose class-``i`` rows run at that class's speed (impacts on the mass that stays)."""
    rng = np.random.default_rng(5)
    grid = SizeGrid.geometric(1.0, 4.0)  # 4 classes
    T = rng.dirichlet(np.ones(N_ST + 2), size=(N_ST + 1, grid.n_classes))
    ratios = np.array([[0.3, 0.9], [0.5, 0.6], [0.8, 1.1], [1.0, 1.0]])
    tr = Transition(T, feed_compartment=0, filling=(np.array([0.2, 0.6]), ratios))
    assert tr.per_class_filling
    assert np.allclose(tr.speed_at(0.1), 1.0 / ratios[:, 0])  # the first point's below it
    assert np.allclose(tr.speed_at(0.4), 1.0 / ratios.mean(axis=1))  # halfway between the points
    assert np.allclose(tr.speed_at(0.8), 1.0 / (0.5 * ratios[:, 1] + 0.5))  # halfway to (1, 1)
    assert np.allclose(tr.speed_at(1.3), 1.0)
    mill = Mill("UG2", RunProvider(synthetic_run(8.0, n_stages=N_ST)), grid=grid)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        _, _, stats, _, _ = mill.prepare(grid, OP)
    lm = assemble(grid.edges_mm, tr, stats, mill.breakage, NoDamage(), 2, 4, "refeed")
    for fill in (0.1, 0.4, 0.8):
        ref = assemble(grid.edges_mm, Transition(tr.at_speed(tr.speed_at(fill)), feed_compartment=0), stats,
                       mill.breakage, NoDamage(), 2, 4, "refeed")
        x = rng.random(lm.n_state)
        y, out = lm.step(x, fill)
        assert np.allclose(y, ref.M @ x, rtol=1e-12, atol=1e-15)
        assert out == pytest.approx(float((ref.out_op @ x).sum()), rel=1e-12)
    c = np.arange(N_ST + 1)
    assert np.allclose(tr.at_speed(1e6)[c, :, c], 0.0)  # capped per class where nothing would stay


def test_table_gives_each_size_its_runs_curve_interpolated_in_log_size_and_held_outside():
    r1 = _run(FillingTransport(fill=[0.1, 0.5], residence_ratio=[0.2, 0.6], tag_mass_kg=[1.0, 2.0]), 8.0)
    r2 = _run(FillingTransport(fill=[0.1, 0.5], residence_ratio=[0.6, 0.9], tag_mass_kg=[3.0, 3.0]), 32.0)
    params = TableProvider(StageParameterTable(runs=[r1, r2])).stage_parameters(np.array([4.0, 8.0, 16.0, 32.0, 64.0]))
    assert np.allclose(params.filling_fill, [0.1, 0.5])
    expect = np.array([[0.2, 0.6], [0.2, 0.6], [0.4, 0.75], [0.6, 0.9], [0.6, 0.9]])  # 16 mm: halfway in ln(size)
    assert np.allclose(params.filling_residence_ratio, expect)
    tr = FillingMatrixTransport().transition(params)
    assert np.allclose(tr.speed_at(0.0), 1.0 / expect[:, 0])


@settings(max_examples=20, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 10_000), ratios=st.lists(st.floats(0.05, 2.0), min_size=8, max_size=8))
def test_the_march_with_per_class_curves_conserves_mass_and_stays_non_negative(seed, ratios):
    rng = np.random.default_rng(seed)
    grid = SizeGrid.geometric(2.0, 8.0)
    n = grid.n_classes
    T = rng.dirichlet(np.ones(N_ST + 2), size=(N_ST + 1, n))
    T[-1, :, -1] += 0.2
    T /= T.sum(axis=-1, keepdims=True)
    tr = Transition(T, feed_compartment=0, filling=(np.array([0.2, 0.7]), np.reshape(ratios[: 2 * n], (n, 2))))
    mill = Mill("UG2", RunProvider(synthetic_run(8.0, n_stages=N_ST)), grid=grid)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        _, _, stats, _, _ = mill.prepare(grid, OP)
    lm = assemble(grid.edges_mm, tr, stats, mill.breakage, NoDamage(), 2, 4, "refeed")
    f = lm.feed_vector(np.full(n, 1.0 / n), 1.0)
    _assert_march_conserves_mass(lm, f, 30)


# ------------------------------------------------------------------ anchor at steady state
def test_ratio_one_everywhere_is_dem_matrix_exactly():
    a = _mill_run(_run(_curve([0.3, 0.7], [1.0, 1.0])), "dem_matrix")
    b = _mill_run(_run(_curve([0.3, 0.7], [1.0, 1.0])), "dem_matrix_fill")
    assert np.array_equal(a.timeseries["holdup_t"].to_numpy(), b.timeseries["holdup_t"].to_numpy())
    assert np.array_equal(a.timeseries["product_tph"].to_numpy(), b.timeseries["product_tph"].to_numpy())
    assert np.array_equal(a.product_psd.fractions, b.product_psd.fractions)


def test_steady_state_is_dem_matrix_and_a_faster_empty_mill_fills_later():
    run = _run(_curve([0.15, 0.5, 0.8], [0.35, 0.6, 0.9]))
    a, b = _mill_run(run, "dem_matrix"), _mill_run(run, "dem_matrix_fill")
    assert np.allclose(a.product_psd.fractions, b.product_psd.fractions, rtol=1e-12, atol=1e-15)
    assert b.p80_mm == pytest.approx(a.p80_mm, rel=1e-12)
    hold_a, hold_b = a.timeseries["holdup_t"].to_numpy(), b.timeseries["holdup_t"].to_numpy()
    assert hold_b[-1] == pytest.approx(hold_a[-1], rel=1e-4)  # the march reaches the same steady state
    k = min(hold_a.size, hold_b.size) // 3
    assert np.all(hold_b[:k] <= hold_a[:k] * (1 + 1e-12))  # rock moving faster in an emptier mill
    assert hold_b[k - 1] < 0.9 * hold_a[k - 1]  # ... holds less once some has left
    assert b.time_to_steady_state_s > a.time_to_steady_state_s
    assert b.mass_balance_error < 1e-10


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 10_000), n_st=st.integers(1, 3), n_cls=st.integers(1, 3),
       fills=st.lists(st.floats(0.0, 0.95), min_size=1, max_size=4, unique=True),
       ratios=st.lists(st.floats(0.05, 2.0), min_size=4, max_size=4))
def test_the_march_conserves_mass_and_stays_non_negative(seed, n_st, n_cls, fills, ratios):
    rng = np.random.default_rng(seed)
    T = rng.dirichlet(np.ones(n_st + 2), size=(n_st + 1, n_cls))
    T[-1, :, -1] += 0.2
    T /= T.sum(axis=-1, keepdims=True)
    h = np.sort(np.array(fills))
    tr = Transition(T, feed_compartment=0, filling=(h, np.array(ratios[: h.size])))
    grid = SizeGrid.geometric(2.0, 2.0 * 2.0 ** (n_cls / 2))
    mill = Mill("UG2", RunProvider(synthetic_run(8.0, n_stages=n_st)), grid=grid)
    op = OperatingPoint(feed_tph=30.0, stage_speeds_rpm=[1500.0] * n_st, gate_deg=40.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        _, _, stats, _, _ = mill.prepare(grid, op)
    lm = assemble(grid.edges_mm, tr, stats, mill.breakage, NoDamage(), 1, 4)
    f = lm.feed_vector(np.full(n_cls, 1.0 / n_cls), 1.0)
    _assert_march_conserves_mass(lm, f, 40)


# ------------------------------------------------------------------ the sub-model
def test_submodel_leaves_out_points_where_the_mill_could_not_fill_and_notes_it():
    params = RunProvider(_run(_curve([0.2, 0.5, 0.8], [0.4, 0.45, 0.9]))).stage_parameters(np.array([8.0]))
    tr = FillingMatrixTransport().transition(params)
    # per size class (the provider's curves are per class): the point at 0.5 is bridged by its neighbours,
    # so the curve is the one without it
    without = lambda h: np.interp(h, [0.2, 0.8, 1.0], [0.4, 0.9, 1.0])  # noqa: E731
    assert tr.per_class_filling and np.allclose(tr.filling[1], without(tr.filling[0]))
    for fill in (0.1, 0.35, 0.5, 0.65, 0.9, 1.2):
        assert tr.speed_at(fill) == pytest.approx(1.0 / without(min(fill, 1.0)))
    assert "0.5" in tr.note
    assert np.array_equal(tr.matrix, MatrixTransport().transition(params).matrix)


def test_submodel_without_filling_data_is_the_steady_matrix_with_a_note():
    params = RunProvider(_run(None)).stage_parameters(np.array([8.0]))
    tr = FillingMatrixTransport().transition(params)
    assert tr.filling is None and "no filling transport" in tr.note
    assert np.array_equal(tr.matrix, MatrixTransport().transition(params).matrix)


def test_table_pools_the_runs_curves_by_tagged_mass():
    r1 = _run(FillingTransport(fill=[0.1, 0.5], residence_ratio=[0.2, 0.6], tag_mass_kg=[1.0, 2.0]))
    r2 = _run(FillingTransport(fill=[0.3, 0.7], residence_ratio=[0.5, 0.9], tag_mass_kg=[3.0, 3.0]))
    fill, ratio = pooled_filling([r1, r2])
    # bins [0, 0.2), [0.2, 0.4), [0.4, 0.6), [0.6, 0.8): one run's point each
    assert np.allclose(fill, [0.1, 0.3, 0.5, 0.7])
    own1 = np.interp(fill, [0.1, 0.5, 1.0], [0.2, 0.6, 1.0])
    own2 = np.interp(fill, [0.3, 0.7, 1.0], [0.5, 0.9, 1.0])
    assert np.allclose(ratio, (3.0 * own1 + 6.0 * own2) / 9.0)
    assert pooled_filling([r1, _run(None)]) is None


def test_curves_of_one_point_pool_by_tagged_mass_bin_by_bin():
    a = FillingTransport(fill=[0.1, 0.3, 0.5], residence_ratio=[0.2, 0.4, 0.6], tag_mass_kg=[1.0, 1.0, 2.0])
    b = FillingTransport(fill=[0.14, 0.5], residence_ratio=[0.5, 0.9], tag_mass_kg=[3.0, 9.0])
    c = pool_filling_curves([a, b])
    assert np.allclose(c.fill, [(0.1 + 3 * 0.14) / 4, 0.3, 0.5])  # bins [0, 0.2), [0.2, 0.4), [0.4, 0.6)
    assert np.allclose(c.tag_mass_kg, [4.0, 1.0, 11.0])
    expect = (4.0 * a.ratio_at(np.array(c.fill)) + 12.0 * b.ratio_at(np.array(c.fill))) / 16.0
    assert np.allclose(c.residence_ratio, expect)
    assert pool_filling_curves([a]) == a
    with pytest.raises(ValueError):
        pool_filling_curves([])


def test_curves_with_their_window_references_pool_against_the_common_reference():
    """Two runs of one point whose short windows mis-measured the steady hold-up and chain residence
    (low by 10 %, high by 10 %): on the common reference (their mean) both are the true curve."""
    true_fill, true_ratio = np.array([0.15, 0.45, 0.75]), np.array([0.4, 0.7, 0.9])

    def measured(k: float) -> FillingTransport:  # window hold-up and chain residence k times the true ones
        return FillingTransport(fill=(true_fill / k).tolist(), residence_ratio=(true_ratio / k).tolist(),
                                tag_mass_kg=[1.0, 2.0, 3.0], window_residence_steps=10.0 * k,
                                window_holdup_kg=100.0 * k)

    c = pool_filling_curves([measured(0.9), measured(1.1)])
    assert c.window_holdup_kg == pytest.approx(100.0) and c.window_residence_steps == pytest.approx(10.0)
    assert np.allclose(c.fill, true_fill) and np.allclose(c.residence_ratio, true_ratio)
    assert np.allclose(c.tag_mass_kg, [2.0, 4.0, 6.0])
    # without the references each is taken as it is: the mean of two distorted curves, not the true one
    plain = [m.model_copy(update={"window_holdup_kg": None, "window_residence_steps": None})
             for m in (measured(0.9), measured(1.1))]
    assert not np.allclose(pool_filling_curves(plain).ratio_at(true_fill), true_ratio, atol=0.01)


def test_curves_pool_against_an_explicit_reference_such_as_a_long_window():
    """Short windows that all read the steady hold-up 10 % low and the chain residence 20 % low (a mill
    still creeping up): on their own mean the curves keep that bias, on the long window's reference the
    true curve comes back, and points at or above the reference hold-up are dropped."""
    true_fill, true_ratio = np.array([0.15, 0.45, 0.75, 0.88]), np.array([0.4, 0.7, 0.9, 0.97])

    def short(kh: float, kr: float) -> FillingTransport:
        return FillingTransport(fill=(true_fill / kh).tolist(), residence_ratio=(true_ratio / kr).tolist(),
                                tag_mass_kg=[1.0] * 4, window_residence_steps=40.0 * kr,
                                window_holdup_kg=3.0 * kh)

    runs = [short(0.9, 0.8), short(0.9, 0.8)]
    own = pool_filling_curves(runs)
    assert not np.allclose(own.ratio_at(true_fill[:3]), true_ratio[:3], atol=0.02)
    c = pool_filling_curves(runs, reference=(3.0, 40.0))
    assert (c.window_holdup_kg, c.window_residence_steps) == (3.0, 40.0)
    assert np.allclose(c.fill, true_fill) and np.allclose(c.residence_ratio, true_ratio)
    lower = pool_filling_curves(runs, reference=(2.6, 40.0))  # 0.88 * 3 / 2.6 >= 1: the top point goes
    assert len(lower.fill) == 3 and max(lower.fill) < 1.0
    one = pool_filling_curves(runs[:1], reference=(3.0, 40.0))  # a single curve is re-referenced too
    assert np.allclose(one.residence_ratio, true_ratio)
    for bad in ((0.0, 40.0), (3.0, float("inf"))):
        with pytest.raises(ValueError, match="reference"):
            pool_filling_curves(runs, reference=bad)


def test_curves_measured_at_other_lags_pool_in_seconds():
    """Runs of one point whose characteristic times differ (30 mm: 0.025 or 0.030 s) count their window
    residence in steps of different lags: the same 1.2 s is 48 or 40 steps. Compared in seconds, every
    curve put on a long window's reference (steps of 0.025 s) is the true curve; counted in steps the
    0.030 s run's ratios would come out 1/6 low."""
    true_fill, true_ratio = np.array([0.15, 0.45, 0.75]), np.array([0.4, 0.7, 0.9])

    def run_at(lag_s: float, kr: float) -> FillingTransport:  # window chain residence kr * 1.2 s
        return FillingTransport(fill=true_fill.tolist(), residence_ratio=(true_ratio / kr).tolist(),
                                tag_mass_kg=[1.0] * 3, window_residence_steps=1.2 * kr / lag_s,
                                window_holdup_kg=3.0, lag_s=lag_s)

    curves = [run_at(0.025, 0.9), run_at(0.030, 1.1), run_at(0.030, 1.0)]
    c = pool_filling_curves(curves, reference=(3.0, 48.0), reference_lag_s=0.025)
    assert np.allclose(c.residence_ratio, true_ratio) and c.lag_s == 0.025
    for one in curves:  # each alone, too
        assert np.allclose(pool_filling_curves([one], reference=(3.0, 48.0), reference_lag_s=0.025).residence_ratio,
                           true_ratio)
    # on their own mean (in seconds, expressed in steps of the curves' mean lag) the three agree as well
    own = pool_filling_curves([run_at(0.025, 1.0), run_at(0.030, 1.0)])
    assert np.allclose(own.residence_ratio, true_ratio)
    assert own.window_residence_steps * own.lag_s == pytest.approx(1.2)
    # a curve without a lag is taken to be on the common one
    bare = run_at(0.025, 1.0).model_copy(update={"lag_s": None})
    assert np.allclose(pool_filling_curves([bare], reference=(3.0, 48.0), reference_lag_s=0.025).residence_ratio,
                       true_ratio)
    with pytest.raises(ValueError, match="reference_lag_s"):
        pool_filling_curves(curves, reference=(3.0, 48.0), reference_lag_s=-1.0)


#: a two-compartment chain (inlet zone, one stage; last column out): its steady state and a faster filling one
P_STEADY = np.array([[0.6, 0.4, 0.0], [0.0, 0.8, 0.2]])
P_FILLING = np.array([[0.2, 0.8, 0.0], [0.0, 0.5, 0.5]])


def _tags(fill: list[float], per_bin: int, hold_kg: float = 2.0, lag_s: float = 0.025) -> FillingTags:
    """SYNTHETIC tags of one run: ``per_bin`` tags of 1 kg per compartment and bin, moved as ``P_FILLING``."""
    k = len(fill)
    return FillingTags(lag_s=lag_s, window_holdup_kg=hold_kg, fill=fill,
                       destination_kg=np.broadcast_to(P_FILLING * per_bin, (k, 2, 3)).tolist(),
                       tag_count=[[per_bin, per_bin]] * k)


def test_tags_of_runs_pool_before_the_chain_and_clear_the_tag_threshold():
    """Each run tagged every compartment 8 times per bin: alone, below the 20-tag threshold, its bins keep
    the steady destinations (ratio 1); three runs' tags summed (24) give the filling chain's ratio."""
    ratio = chain_residence_steps(P_FILLING) / chain_residence_steps(P_STEADY)
    runs = [_tags([0.1, 0.3], 8) for _ in range(3)]
    alone = filling_curve_from_tags(runs[:1], (2.0, P_STEADY))
    assert np.allclose(alone.residence_ratio, 1.0)
    c = filling_curve_from_tags(runs, (2.0, P_STEADY))
    assert np.allclose(c.residence_ratio, ratio) and np.allclose(c.fill, [0.1, 0.3])
    assert np.allclose(c.tag_mass_kg, 3 * 16.0) and c.lag_s == 0.025
    assert c.window_residence_steps == pytest.approx(chain_residence_steps(P_STEADY)) and c.window_holdup_kg == 2.0
    # the averaged per-run curves (today's pooling of curves) stay at 1: the threshold bias survives averaging
    assert np.allclose(pool_filling_curves([filling_curve_from_tags([t], (2.0, P_STEADY)) for t in runs]
                                           ).residence_ratio, 1.0)


def test_tags_go_on_the_reference_hold_up_before_binning():
    """A run whose window read 2.4 kg puts its fine bins at fill * 2.4 / reference: on a 3.0 kg reference
    0.3 -> 0.24 (bin [0.2, 0.4)), 0.9 -> 0.72, and 1.3 (above its own window) -> 1.04, dropped."""
    c = filling_curve_from_tags([_tags([0.3, 0.9, 1.3], 25, hold_kg=2.4)], (3.0, P_STEADY))
    assert np.allclose(c.fill, [0.24, 0.72])
    lower = filling_curve_from_tags([_tags([0.3, 0.9, 1.3], 25, hold_kg=2.4)], (2.4, P_STEADY))
    assert np.allclose(lower.fill, [0.3, 0.9])
    with pytest.raises(ValueError, match="one lag"):
        filling_curve_from_tags([_tags([0.3], 25), _tags([0.3], 25, lag_s=0.030)], (2.0, P_STEADY))
    assert filling_curve_from_tags([_tags([1.2], 25)], (2.0, P_STEADY)) is None  # nothing below the reference
    with pytest.raises(ValueError, match="shape"):
        FillingTags(lag_s=0.025, window_holdup_kg=2.0, fill=[0.1], destination_kg=[[[1.0, 0.0, 0.0]]], tag_count=[[1]])


def test_add_filling_transport_pools_replica_tags_against_the_run_window(tmp_path):
    """``scripts/add_filling_transport.py --pool tags``: the table run's curve is the replicas' tags summed
    against its window (hold-up and destinations); replicas at another lag are refused in one line."""
    import json
    import subprocess
    import sys
    from pathlib import Path

    n = N_ST + 1
    run = _run(_curve([0.3, 0.7], [0.5, 0.9])).model_copy(update={"provenance": {"stats": {"mean_holdup_kg": 2.0}}})
    table = StageParameterTable(runs=[run])
    tpath = tmp_path / "table.json"
    tpath.write_text(table.model_dump_json(), encoding="utf-8")
    p_ref = run.destination_matrix()
    fast = np.zeros((n, n + 1))
    fast[np.arange(n), np.arange(1, n + 1)] = 1.0  # every compartment passes its rock on at once

    def replica(seed: int, lag_s: float) -> dict:
        tags = FillingTags(lag_s=lag_s, window_holdup_kg=2.2, fill=[0.25, 0.5],
                           destination_kg=np.broadcast_to(fast * 9.0, (2, n, n + 1)).tolist(), tag_count=[[9] * n] * 2)
        return {"size_mm": run.design.size_mm, "seed": seed, "characteristic_time_s": lag_s,
                "filling_transport": _curve([0.5], [0.8]).model_dump(), "filling_tags": tags.model_dump()}

    tau = run.characteristic_time_s
    rpath = tmp_path / "replicas.json"
    rpath.write_text(json.dumps({"replicas": [replica(s, tau) for s in (1, 2, 3)]}), encoding="utf-8")
    script = Path(__file__).resolve().parents[2] / "scripts" / "add_filling_transport.py"
    out = tmp_path / "out.json"
    res = subprocess.run([sys.executable, str(script), str(tpath), "--replicas", str(rpath), "--pool", "tags",
                          "--out", str(out)], capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    got = StageParameterTable.from_json(out).runs[0]
    want = filling_curve_from_tags([FillingTags.model_validate(replica(s, tau)["filling_tags"]) for s in (1, 2, 3)],
                                   (2.0, p_ref))
    assert got.filling_transport == want
    assert np.allclose(want.fill, [0.275, 0.55]) and all(r < 0.5 for r in want.residence_ratio)  # 27 tags each
    added = got.provenance["filling_transport_added_by"]
    assert added["pool"] == "tags" and added["replica_seeds"] == [1, 2, 3]
    assert FillingTransport.model_validate(added["own_curve"]) == run.filling_transport  # kept, not pooled
    # a warm run (no curve of its own) with its curve from a cold table: that curve is the one kept
    warm = tmp_path / "warm.json"
    warm.write_text(StageParameterTable(runs=[run.model_copy(update={"filling_transport": None})]).model_dump_json(),
                    encoding="utf-8")
    res = subprocess.run([sys.executable, str(script), str(warm), "--curves-from", str(tpath), "--replicas", str(rpath),
                          "--pool", "tags", "--out", str(out)], capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    got = StageParameterTable.from_json(out).runs[0]
    assert got.filling_transport == want
    own = FillingTransport.model_validate(got.provenance["filling_transport_added_by"]["own_curve"])
    assert own.fill == run.filling_transport.fill and own.residence_ratio == run.filling_transport.residence_ratio
    rpath.write_text(json.dumps({"replicas": [replica(1, tau), replica(2, 1.2 * tau)]}), encoding="utf-8")
    res = subprocess.run([sys.executable, str(script), str(tpath), "--replicas", str(rpath), "--pool", "tags",
                          "--out", str(tmp_path / "bad.json")], capture_output=True, text=True)
    assert res.returncode != 0 and "another lag" in res.stderr and "Traceback" not in res.stderr
    assert not (tmp_path / "bad.json").exists()


def test_window_reference_is_the_windows_hold_up_and_chain_residence():
    run = _run(None)
    assert run.window_reference() is None  # no mean hold-up recorded
    run = run.model_copy(update={"provenance": {"stats": {"mean_holdup_kg": 2.5}}})
    hold, steps = run.window_reference()
    assert hold == 2.5
    # inlet zone: half stays (2 visits), then stage 1 (1 / 0.6), stages 2, 3: 40 % stay, 10 % back
    p = run.destination_matrix()
    assert p.shape == (N_ST + 1, N_ST + 2) and np.allclose(p.sum(axis=1), 1.0)
    q = p[:, :-1]
    assert steps == pytest.approx(np.linalg.inv(np.eye(N_ST + 1) - q)[0].sum())
    assert steps == pytest.approx(chain_residence_steps(p))
    assert run.model_copy(update={"inlet_destinations": None}).window_reference() is None


def test_the_default_provider_takes_its_filling_curves_from_the_shipped_table():
    """The campaign's runs start from a filled mill and carry no filling curves; the default provider
    (the shipped surrogate) takes the shipped table's, so the default transport runs fill-dependent."""
    prov = load_provider("default")
    assert isinstance(prov, WithFillingCurves)
    sizes = np.array([0.5, 6.0, 11.0, 30.0, 45.0])
    speeds = [1500.0] * 4 + [3000.0]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        got = prov.stage_parameters(sizes, speeds, 30.0, 40.0)
        own = prov.provider.stage_parameters(sizes, speeds, 30.0, 40.0)
        table = TableProvider.from_file(default_table_path()).stage_parameters(sizes)
        draws = prov.sample_stage_parameters(sizes, 2, speeds, 30.0, 40.0, seed=3)
    assert np.array_equal(got.filling_fill, table.filling_fill)
    assert np.array_equal(got.filling_residence_ratio, table.filling_residence_ratio)
    assert own.filling_fill is None  # the surrogate alone has none
    assert np.array_equal(got.hit_probability, own.hit_probability) and np.array_equal(got.streams, own.streams)
    assert all(np.array_equal(d.filling_residence_ratio, table.filling_residence_ratio) for d in draws)
    assert "filling curves from the shipped stage table" in got.source
    tr = FillingMatrixTransport().transition(got)
    assert tr.per_class_filling and "no filling transport" not in tr.note
    assert SUBMODELS["transport"][DEFAULT_TRANSPORT] is FillingMatrixTransport


def test_the_surrogate_file_not_its_path_says_where_filling_curves_come_from(tmp_path):
    """A copy of the shipped surrogate saved elsewhere predicts the same dynamics; the field decides."""
    import json

    from msmill.model.providers import default_surrogate_path

    doc = json.loads(default_surrogate_path().read_text(encoding="utf-8"))
    assert doc["filling_curves"] == "table"
    copy = tmp_path / "mine.json"
    copy.write_text(json.dumps(doc), encoding="utf-8")
    assert isinstance(load_provider(copy), WithFillingCurves)
    own = tmp_path / "own.json"
    own.write_text(json.dumps({**doc, "filling_curves": None}), encoding="utf-8")
    assert not isinstance(load_provider(own), WithFillingCurves)
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({**doc, "filling_curves": "tabel"}), encoding="utf-8")
    with pytest.raises(MsmillInputError, match=r"bad\.json\.filling_curves"):
        load_provider(bad)


# ------------------------------------------------------------------ schema
def test_filling_transport_is_optional_and_round_trips():
    run = _run(None)
    assert run.filling_transport is None
    again = RunStatistics.from_json(_run(_curve([0.2, 0.6], [0.5, 0.8])).to_json())
    assert again.filling_transport.residence_ratio == [0.5, 0.8]
    assert again.filling_transport.ratio_at(np.array([1.2]))[0] == 1.0


@pytest.mark.parametrize("bad", [dict(fill=[0.2, 1.0]), dict(fill=[0.6, 0.2]), dict(residence_ratio=[0.5, 0.0]),
                                 dict(tag_mass_kg=[1.0])])
def test_bad_filling_transport_is_refused(bad):
    doc = {"fill": [0.2, 0.6], "residence_ratio": [0.5, 0.8], "tag_mass_kg": [1.0, 1.0], **bad}
    data = _run(None).model_dump(mode="json")
    data["filling_transport"] = doc
    with pytest.raises(MsmillInputError):
        RunStatistics.from_dict(data)


# ------------------------------------------------------------------ the DEM measurement
def test_chain_residence_of_a_compartment_that_keeps_p_is_one_over_one_minus_p():
    assert chain_residence_steps(np.array([[0.75, 0.25]])) == pytest.approx(4.0)
    assert chain_residence_steps(np.array([[0.5, 0.5, 0.0], [0.0, 0.8, 0.2]])) == pytest.approx(2.0 + 5.0)
    assert chain_residence_steps(np.array([[1.0, 0.0]])) == np.inf


def _record(fast_until_s: float, slow: tuple[int, ...], fast: tuple[int, ...], n_rocks: int = 400):
    """SYNTHETIC record: rock fed one per snapshot walks inlet -> stages -> out, ``slow[c]`` snapshots in
    compartment ``c`` (``fast`` for rock fed before ``fast_until_s``)."""
    m = Machine.default()
    edges = m.stage_edges_z_m()
    mid = [edges[-1] + 0.05] + [0.5 * (edges[m.n_stages - s] + edges[m.n_stages - s + 1]) for s in range(1, m.n_stages + 1)]
    dt = 0.005
    rows, removed = [], []
    for p in range(n_rocks):
        t_in = p * dt
        path = fast if t_in < fast_until_s else slow
        k = p
        for c, d in enumerate(path):
            for _ in range(d):
                rows.append((p, k * dt, 0.1, mid[c], 0.004))
                k += 1
        removed.append((p, k * dt - 1e-6, "outlet"))
    snaps = pd.DataFrame(rows, columns=["particle_id", "time_s", "y_m", "z_m", "radius_m"])
    snaps["time_s"] = np.round(snaps["time_s"], 9)
    rem = pd.DataFrame(removed, columns=["particle_id", "time_s", "tag"])
    end = (n_rocks - 1) * dt
    return m, snaps[snaps["time_s"] <= end], rem[rem["time_s"] <= end], (end - 0.3, end)


def test_filling_measurement_finds_faster_rock_in_the_emptier_mill_and_none_when_alike():
    slow = (6, 4, 4, 4, 4, 4)
    fast = (2, 2, 2, 2, 2, 2)
    m, snaps, rem, win = _record(0.4, slow, fast)
    ft = filling_transport(m, snaps, rem, win, lag=1)
    k = int(np.argmax(ft.tag_mass_kg))  # the fast rock's fill: its hold-up 12 of the steady 26 rocks
    assert ft.fill[k] == pytest.approx(12 / 26, abs=0.05)
    assert ft.residence_ratio[k] == pytest.approx(sum(fast) / sum(slow), rel=0.15)
    assert np.allclose(np.delete(ft.residence_ratio, k), 1.0)  # few tags there: the window's destinations
    rock_kg = 2700.0 * 4.0 / 3.0 * np.pi * 0.004**3
    assert ft.window_residence_steps == pytest.approx(sum(slow), rel=0.05)  # the references of the curve
    assert ft.lag_s == pytest.approx(0.005)  # its steps are of one snapshot interval (_record) here
    assert filling_transport(m, snaps, rem, win, lag=2).lag_s == pytest.approx(0.010)
    assert ft.window_holdup_kg == pytest.approx(sum(slow) * rock_kg, rel=0.05)  # one rock fed per snapshot
    t0 = 0.45  # a window that opens while the mill still fills: its tags at fills below 1 stay out
    early = filling_transport(m, snaps, rem, (t0, win[1]), lag=1)
    rock_kg = 2700.0 * 4.0 / 3.0 * np.pi * 0.004**3
    assert sum(early.tag_mass_kg) <= (snaps["time_s"] < t0 - 1e-9).sum() * rock_kg * (1 + 1e-9)
    m, snaps, rem, win = _record(0.0, slow, fast)
    same = filling_transport(m, snaps, rem, win, lag=1)
    assert np.allclose(same.residence_ratio, 1.0, atol=0.02)
