"""Closed circuits (issue 42): analytic circulating load, mass balance, Wegstein vs direct substitution,
non-convergence, circuit-file checks, the Whiten curve and the mill unit's transfer matrix."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from msmill.errors import MsmillInputError, OutOfDomainWarning
from msmill.model.circuit import (
    BreakageMatrixMill,
    Circuit,
    CircuitFile,
    CircuitNotConverged,
    FreshFeed,
    MillUnit,
    Product,
    Screen,
    Splitter,
    Stream,
    whiten_fine_partition,
)
from msmill.psd import PSD, SizeGrid

GRID2 = SizeGrid([1.0, 2.0, 4.0])  # class 0 (fine, < 2 mm incl. the pan) and class 1 (coarse, 2-4 mm)


def closed(grid, B, fresh_fractions, screen, fresh_tph=10.0, splitter_to_mill=None):
    """fresh -> mill (breakage matrix B) -> screen; oversize -> mill (or a splitter: part to mill, rest out)."""
    units = [FreshFeed("fresh", fresh_tph, PSD(grid, fresh_fractions)), BreakageMatrixMill("mill", B), screen,
             Product("product")]
    streams = [Stream("f", "fresh", "out", "mill"), Stream("mp", "mill", "product", "screen"),
               Stream("u", "screen", "undersize", "product")]
    if splitter_to_mill is None:
        streams.append(Stream("o", "screen", "oversize", "mill", recycle=True))
    else:
        units += [Splitter("split", {"back": splitter_to_mill, "out": 1.0 - splitter_to_mill}), Product("bleed")]
        streams += [Stream("o", "screen", "oversize", "split"), Stream("r", "split", "back", "mill", recycle=True),
                    Stream("b", "split", "out", "bleed")]
    return Circuit(units, streams, grid=grid)


@pytest.mark.parametrize("method", ["wegstein", "direct"])
@pytest.mark.parametrize("k,bypass", [(0.8, 0.0), (0.5, 0.2), (0.9, 0.05)])
def test_analytic_circulating_load(method, k, bypass):
    """Two classes; the mill leaves k of the coarse class coarse; an ideal screen at the class edge sends
    the coarse class and a bypass b of the fines back: circulating load k/(1-k) + b/(1-b)."""
    B = np.array([[1.0, 1.0 - k], [0.0, k]])
    scr = Screen("screen", d50c_mm=2.0, alpha=math.inf, bypass=bypass)
    res = closed(GRID2, B, [0.0, 1.0], scr).solve(method)
    expected = 100.0 * (k / (1 - k) + bypass / (1 - bypass))
    assert res.circulating_load_pct == pytest.approx(expected, rel=1e-9)
    assert res.product_tph == pytest.approx(10.0, rel=1e-9)
    assert res.residual <= 1e-10
    assert res.mass_balance_error <= 1e-10


def test_analytic_circulating_load_linear_solve():
    """Four classes, a general breakage matrix and a bypass: recycle = S B (I - S B)^-1 F in closed form."""
    grid = SizeGrid([0.5, 1.0, 2.0, 4.0, 8.0])
    B = np.array([[1.0, 0.3, 0.1, 0.05], [0.0, 0.7, 0.3, 0.15], [0.0, 0.0, 0.6, 0.3], [0.0, 0.0, 0.0, 0.5]])
    F = 12.0 * np.array([0.05, 0.1, 0.25, 0.6])
    b = 0.1
    scr = Screen("screen", d50c_mm=2.0, alpha=math.inf, bypass=b)  # mids 0.71, 1.41 pass; 2.83, 5.66 do not
    S = np.diag([b, b, 1.0, 1.0])
    m = np.linalg.solve(np.eye(4) - S @ B, F)
    res = closed(grid, B, F / F.sum(), scr, fresh_tph=12.0).solve()
    np.testing.assert_allclose(res.flows_tph["o"], S @ B @ m, rtol=1e-9, atol=1e-12)
    assert res.circulating_load_pct == pytest.approx(100 * (S @ B @ m).sum() / 12.0, rel=1e-9)
    np.testing.assert_allclose(res.product_tph_by_class, (np.eye(4) - S) @ B @ m, rtol=1e-9, atol=1e-12)


def _random_matrix(rng, n):
    B = np.triu(rng.uniform(0.0, 1.0, (n, n)))  # B[i, j]: from class j to a finer (or the same) class i
    np.fill_diagonal(B, 0.0)
    diag = rng.uniform(0.0, 0.9, n)
    diag[0] = 1.0  # the finest class can only stay
    col = B.sum(axis=0)
    B = np.where(col > 0, B * (1.0 - diag) / np.where(col > 0, col, 1.0), 0.0)
    B[np.arange(n), np.arange(n)] = diag
    B[0, 0] = 1.0
    return B


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**32 - 1), d50c=st.floats(0.3, 6.0), alpha=st.floats(0.5, 20.0),
       beta=st.floats(0.0, 1.0), bypass=st.floats(0.0, 0.5), split=st.floats(0.0, 0.95),
       method=st.sampled_from(["wegstein", "direct"]))
def test_mass_balance_on_every_stream(seed, d50c, alpha, beta, bypass, split, method):
    """Every unit conserves mass (size by size for screens and splitters), no stream is negative and the
    products carry the fresh feed; the torn stream closes to the solver's tolerance (1e-10 of the feed)."""
    rng = np.random.default_rng(seed)
    grid = SizeGrid.geometric(0.1, 8.0)
    n = grid.n_classes
    try:
        scr = Screen("screen", d50c_mm=d50c, alpha=alpha, beta=beta, bypass=bypass)
    except MsmillInputError:
        return  # a fish-hook that sends more than all of a size to the undersize is refused
    fresh = rng.dirichlet(np.ones(n))
    c = closed(grid, _random_matrix(rng, n), fresh, scr, fresh_tph=25.0, splitter_to_mill=split)
    res = c.solve(method, max_iterations=5000)
    f = res.flows_tph
    for q in f.values():
        assert np.all(q >= -1e-12)
    np.testing.assert_allclose(f["f"], 25.0 * fresh, rtol=1e-12)
    tol = 25.0 * 1e-10
    np.testing.assert_allclose(f["mp"], f["o"] + f["u"], rtol=0, atol=tol)          # screen, per class
    np.testing.assert_allclose(f["o"], f["r"] + f["b"], rtol=0, atol=tol)           # splitter, per class
    np.testing.assert_allclose(f["r"], split * f["o"], rtol=0, atol=tol)
    np.testing.assert_allclose(f["u"], scr.fine_partition * f["mp"], rtol=0, atol=tol)
    assert f["mp"].sum() == pytest.approx((f["f"] + f["r"]).sum(), rel=1e-9)               # mill (in the loop)
    assert (f["u"] + f["b"]).sum() == pytest.approx(25.0, rel=1e-9)                         # circuit
    assert res.mass_balance_error <= 1e-9


def test_wegstein_agrees_with_direct_substitution_and_is_faster():
    grid = SizeGrid.geometric(0.1, 8.0)
    rng = np.random.default_rng(3)
    n = grid.n_classes
    B = _random_matrix(rng, n)
    B[:, 1:] = 0.0
    B[np.arange(1, n), np.arange(1, n)] = 0.9  # slow breakage: a high circulating load
    B[np.arange(0, n - 1), np.arange(1, n)] = 0.1
    fresh = np.zeros(n)
    fresh[-1] = 1.0
    scr = Screen("screen", d50c_mm=1.0, alpha=3.0, beta=0.3, bypass=0.1)
    c = closed(grid, B, fresh, scr)
    w = c.solve("wegstein")
    d = c.solve("direct", max_iterations=20000)
    assert w.circulating_load_pct > 500
    for s in w.flows_tph:
        np.testing.assert_allclose(w.flows_tph[s], d.flows_tph[s], rtol=1e-8, atol=1e-10)
    assert w.iterations < d.iterations / 3


def test_non_convergence_is_one_line_with_the_last_residual():
    B = np.array([[1.0, 0.1], [0.0, 0.9]])
    c = closed(GRID2, B, [0.0, 1.0], Screen("screen", d50c_mm=2.0, alpha=math.inf))
    with pytest.raises(CircuitNotConverged) as exc:
        c.solve("direct", max_iterations=5)
    msg = str(exc.value)
    assert "\n" not in msg
    assert "did not converge in 5 iterations" in msg
    # direct substitution from empty: after 5 passes the recycle still grows by 9 x 0.9^4 t/h
    last = float(msg.split("relative mass-balance error ")[1].split(" ")[0])
    assert last == pytest.approx(0.9 ** 5, rel=1e-2)


def test_whiten_curve():
    x = np.array([0.0, 1.0, 50.0])
    for beta in (0.0, 0.5):
        e = whiten_fine_partition(x, alpha=3.0, beta=beta, bypass=0.2)
        np.testing.assert_allclose(e, [0.8, 0.4, 0.0], atol=1e-12)
    # the fish-hook: with beta the oversize partition dips below the bypass at fine sizes
    fine = np.linspace(0.05, 0.5, 10)
    assert np.all(1 - whiten_fine_partition(fine, 3.0, 0.5, 0.2) < 0.2)
    assert np.all(np.abs(1 - whiten_fine_partition(fine, 3.0, 0.0, 0.2) - 0.2) < 0.2 * 0.9 + 1e-9)
    # a fish-hook too small to show in floating point is no fish-hook (beta* = 1), not an error
    np.testing.assert_allclose(whiten_fine_partition(x, 0.6875, 2.6e-61, 0.0), whiten_fine_partition(x, 0.6875, 0.0, 0.0))
    # sharpness: a larger alpha classifies more sharply around d50c
    assert whiten_fine_partition(0.8, 10.0, 0.0, 0.0) > whiten_fine_partition(0.8, 2.0, 0.0, 0.0)
    with pytest.raises(MsmillInputError, match=r"s\.beta"):
        Screen("s", d50c_mm=2.0, alpha=3.0, beta=2.0, bypass=0.0)  # the hook would send > 100 % to fines


BASE = {
    "units": [
        {"name": "fresh", "type": "feed", "rate_tph": 10.0, "size_mm": [2.0, 4.0], "passing_pct": [0.0, 100.0]},
        {"name": "mill", "type": "breakage_matrix", "matrix": None},
        {"name": "screen", "type": "screen", "d50c_mm": 2.0, "alpha": 5.0},
        {"name": "out", "type": "product"},
    ],
    "streams": [
        {"name": "a", "from": "fresh", "to": "mill"},
        {"name": "b", "from": "mill", "to": "screen"},
        {"name": "c", "from": "screen.oversize", "to": "mill"},
        {"name": "d", "from": "screen.undersize", "to": "out"},
    ],
    "grid": {"min_mm": 1.0, "ratio": 2.0},
}


def _file(**changes):
    import copy

    d = copy.deepcopy(BASE)
    d["units"][1]["matrix"] = [[1.0, 0.4], [0.0, 0.6]]
    for k, v in changes.items():
        d[k] = v
    return d


def test_circuit_file_solves():
    res = CircuitFile.from_mapping(_file(), name="c.toml").solve()
    assert res.product_tph == pytest.approx(10.0, rel=1e-9)


@pytest.mark.parametrize("edit,field,text", [
    (lambda d: d["units"].append({"name": "mill", "type": "product"}), "c.toml.units[4].name", "no other unit"),
    (lambda d: d["streams"].pop(3), "c.toml.units.screen", "goes nowhere"),
    (lambda d: d["streams"][3].update(to="nowhere"), "c.toml.streams[3].to", "a unit of this circuit"),
    (lambda d: d["streams"][2].update({"from": "screen.coarse"}), "c.toml.streams[2].from", "screen.oversize"),
    (lambda d: d["units"][2].update(d50c_mm=-1.0), "c.toml.units[2].d50c_mm", "> 0"),
    (lambda d: d["units"][1].update(type="mil"), "c.toml.units[1].type", "mill"),
    (lambda d: d["streams"].append({"name": "a", "from": "fresh", "to": "out"}), "c.toml.streams[4].name",
     "no other stream"),
])
def test_circuit_file_errors_are_one_line(edit, field, text):
    d = _file()
    edit(d)
    with pytest.raises(MsmillInputError) as exc:
        CircuitFile.from_mapping(d, name="c.toml")
    assert exc.value.field == field
    assert text in str(exc.value) and "\n" not in str(exc.value)


def test_a_loop_without_a_mill_is_refused():
    d = _file()
    d["units"].append({"name": "split", "type": "splitter", "fractions": {"back": 0.5, "on": 0.5}})
    d["streams"][3] = {"name": "d", "from": "screen.undersize", "to": "split"}
    d["streams"] += [{"name": "e", "from": "split.back", "to": "screen"}, {"name": "g", "from": "split.on",
                                                                          "to": "out"}]
    d["streams"][1] = {"name": "b", "from": "mill", "to": "out"}
    d["streams"][2] = {"name": "c", "from": "screen.oversize", "to": "out"}
    d["streams"][0] = {"name": "a", "from": "fresh", "to": "screen"}
    d["units"][1] = {"name": "mill", "type": "breakage_matrix", "matrix": [[1.0, 0.4], [0.0, 0.6]]}
    # fresh -> screen; undersize -> split; split.back -> screen: a loop of screen and splitter only
    d["streams"][1] = {"name": "b", "from": "mill", "to": "out"}
    d["units"].append({"name": "fresh2", "type": "feed", "rate_tph": 1.0, "size_mm": [2.0, 4.0],
                       "passing_pct": [0.0, 100.0]})
    d["streams"].append({"name": "m", "from": "fresh2", "to": "mill"})
    with pytest.raises(MsmillInputError, match="recycle loops that pass a mill") as exc:
        CircuitFile.from_mapping(d, name="c.toml")
    assert "screen" in str(exc.value) and "split" in str(exc.value)


@pytest.fixture(scope="module")
def table_mill():
    from msmill.model import Mill

    grid = SizeGrid.geometric(0.038, 45.0)
    mill = Mill("UG2", "table", damage_classes=3, quadrature_nodes=4, band_samples=0, envelope=None)
    unit = MillUnit("mill", mill, {"speed_rpm": 1500.0, "gate_deg": 40.0})
    unit.bind(grid)
    return unit, grid


def table_circuit(unit, grid, bypass=0.0):
    """20 t/h fresh -> the table mill -> a screen at 8 mm; oversize back to the mill, undersize out."""
    feed = PSD.from_passing([2, 4.75, 9.5, 19, 31.5, 45], [2, 6, 18, 58, 90, 100], grid=grid)
    return Circuit([FreshFeed("fresh", 20.0, feed), unit, Screen("screen", d50c_mm=8.0, alpha=4.0, bypass=bypass),
                    Product("p")],
                   [Stream("f", "fresh", "out", "mill"), Stream("m", "mill", "product", "screen"),
                    Stream("o", "screen", "oversize", "mill"), Stream("u", "screen", "undersize", "p")], grid=grid)


def test_mill_unit_transfer_matrix_is_the_mills_steady_state(table_mill):
    """T @ feed equals Mill.run's steady product at that feed, and every column of T sums to 1."""
    from msmill.machine import OperatingPoint

    unit, grid = table_mill
    feed = PSD.from_passing([2, 4.75, 9.5, 19, 31.5, 45], [2, 6, 18, 58, 90, 100], grid=grid)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", OutOfDomainWarning)
        T = unit.transfer_matrix(30.0)
        res = unit.mill.run(feed, OperatingPoint(feed_tph=30.0, speed_rpm=1500.0, gate_deg=40.0), timeseries=False)
    np.testing.assert_allclose(T.sum(axis=0), 1.0, atol=1e-9)
    assert np.all(np.triu(T.T, 1) <= 1e-12)  # nothing coarser than its parent
    prod = T @ (30.0 * feed.fractions)
    np.testing.assert_allclose(prod / prod.sum(), res.product_psd.fractions, rtol=1e-6, atol=1e-10)


def test_mill_unit_in_a_circuit_finishes_at_its_own_feed_rate(table_mill):
    unit, grid = table_mill
    c = table_circuit(unit, grid, bypass=0.05)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", OutOfDomainWarning)
        res = c.solve()
    rate = res.unit_feeds_tph["mill"].sum()
    assert abs(rate - unit.operator_rate_tph) <= 1e-6 * rate
    assert res.product_tph == pytest.approx(20.0, rel=1e-9)
    assert res.circulating_load_pct > 0
    assert res.product_p80_mm < 8.0


def test_mill_feed_rate_that_does_not_settle_is_one_line(table_mill):
    unit, grid = table_mill
    c = table_circuit(unit, grid)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", OutOfDomainWarning)
        with pytest.raises(CircuitNotConverged) as exc:
            c.solve(max_rebuilds=0)  # operators built at the fresh rate only
    msg = str(exc.value)
    assert "\n" not in msg and "did not settle in 0 rebuilds" in msg
    fed, built = (float(msg.split(k)[1].split(" ")[0]) for k in ("fed ", "built at "))
    assert built == pytest.approx(20.0) and fed > 25.0  # the recycle came on top of the fresh feed


@pytest.fixture(scope="module")
def ug2_circuit():
    """The shipped example (default surrogate), solved, and its 64-sample band."""
    from pathlib import Path

    path = Path(__file__).resolve().parents[2] / "examples" / "ug2_closed_circuit.toml"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cf = CircuitFile.from_toml(path)
        res = cf.solve()
        band = cf.circuit.band(res, 64)
    return cf, res, band


def test_band_holds_the_prediction_and_every_sample_balances(ug2_circuit):
    _, res, band = ug2_circuit
    lo, hi = band.circulating_load_band_pct
    assert lo < res.circulating_load_pct < hi
    lo, hi = band.product_p80_band_mm
    assert lo < res.product_p80_mm < hi
    assert band.circulating_load_pct.shape == (64,) and np.ptp(band.circulating_load_pct) > 1.0
    mill_feed = band.mill_feed_tph["mill"]  # fresh + recycle, per sample
    np.testing.assert_allclose(mill_feed, 20.0 * (1 + band.circulating_load_pct / 100.0), rtol=1e-9)


def test_band_sample_agrees_with_that_sample_solved_alone(ug2_circuit):
    """Sample k of the band (transfer matrices interpolated in feed rate) against a circuit whose mill takes
    posterior sample k wherever it is asked (PosteriorSample), solved by rebuilding at its own rates."""
    import copy

    from msmill.model.providers import posterior_samples

    cf, res, band = ug2_circuit
    c = cf.circuit
    mu = c.units["mill"]
    mill = copy.copy(mu.mill)
    mill.provider = posterior_samples(mu.mill.provider, 64, 0)[0]
    mill._cache, mill.damage_classes, mill.quadrature_nodes = {}, mill.band_damage_classes, mill.band_quadrature_nodes
    alone = Circuit([MillUnit("mill", mill, mu.operating) if n == "mill" else u for n, u in c.units.items()],
                    list(c.streams.values()), grid=c.grid)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        r = alone.solve()
    assert abs(band.circulating_load_pct[0] - r.circulating_load_pct) < 0.05 * r.circulating_load_pct
    assert band.product_p80_mm[0] == pytest.approx(r.product_p80_mm, rel=0.02)
    # the sample sits far from the prediction: the agreement is not the band's width
    assert abs(r.circulating_load_pct - res.circulating_load_pct) > 0.1 * res.circulating_load_pct


def test_band_needs_posterior_samples(table_mill):
    unit, grid = table_mill
    c = table_circuit(unit, grid)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", OutOfDomainWarning)
        res = c.solve()
    with pytest.raises(MsmillInputError, match="posterior samples"):
        c.band(res, 8)
    B = np.array([[1.0, 0.2], [0.0, 0.8]])
    analytic = closed(GRID2, B, [0.0, 1.0], Screen("screen", d50c_mm=2.0, alpha=math.inf))
    with pytest.raises(MsmillInputError, match="without a mill unit"):
        analytic.band(analytic.solve(), 8)


def test_capacity_warning_names_the_circulating_load(table_mill, monkeypatch):
    """The mill's feed (fresh plus recycle) against a capacity between the fresh feed and that feed."""
    from msmill.surrogate.capacity import AboveCapacityWarning, CapacityCheck

    unit, grid = table_mill
    c = table_circuit(unit, grid)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", OutOfDomainWarning)
        res = c.solve()
    monkeypatch.setattr(unit.mill, "check_capacity", lambda f, op: CapacityCheck(
        feed_tph=op.feed_tph, capacity_tph=25.0, probability_steady=0.2, size_mm=f.p80_mm, speed_rpm=1500.0,
        gate_deg=40.0))
    with pytest.warns(AboveCapacityWarning) as rec:
        summary = res.mill_summaries()
    msg = " ".join(str(w.message) for w in rec if issubclass(w.category, AboveCapacityWarning))
    rate = res.unit_feeds_tph["mill"].sum()
    assert f"fresh feed plus recycle is {rate:.4g} t/h" in msg
    assert f"circulating load {res.circulating_load_pct:.3g} %" in msg
    assert summary["mill"]["capacity"].above
