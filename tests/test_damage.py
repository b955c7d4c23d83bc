"""Tests of the Tavares damage functions in msmill.breakage."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from msmill import breakage as br
from msmill.errors import MsmillInputError


def _rhs(d, r, g):
    return (2 * g / (2 * g - 5 * d + 5) * r) ** (2 * g / 5)


@settings(max_examples=300, deadline=None)
@given(r=st.floats(0.0, 0.999999), g=st.floats(0.5, 50.0))
def test_damage_satisfies_its_equation(r, g):
    d = br.damage_increment(r, g)
    assert 0.0 <= d < 1.0
    assert abs(d - _rhs(d, r, g)) < 1e-10


@settings(max_examples=50, deadline=None)
@given(g=st.floats(1.0, 20.0))
def test_damage_monotone_in_ratio_and_zero_at_zero(g):
    r = np.linspace(0.0, 0.995, 200)
    d = br.damage_increment(r, g)
    assert d[0] == 0.0
    assert np.all(np.diff(d) > 0)


def test_damage_small_ratio_limit():
    # D -> (2g r / (2g + 5))**(2g/5) as r -> 0
    g, r = 4.0, 1e-6
    assert br.damage_increment(r, g) == pytest.approx((2 * g * r / (2 * g + 5)) ** (2 * g / 5), rel=1e-6)


def test_damage_vectorised_broadcast():
    d = br.damage_increment(np.array([[0.1], [0.5]]), np.array([3.0, 4.0, 5.4]))
    assert d.shape == (2, 3)
    for i, r in enumerate((0.1, 0.5)):
        for j, g in enumerate((3.0, 4.0, 5.4)):
            assert d[i, j] == pytest.approx(br.damage_increment(r, g), abs=1e-14)
    # larger gamma -> less damage for the same ratio (exponent 2g/5 on a number < 1)
    assert np.all(np.diff(d, axis=1) < 0)


@pytest.mark.parametrize(("r", "g", "field"), [(1.0, 4.0, "energy_ratio"), (-0.1, 4.0, "energy_ratio"),
                                               (0.5, 0.1, "gamma"), (0.5, 100.0, "gamma")])
def test_damage_validation(r, g, field):
    with pytest.raises(MsmillInputError, match=rf"^{field}"):
        br.damage_increment(r, g)


def test_accumulate_damage():
    assert br.accumulate_damage(0.2, 0.5) == pytest.approx(0.6)  # 1 - 0.8 * 0.5
    assert br.accumulate_damage(0.0, 0.0) == 0.0
    with pytest.raises(MsmillInputError, match=r"^d_inc"):
        br.accumulate_damage(0.1, 1.5)


def test_is_broken():
    np.testing.assert_array_equal(br.is_broken([0.1, 0.5, 0.9], 0.5), [False, True, True])
    with pytest.raises(MsmillInputError, match=r"^damage_threshold"):
        br.is_broken(0.1, 0.0)


def test_survivor_energy_ratio():
    # E_m = L_ref/(b L) = 30/(1.5*10) = 2 kWh/t; D = 0.5 -> E_m(1-D) = 1; r = 1/(1+1) = 0.5
    assert br.survivor_energy_ratio(1.0, 10.0, 1.5, 30.0, 0.5) == pytest.approx(0.5)
    assert br.survivor_energy_ratio(0.0, 10.0, 1.5, 30.0) == 0.0
    assert br.mean_fracture_energy_kwh_t(10.0, 1.5, 30.0) == pytest.approx(2.0)


def test_damage_after_impact():
    e, size, b, lref, g = 0.2, 10.0, 1.67, 30.0, 4.0
    res = br.damage_after_impact(e, size, b, lref, g)
    assert res.pb == pytest.approx(br.breakage_probability(e, size, b, lref))
    r = br.survivor_energy_ratio(e, size, b, lref)
    assert res.damage == pytest.approx(br.damage_increment(r, g))
    # a second identical impact: higher P_b and more damage
    res2 = br.damage_after_impact(e, size, b, lref, g, damage=res.damage)
    assert res2.pb > res.pb
    assert res2.damage > res.damage
    # threshold: damaged rocks beyond it break with certainty
    res3 = br.damage_after_impact(e, size, b, lref, g, damage=res.damage, damage_threshold=res.damage)
    assert res3.pb == 1.0


def test_damage_after_impact_vectorised():
    e = np.linspace(0.0, 1.0, 7)[:, None]
    d = np.array([0.0, 0.3, 0.6])
    res = br.damage_after_impact(e, 10.0, 1.67, 30.0, 4.0, damage=d)
    assert res.pb.shape == res.damage.shape == (7, 3)
    assert np.all(res.damage >= d)
    np.testing.assert_allclose(res.damage[0], d)
