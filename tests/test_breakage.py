"""Tests of msmill.breakage: Eq. 11-12, energy units, t_n constants, appearance matrix."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from msmill import breakage as br
from msmill.errors import MsmillInputError
from msmill.psd import SizeGrid

UG2_A, UG2_B = 71.8, 1.67


# ------------------------------------------------------------------ energies


def test_energy_conversions():
    # domain notes §1: 40 m/s -> 800 J/kg = 0.222 kWh/t
    assert br.velocity_to_ecs_j_kg(40.0) == pytest.approx(800.0)
    assert br.j_kg_to_kwh_t(800.0) == pytest.approx(800.0 / 3600.0)
    assert br.velocity_to_ecs_kwh_t(40.0) == pytest.approx(0.2222, abs=1e-4)
    assert br.kwh_t_to_j_kg(1.0) == 3600.0
    assert br.ecs_kwh_t_to_velocity(800.0 / 3600.0) == pytest.approx(40.0)
    np.testing.assert_allclose(br.velocity_to_ecs_j_kg([0.0, 10.0]), [0.0, 50.0])


# -------------------------------------------------------------------- Eq. 11


def test_pb_zero_at_zero_energy_and_tends_to_one():
    assert br.breakage_probability(0.0, 10.0, UG2_B, 30.0) == 0.0
    assert br.breakage_probability(1e3, 10.0, UG2_B, 30.0) == pytest.approx(1.0)


def test_pb_closed_form_and_reduction_at_lref():
    e, size, lref = 0.2, 15.0, 30.0
    assert br.breakage_probability(e, size, UG2_B, lref) == pytest.approx(
        1.0 - math.exp(-UG2_B * e * size / lref)
    )
    # at L = L_ref: the standard 1 - exp(-b E)
    assert br.breakage_probability(e, lref, UG2_B, lref) == pytest.approx(1.0 - math.exp(-UG2_B * e))


def test_pb_monotone_in_energy_size_and_damage():
    e = np.linspace(0.0, 2.0, 50)
    pb = br.breakage_probability(e, 10.0, UG2_B, 30.0)
    assert np.all(np.diff(pb) > 0)
    sizes = np.linspace(1.0, 60.0, 40)
    pb = br.breakage_probability(0.1, sizes, UG2_B, 30.0)
    assert np.all(np.diff(pb) > 0)
    d = np.linspace(0.0, 0.9, 10)
    pb = br.breakage_probability(0.1, 10.0, UG2_B, 30.0, damage=d)
    assert np.all(np.diff(pb) > 0)
    # damage scales fracture energy by (1 - D): P_b(E, D) = P_b(E / (1 - D), 0)
    assert br.breakage_probability(0.1, 10.0, UG2_B, 30.0, damage=0.5) == pytest.approx(
        br.breakage_probability(0.2, 10.0, UG2_B, 30.0)
    )


def test_pb_broadcasts():
    pb = br.breakage_probability(np.array([[0.1], [0.2]]), np.array([5.0, 10.0, 20.0]), UG2_B, 30.0)
    assert pb.shape == (2, 3)


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [({"ecs_kwh_t": -1.0}, "ecs_kwh_t"), ({"size_mm": 0.0}, "size_mm"), ({"b_t_per_kwh": -1.0}, "b_t_per_kwh"),
     ({"l_ref_mm": 0.0}, "l_ref_mm"), ({"damage": 1.0}, "damage"), ({"ecs_kwh_t": float("nan")}, "ecs_kwh_t"),
     ({"ecs_kwh_t": "abc"}, "ecs_kwh_t")],
)
def test_pb_validation(kwargs, field):
    args = {"ecs_kwh_t": 0.1, "size_mm": 10.0, "b_t_per_kwh": 1.0, "l_ref_mm": 30.0, "damage": 0.0} | kwargs
    with pytest.raises(MsmillInputError) as exc:
        br.breakage_probability(**args)
    assert str(exc.value).startswith(field)
    assert "\n" not in str(exc.value)


# -------------------------------------------------------------------- Eq. 12


def test_t10_limits():
    e = np.array([0.0, 0.01, 0.1, 1.0, 10.0, 100.0])
    t10 = br.t10_pct(br.breakage_probability(e, 30.0, UG2_B, 30.0), UG2_A)
    assert t10[0] == 0.0
    assert np.all(np.diff(t10) > 0)
    assert t10[-1] == pytest.approx(UG2_A)
    # Eq. 12 by hand: E = 0.1 kWh/t, L = L_ref = 30 mm -> P_b = 1 - exp(-0.167) = 0.1538,
    # t10 = 71.8 * 0.1538 = 11.04 %
    assert t10[2] == pytest.approx(71.8 * (1 - math.exp(-1.67 * 0.1)), rel=1e-12)
    assert t10[2] == pytest.approx(11.04, abs=0.01)
    assert br.t10_pct(0.25, 60.0) == pytest.approx(15.0)
    with pytest.raises(MsmillInputError, match=r"^pb"):
        br.t10_pct(1.5, UG2_A)
    with pytest.raises(MsmillInputError, match=r"^A"):
        br.t10_pct(0.5, 120.0)


def test_tn_power_law_and_cap():
    assert br.tn_pct(10.0, 2.0, 0.5) == pytest.approx(2.0 * math.sqrt(10.0))
    assert br.tn_pct(90.0, 19.6, 0.425) == 100.0  # 19.6 * 90**0.425 = 110 -> capped
    with pytest.raises(MsmillInputError, match=r"^t10_pct"):
        br.tn_pct(-1.0, 1.0, 1.0)
    with pytest.raises(MsmillInputError, match=r"^k"):
        br.tn_pct(10.0, 0.0, 1.0)


def test_default_tn_constants_match_domain_notes_fit():
    tn = br.default_tn_constants()
    # domain notes §3, table A least-squares fits (log-log): (k, s)
    notes = {2: (19.6, 0.425), 4: (3.75, 0.803), 25: (0.469, 1.027), 50: (0.323, 0.982), 75: (0.273, 0.936)}
    for n, (k, s) in tn.as_dict().items():
        assert k == pytest.approx(notes[n][0], rel=5e-3)
        assert s == pytest.approx(notes[n][1], abs=1e-3)
    assert "table A" in tn.source
    b = br.default_tn_constants("B")
    assert b.as_dict()[75][1] == pytest.approx(1.304, abs=1e-3)
    with pytest.raises(MsmillInputError, match=r"^table"):
        br.default_tn_constants("Z")


def test_tn_constants_validation():
    with pytest.raises(MsmillInputError, match=r"^tn"):
        br.TnConstants.from_mapping({2: (1.0, 1.0)})
    with pytest.raises(MsmillInputError, match=r"^tn"):
        br.TnConstants.from_mapping({n: (-1.0, 1.0) for n in br.TN_SIZES})
    tn = br.TnConstants.from_mapping({f"t{n}": (1.0, 1.0) for n in br.TN_SIZES})
    assert tn.k == (1.0,) * 5


# ---------------------------------------------------------------- appearance


def _check_appearance(B: np.ndarray) -> None:
    n = B.shape[-1]
    np.testing.assert_allclose(B.sum(axis=-2), 1.0, rtol=0, atol=1e-12)
    assert np.all(B >= 0.0)
    i, j = np.indices((n, n))
    assert np.all(B[..., i > j] == 0.0), "mass above the parent class"
    cum = np.cumsum(B, axis=-2)
    assert np.all(np.diff(cum, axis=-2) >= -1e-15)


@settings(max_examples=80, deadline=None)
@given(
    lo=st.floats(0.01, 5.0),
    span=st.floats(2.0, 2000.0),
    ratio=st.floats(1.05, 3.0),
    t10=st.lists(st.floats(0.0, 100.0), min_size=1, max_size=6),
    per_parent=st.booleans(),
)
def test_appearance_property(lo, span, ratio, t10, per_parent):
    grid = SizeGrid.geometric(lo, lo * span, ratio=ratio)
    if grid.n_classes > 200:
        return
    t = np.asarray(t10)[:, None]
    if per_parent:
        rng = np.random.default_rng(len(t10))
        t = rng.uniform(0.0, 100.0, size=(len(t10), grid.n_classes))
    B = br.appearance_matrix(grid, t)
    assert B.shape == (len(t10), grid.n_classes, grid.n_classes)
    _check_appearance(B)


@settings(max_examples=60, deadline=None)
@given(
    lo=st.floats(0.01, 2.0),
    span=st.floats(5.0, 5000.0),
    ratio=st.floats(1.1, 2.5),
    velocities=st.lists(st.floats(0.0, 150.0), min_size=1, max_size=5),
    b=st.floats(0.1, 3.0),
    a=st.floats(20.0, 90.0),
    l_ref=st.floats(5.0, 60.0),
)
def test_appearance_property_from_sizes_and_energies(lo, span, ratio, velocities, b, a, l_ref):
    # t10 from Eq. 11-12 for every (energy, parent size) pair -> B[e, i, j]
    grid = SizeGrid.geometric(lo, lo * span, ratio=ratio)
    ecs = br.velocity_to_ecs_kwh_t(np.asarray(velocities))[:, None]
    t10 = br.t10_pct(br.breakage_probability(ecs, grid.mids_mm[None, :], b, l_ref), a)
    B = br.appearance_matrix(grid, t10)
    assert B.shape == (len(velocities), grid.n_classes, grid.n_classes)
    _check_appearance(B)


@settings(max_examples=40, deadline=None)
@given(edges=st.lists(st.floats(0.01, 500.0), min_size=2, max_size=25, unique=True),
       t10=st.floats(0.0, 100.0))
def test_appearance_property_irregular_grid(edges, t10):
    e = np.sort(np.asarray(edges))
    if np.any(np.diff(e) <= 1e-9 * e[1:]):
        return
    B = br.appearance_matrix(SizeGrid(e), t10)
    assert B.shape == (e.size - 1, e.size - 1)
    _check_appearance(B)


def test_appearance_reads_t_n_at_parent_fractions():
    # a fine grid with edges exactly at parent/n for the top class's mid
    grid = SizeGrid.geometric(0.01, 100.0, ratio=1.05)
    j = grid.n_classes - 1
    x = grid.mids_mm[j]
    t10 = 25.0
    B = br.appearance_matrix(grid, t10)
    cum = np.concatenate(([0.0], np.cumsum(B[:, j]))) * 100.0  # passing at each edge
    tn = br.default_tn_constants().tn_pct(t10)
    for n, expected in zip((2, 4, 10, 25, 50, 75), (tn[0], tn[1], t10, tn[2], tn[3], tn[4]), strict=True):
        got = np.exp(np.interp(np.log(x / n), np.log(grid.edges_mm), np.log(np.maximum(cum, 1e-300))))
        assert got == pytest.approx(expected, rel=0.02), n


def test_appearance_zero_t10_keeps_mass_in_parent():
    grid = SizeGrid.geometric(0.1, 50.0)
    B = br.appearance_matrix(grid, 0.0)
    np.testing.assert_allclose(np.diag(B), 1.0, atol=1e-9)


def test_appearance_more_energy_more_fines():
    grid = SizeGrid.geometric(0.1, 50.0)
    B = br.appearance_matrix(grid, np.array([[5.0], [20.0], [50.0]]))
    j = grid.n_classes - 1
    fines = np.cumsum(B[:, :, j], axis=1)[:, j - 4]
    assert np.all(np.diff(fines) > 0)


def test_appearance_batch_equals_single():
    grid = SizeGrid.geometric(0.1, 50.0)
    t = np.array([[3.0], [40.0]])
    B = br.appearance_matrix(grid, t)
    np.testing.assert_allclose(B[1], br.appearance_matrix(grid, 40.0))


def test_appearance_validation():
    grid = SizeGrid.geometric(0.1, 50.0)
    with pytest.raises(MsmillInputError, match=r"^t10_pct"):
        br.appearance_matrix(grid, 120.0)
    with pytest.raises(MsmillInputError, match=r"^t10_pct"):
        br.appearance_matrix(grid, np.ones(grid.n_classes + 3))
    with pytest.raises(MsmillInputError, match=r"^grid"):
        br.appearance_matrix([1, 2, 3], 10.0)  # type: ignore[arg-type]
    with pytest.raises(MsmillInputError, match=r"^tn"):
        br.appearance_matrix(grid, 10.0, tn=3)  # type: ignore[arg-type]


def test_appearance_speed():
    grid = SizeGrid.geometric(0.1, 100.0)  # 20-21 classes
    t10 = np.linspace(0.0, 71.8, 100)[:, None]
    br.appearance_matrix(grid, t10)
    start = time.perf_counter()
    for _ in range(10):
        br.appearance_matrix(grid, t10)
    per_call = (time.perf_counter() - start) / 10
    assert per_call < 0.05  # measured ~2 ms; generous bound for shared CI machines


def _pchip_column(grid: SizeGrid, j: int, t10: float, tn: br.TnConstants) -> np.ndarray:
    """Column ``j`` of the appearance matrix built independently with scipy's PchipInterpolator.

    Knots ``(x/n, t_n)`` for n = 75, 50, 25, 10, 4, 2, 1 with ``t_n = min(k t10^s, 100)``
    (made non-decreasing with size), PCHIP of ln(passing) against ln(size), a
    power-law tail below x/75 with the secant slope of the (x/75, x/50) segment,
    100 % at and above the parent size, class 0 taking everything finer.
    """
    from scipy.interpolate import PchipInterpolator

    x = grid.mids_mm[j]
    knots_n = [75, 50, 25, 10, 4, 2, 1]
    consts = dict(zip(br.TN_SIZES, zip(tn.k, tn.s, strict=True), strict=True))
    p = [100.0 if n == 1 else t10 if n == 10 else min(consts[n][0] * t10 ** consts[n][1], 100.0)
         for n in knots_n]
    p = np.minimum.accumulate(np.asarray(p)[::-1])[::-1]
    u_k = np.log(x / np.asarray(knots_n, dtype=float))
    curve = PchipInterpolator(u_k, np.log(p))
    slope = (math.log(p[1]) - math.log(p[0])) / (u_k[1] - u_k[0])
    u = np.log(grid.edges_mm)
    lnp = np.where(u < u_k[0], math.log(p[0]) + slope * (u - u_k[0]), curve(np.clip(u, u_k[0], u_k[-1])))
    cum = np.where(u >= math.log(x), 100.0, np.exp(np.minimum(lnp, math.log(100.0))))
    cum[0] = 0.0
    cum[-1] = 100.0
    col = np.diff(cum) / 100.0
    col[0] = cum[1] / 100.0
    return col


@pytest.mark.parametrize("t10", [5.0, 30.0, 60.0])
@pytest.mark.parametrize("table", ["A", "B"])
def test_appearance_columns_equal_an_independent_pchip_curve(t10, table):
    grid = SizeGrid.geometric(0.038, 45.0)
    tn = br.default_tn_constants(table)
    B = br.appearance_matrix(grid, t10, tn)
    for j in (grid.n_classes - 1, grid.n_classes // 2, 3):
        np.testing.assert_allclose(B[:, j], _pchip_column(grid, j, t10, tn), rtol=0, atol=1e-12)


def test_tn_cap_second_check():
    """t_n above 100 % is capped, in both t_n functions and in the appearance curve."""
    tn = br.TnConstants.from_mapping({2: (19.6, 0.425), 4: (3.75, 0.803), 25: (0.469, 1.027),
                                      50: (0.323, 0.982), 75: (0.273, 0.936)})
    # t10 = 60: t2 = 19.6 * 60^0.425 = 111 %, t4 = 3.75 * 60^0.803 = 101 % -> both 100 %
    assert 19.6 * 60**0.425 > 100 and 3.75 * 60**0.803 > 100
    got = tn.tn_pct(60.0)
    np.testing.assert_array_equal(got[:2], [100.0, 100.0])
    assert got[2] == pytest.approx(0.469 * 60**1.027)
    assert br.tn_pct(60.0, 3.75, 0.803) == 100.0
    # the appearance column then has nothing coarser than parent/4 (and sums to one)
    grid = SizeGrid.geometric(0.01, 100.0, ratio=1.05)
    j = grid.n_classes - 1
    B = br.appearance_matrix(grid, 60.0, tn)
    coarse = grid.edges_mm[:-1] >= grid.mids_mm[j] / 4 * 1.0001
    assert B[coarse, j].sum() == pytest.approx(0.0, abs=1e-12)
    assert B[:, j].sum() == pytest.approx(1.0, abs=1e-12)
