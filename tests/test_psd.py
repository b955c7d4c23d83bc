"""Tests of msmill.psd: grids, PSDs, passing tables, percentiles, fits, rebin, K-S."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from msmill.errors import MsmillInputError
from msmill.psd import PSD, SizeGrid, ks_statistic

# ------------------------------------------------------------------ SizeGrid


def test_geometric_grid_sqrt2_series():
    g = SizeGrid.geometric(1.0, 16.0)
    # sqrt(2) series from 1 to 16: 1, 1.414, 2, ..., 16 -> 9 edges, 8 classes
    assert g.n_classes == 8
    np.testing.assert_allclose(g.edges_mm, 2.0 ** (np.arange(9) / 2))
    np.testing.assert_allclose(g.mids_mm, np.sqrt(g.edges_mm[:-1] * g.edges_mm[1:]))


def test_geometric_grid_custom_ratio_reaches_max():
    g = SizeGrid.geometric(0.1, 50.0, ratio=2.0)
    assert g.edges_mm[-1] >= 50.0
    assert g.edges_mm[-2] < 50.0
    np.testing.assert_allclose(g.edges_mm[1:] / g.edges_mm[:-1], 2.0)


def test_class_of():
    g = SizeGrid([1.0, 2.0, 4.0, 8.0])
    np.testing.assert_array_equal(g.class_of([0.1, 1.0, 1.9, 2.0, 7.9, 100.0]), [0, 0, 0, 1, 2, 2])


@pytest.mark.parametrize(
    ("edges", "field"),
    [([1.0], "edges_mm"), ([1.0, 1.0], "edges_mm"), ([2.0, 1.0], "edges_mm"), ([0.0, 1.0], "edges_mm"),
     ([-1.0, 1.0], "edges_mm"), ([1.0, float("nan")], "edges_mm"), (["a", "b"], "edges_mm")],
)
def test_grid_validation(edges, field):
    with pytest.raises(MsmillInputError) as exc:
        SizeGrid(edges)
    msg = str(exc.value)
    assert msg.startswith(field) and "\n" not in msg


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [({"min_mm": 0.0, "max_mm": 1.0}, "min_mm"), ({"min_mm": 2.0, "max_mm": 1.0}, "max_mm"),
     ({"min_mm": 1.0, "max_mm": 2.0, "ratio": 1.0}, "ratio")],
)
def test_geometric_validation(kwargs, field):
    with pytest.raises(MsmillInputError, match=rf"^{field}"):
        SizeGrid.geometric(**kwargs)


# ----------------------------------------------------------------------- PSD


def test_psd_fraction_validation():
    g = SizeGrid([1.0, 2.0, 4.0])
    with pytest.raises(MsmillInputError, match=r"^fractions.*summing to 1"):
        PSD(g, [0.5, 0.4])
    with pytest.raises(MsmillInputError, match=r"^fractions.*>= 0"):
        PSD(g, [1.5, -0.5])
    with pytest.raises(MsmillInputError, match=r"^fractions.*2 mass fractions"):
        PSD(g, [1.0])
    with pytest.raises(MsmillInputError, match=r"^grid"):
        PSD([1, 2], [1.0])  # type: ignore[arg-type]


def test_passing_defined_at_upper_edges():
    g = SizeGrid([1.0, 2.0, 4.0, 8.0])
    p = PSD(g, [0.2, 0.3, 0.5])
    np.testing.assert_allclose(p.sizes_mm, [2.0, 4.0, 8.0])
    np.testing.assert_allclose(p.passing_pct, [20.0, 50.0, 100.0])


def test_passing_table_round_trip():
    sizes = np.array([0.5, 1.0, 2.0, 4.0, 8.0, 16.0])
    passing = np.array([3.0, 10.0, 25.0, 51.0, 80.0, 100.0])
    p = PSD.from_passing(sizes, passing)
    df = p.to_frame()
    np.testing.assert_allclose(df["size_mm"], sizes)
    np.testing.assert_allclose(df["passing_pct"], passing, atol=1e-12)
    # interpolation reproduces the table at its own sizes
    np.testing.assert_allclose(p.passing_at(sizes), passing, atol=1e-12)


def test_csv_round_trip(tmp_path):
    sizes = [0.3, 0.6, 1.18, 2.36, 4.75]
    passing = [5.0, 12.0, 30.0, 70.0, 100.0]
    path = tmp_path / "feed.csv"
    pd.DataFrame({"size_mm": sizes, "passing_pct": passing}).to_csv(path, index=False)
    p = PSD.read_csv(path)
    out = tmp_path / "out.csv"
    p.to_csv(out)
    back = pd.read_csv(out)
    np.testing.assert_allclose(back["passing_pct"], passing)
    np.testing.assert_allclose(PSD.read_csv(out).fractions, p.fractions)


def test_from_passing_oversize_adds_top_class():
    p = PSD.from_passing([1.0, 2.0], [40.0, 90.0])
    assert p.grid.n_classes == 3
    np.testing.assert_allclose(p.fractions, [0.4, 0.5, 0.1])
    np.testing.assert_allclose(p.grid.edges_mm, [0.5, 1.0, 2.0, 4.0])


def test_from_passing_onto_grid_conserves_mass_and_lumps_oversize():
    g = SizeGrid([1.0, 2.0, 4.0])
    p = PSD.from_passing([1.0, 2.0, 4.0, 8.0], [10.0, 30.0, 60.0, 100.0], grid=g)
    # class 0 (<2 mm) = 30 %, class 1 ([2,4)) = 30 %, top class lumps the 40 % >= 4 mm
    np.testing.assert_allclose(p.fractions, [0.3, 0.7])


@pytest.mark.parametrize(
    ("sizes", "passing", "field"),
    [([1.0, 2.0], [10.0, 5.0], "passing_pct"), ([1.0, 2.0], [10.0, 101.0], "passing_pct"),
     ([1.0, 2.0], [-1.0, 50.0], "passing_pct"), ([2.0, 1.0], [10.0, 50.0], "size_mm"),
     ([0.0, 1.0], [10.0, 50.0], "size_mm"), ([1.0], [100.0], "size_mm"),
     ([1.0, 2.0], [10.0], "passing_pct")],
)
def test_from_passing_validation(sizes, passing, field):
    with pytest.raises(MsmillInputError) as exc:
        PSD.from_passing(sizes, passing)
    assert str(exc.value).startswith(field)
    assert "\n" not in str(exc.value)


def test_frame_and_csv_errors(tmp_path):
    with pytest.raises(MsmillInputError, match=r"^columns"):
        PSD.from_frame(pd.DataFrame({"size": [1, 2], "passing_pct": [1, 100]}))
    with pytest.raises(MsmillInputError, match=r"^passing_pct"):
        PSD.from_frame(pd.DataFrame({"size_mm": [1, 2], "passing_pct": ["x", 100]}))
    with pytest.raises(MsmillInputError, match=r"^path"):
        PSD.read_csv(tmp_path / "missing.csv")
    empty = tmp_path / "empty.csv"
    empty.write_text("")
    with pytest.raises(MsmillInputError, match=r"^path"):
        PSD.read_csv(empty)


def test_percentiles_hand_cases():
    # passing 20 % at 1 mm, 60 % at 2 mm, 100 % at 4 mm.
    p = PSD.from_passing([1.0, 2.0, 4.0], [20.0, 60.0, 100.0])
    # P50: between 1 mm (20 %) and 2 mm (60 %): t = (50-20)/40 = 0.75 -> 2**0.75 mm
    assert p.p50_mm == pytest.approx(2.0**0.75)
    # P80: between 2 mm (60 %) and 4 mm (100 %): t = 0.5 -> 2 * 2**0.5 mm
    assert p.p80_mm == pytest.approx(2.0 * math.sqrt(2.0))
    # exact knots
    np.testing.assert_allclose(p.percentile([20.0, 60.0, 100.0]), [1.0, 2.0, 4.0])
    # below the first sieve: knot (0.5 mm, 0 %) -> P10 = 0.5 * 2**0.5
    assert p.percentile(10.0) == pytest.approx(0.5 * math.sqrt(2.0))
    with pytest.raises(MsmillInputError, match=r"^pct"):
        p.percentile(0.0)
    with pytest.raises(MsmillInputError, match=r"^pct"):
        p.percentile(120.0)


def test_percentile_flat_segment_takes_smallest_size():
    p = PSD(SizeGrid([1.0, 2.0, 4.0, 8.0]), [0.5, 0.0, 0.5])
    assert p.percentile(50.0) == pytest.approx(2.0)


def test_passing_at_interpolates_in_log_size():
    p = PSD.from_passing([1.0, 4.0], [10.0, 100.0])
    assert p.passing_at(2.0) == pytest.approx(55.0)  # midway in log size
    assert p.passing_at(1000.0) == 100.0
    assert p.passing_at(1e-6) == 0.0
    with pytest.raises(MsmillInputError, match=r"^size_mm"):
        p.passing_at(-1.0)


def test_rosin_rammler_fit_recovers_parameters():
    sizes = SizeGrid.geometric(0.1, 50.0).edges_mm[1:]
    x63, n = 6.0, 1.3
    passing = 100.0 * (1.0 - np.exp(-((sizes / x63) ** n)))
    passing[-1] = 100.0
    fit = PSD.from_passing(sizes, passing).fit_rosin_rammler()
    assert fit.params["x63_mm"] == pytest.approx(x63, rel=1e-4)
    assert fit.params["n"] == pytest.approx(n, rel=1e-4)
    assert fit.r_squared > 0.99999


def test_ggs_fit_recovers_parameters():
    sizes = SizeGrid.geometric(0.1, 20.0).edges_mm[1:]
    k, m = 20.0, 0.7
    passing = np.minimum(100.0 * (sizes / k) ** m, 100.0)
    fit = PSD.from_passing(sizes, passing).fit_gates_gaudin_schuhmann()
    assert fit.params["m"] == pytest.approx(m, rel=1e-4)
    assert fit.params["k_mm"] == pytest.approx(k, rel=1e-3)
    assert fit.r_squared > 0.9999


def test_fit_needs_spread_psd():
    p = PSD(SizeGrid([1.0, 2.0, 4.0]), [0.0, 1.0])
    with pytest.raises(MsmillInputError, match=r"^psd"):
        p.fit_rosin_rammler()


@settings(max_examples=60, deadline=None)
@given(
    st.lists(st.floats(0.0, 1.0), min_size=2, max_size=30),
    st.floats(0.01, 1.0),
    st.floats(5.0, 200.0),
    st.floats(1.1, 3.0),
)
def test_rebin_conserves_mass(weights, lo, hi, ratio):
    w = np.asarray(weights)
    if w.sum() == 0:
        w = w + 1.0
    g = SizeGrid.geometric(0.05, 100.0, ratio=math.sqrt(2))
    g = SizeGrid(g.edges_mm[: w.size + 1]) if w.size < g.n_classes else g
    w = w[: g.n_classes]
    if w.sum() == 0:
        w = np.ones_like(w)
    p = PSD(g, w / w.sum())
    g2 = SizeGrid.geometric(lo, hi, ratio=ratio)
    q = p.rebin(g2)
    assert q.fractions.sum() == pytest.approx(1.0, abs=1e-12)
    assert np.all(q.fractions >= 0)
    # cumulative passing is preserved at sizes both grids share (inside both ranges)
    s = g2.edges_mm[1:-1]
    s = s[(s > g.edges_mm[0]) & (s < g.edges_mm[-1])]
    if s.size:
        np.testing.assert_allclose(q.passing_at(s), p.passing_at(s), atol=1e-9)


def test_rebin_by_hand():
    """Cumulative passing read at the new upper edges (log interpolation), by hand.

    Feed on edges 1, 2, 4, 8 mm: 20 %, 30 %, 50 %. Passing 0, 20, 50, 100 % at the edges.
    """
    p = PSD(SizeGrid([1.0, 2.0, 4.0, 8.0]), [0.2, 0.3, 0.5])
    np.testing.assert_allclose(p.rebin(SizeGrid([1.0, 4.0, 8.0])).fractions, [0.5, 0.5], atol=1e-12)
    np.testing.assert_allclose(p.rebin(SizeGrid([1.0, 2.0, 8.0])).fractions, [0.2, 0.8], atol=1e-12)
    # sqrt(2) mm is half-way between 1 and 2 mm in log size: 10 % passing
    fine = SizeGrid([1.0, math.sqrt(2.0), 2.0, 4.0, 8.0])
    np.testing.assert_allclose(p.rebin(fine).fractions, [0.1, 0.1, 0.3, 0.5], atol=1e-12)
    # a wider grid: class 0 takes everything below 2 mm, the top class is empty
    wide = SizeGrid([0.5, 2.0, 8.0, 16.0])
    np.testing.assert_allclose(p.rebin(wide).fractions, [0.2, 0.8, 0.0], atol=1e-12)
    # a narrower one: 4 mm and coarser lumped into the top class
    np.testing.assert_allclose(p.rebin(SizeGrid([1.5, 2.0, 4.0])).fractions, [0.2, 0.8], atol=1e-12)


def test_rebin_same_grid_is_identity():
    g = SizeGrid([1.0, 2.0, 4.0])
    p = PSD(g, [0.3, 0.7])
    assert p.rebin(g) is p


def test_mix():
    g = SizeGrid([1.0, 2.0, 4.0])
    m = PSD.mix([PSD(g, [1.0, 0.0]), PSD(g, [0.0, 1.0])], [1.0, 3.0])
    np.testing.assert_allclose(m.fractions, [0.25, 0.75])
    with pytest.raises(MsmillInputError, match=r"^weights"):
        PSD.mix([PSD(g, [1.0, 0.0])], [-1.0])


# ------------------------------------------------------------------------ K-S


def test_ks_hand_case():
    # a: 20 % at 1 mm, 60 % at 2 mm, 100 % at 4 mm; b: 10 % at 1 mm, 100 % at 4 mm.
    # Union of sieves {1, 2, 4}. b at 2 mm is midway in log size: (10 + 100)/2 = 55.
    # |diff| = |20-10| = 10, |60-55| = 5, |100-100| = 0 -> max 10 % -> 0.10.
    a = PSD.from_passing([1.0, 2.0, 4.0], [20.0, 60.0, 100.0])
    b = PSD.from_passing([1.0, 4.0], [10.0, 100.0])
    assert ks_statistic(a, b) == pytest.approx(0.10)
    assert ks_statistic(b, a) == pytest.approx(0.10)
    assert ks_statistic(a, a) == 0.0


def test_ks_hand_case_disjoint_sieves():
    # a: 50 % at 1 mm, 100 % at 2 mm; b: 0 % at 2 mm, 100 % at 4 mm.
    # Union {1, 2, 4}: a = 50, 100, 100; b at 1 mm: below b's first sieve, b's
    # lower knot is 1 mm (2*2/4) with 0 % -> 0; b = 0, 0, 100 -> max |diff| = 100 % -> 1.0
    a = PSD.from_passing([1.0, 2.0], [50.0, 100.0])
    b = PSD.from_passing([2.0, 4.0], [0.0, 100.0])
    assert ks_statistic(a, b) == pytest.approx(1.0)


def test_ks_validation():
    a = PSD.from_passing([1.0, 2.0], [50.0, 100.0])
    with pytest.raises(MsmillInputError, match=r"^b"):
        ks_statistic(a, [1, 2])  # type: ignore[arg-type]
