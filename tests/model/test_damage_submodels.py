"""Damage sub-models over three or more impacts against a hand calculation.

The hand calculation is written out here, independently of ``msmill.breakage``:
mean fracture energy ``E_m = L_ref (1 - D) / (b L)`` (kWh/t), survivor energy
ratio ``r = E / (E + E_m)``, Tavares' increment ``dD`` as the root of
``dD = (2 g r / (2 g - 5 dD + 5))^(2 g / 5)`` (scipy ``brentq``), accumulated
damage ``1 - (1 - D)(1 - dD)``; a rock whose damage reaches the threshold
breaks. A single impact cannot tell an accumulating model from one that
forgets the damage already there, so every chain here has three or more.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.optimize import brentq

from msmill import breakage as bk
from msmill.model.expected_value import impact_operator
from msmill.model.parameters import MixtureArrays
from msmill.model.submodels import AbT10Breakage, BreakageParameters, NoDamage, TavaresDamage

ORE = BreakageParameters(name="hand", A_pct=60.0, b_t_per_kwh=1.0, l_ref_mm=30.0, gamma=4.2,
                         damage_threshold=0.5)


def hand_increment(r: float, g: float) -> float:
    """Tavares' damage increment at energy ratio ``r`` (root of the implicit equation)."""
    if r == 0.0:
        return 0.0
    f = lambda d: d - (2 * g * r / (2 * g - 5 * d + 5)) ** (2 * g / 5)  # noqa: E731
    return brentq(f, 0.0, 1.0 - 1e-15, xtol=1e-15)


def hand_chain(energies_kwh_t, size_mm: float, d0: float = 0.0, ore=ORE) -> list[float]:
    """Damage after each impact of ``energies_kwh_t``, by hand."""
    d, out = d0, []
    for e in energies_kwh_t:
        em = ore.l_ref_mm * (1.0 - d) / (ore.b_t_per_kwh * size_mm)
        r = e / (e + em)
        d = 1.0 - (1.0 - d) * (1.0 - hand_increment(r, ore.gamma))
        out.append(d)
    return out


def test_hand_increment_is_the_first_root():
    # the equation has one root in [0, 1) over the range used here: brentq's is the code's
    for r in (0.05, 0.3, 0.6, 0.9):
        assert hand_increment(r, 4.2) == pytest.approx(bk.damage_increment(r, 4.2), abs=1e-12)


def test_tavares_three_unequal_impacts_accumulate():
    energies = [0.4, 0.9, 0.25, 1.3]  # kWh/t
    size = 20.0
    model = TavaresDamage(ORE)
    d, got = 0.0, []
    for e in energies:
        d = float(model.after_impact(e, size, d))
        got.append(d)
    want = hand_chain(energies, size)
    np.testing.assert_allclose(got, want, rtol=2e-5)
    # each impact adds damage: the increments alone would not be increasing like this
    assert np.all(np.diff(got) > 0)
    assert got[-1] > hand_increment(energies[-1] / (energies[-1] + ORE.l_ref_mm / size), ORE.gamma)


def test_tavares_on_predamaged_rocks_vectorised():
    d0 = np.array([0.0, 0.1, 0.3, 0.6])
    e, size = 0.5, np.array([[10.0], [40.0]])
    got = TavaresDamage(ORE).after_impact(e, size, d0)
    assert got.shape == (2, 4)
    for a, s in enumerate((10.0, 40.0)):
        for k, d in enumerate(d0):
            assert got[a, k] == pytest.approx(hand_chain([e], s, d0=float(d))[0], rel=2e-5)
    # 1 - D' = (1 - D)(1 - dD) with dD > 0: more damage than before, always
    assert np.all(got > d0)


def test_tavares_threshold_reached_after_hand_counted_impacts():
    model = TavaresDamage(ORE)
    assert model.threshold == ORE.damage_threshold
    e, size = 1.5, 20.0
    hand = hand_chain([e] * 10, size)
    n_hand = 1 + next(k for k, d in enumerate(hand) if d >= ORE.damage_threshold)
    assert n_hand >= 3  # the threshold is reached by accumulation, not by one impact
    d, n = 0.0, 0
    while d < model.threshold:
        d = float(model.after_impact(e, size, d))
        n += 1
        assert n <= 10
    assert n == n_hand


def test_no_damage_keeps_damage_over_three_impacts():
    model = NoDamage(ORE)
    assert model.threshold == 1.0
    d = np.array([0.0, 0.25, 0.5])
    for e in (0.3, 1.0, 2.0):
        d = model.after_impact(e, np.array([[10.0], [30.0]]), d)
        assert d.shape == (2, 3)
    np.testing.assert_array_equal(d, np.broadcast_to([0.0, 0.25, 0.5], (2, 3)))


def test_core_damage_after_impact_chain_with_threshold():
    """``msmill.breakage.damage_after_impact``: P_b with damage, then D', then the threshold."""
    energies, size, th = [1.5] * 5, 20.0, 0.5
    hand = hand_chain(energies, size)
    d = 0.0
    for k, e in enumerate(energies):
        res = bk.damage_after_impact(e, size, ORE.b_t_per_kwh, ORE.l_ref_mm, ORE.gamma, damage=d,
                                     damage_threshold=th)
        pb_hand = 1.0 - math.exp(-ORE.b_t_per_kwh * e * size / (ORE.l_ref_mm * (1.0 - d)))
        assert float(res.damage) == pytest.approx(hand[k], rel=1e-9)
        assert float(res.pb) == pytest.approx(1.0 if hand[k] >= th else pb_hand, rel=1e-12)
        d = float(res.damage)
    assert [h >= th for h in hand] == [False, False, False, True, True]


def test_expected_value_operator_breaks_at_the_threshold():
    """One size class, one velocity: the survive/break split of every damage class by hand."""
    edges = np.array([14.0, 16.0])
    size = math.sqrt(14.0 * 16.0)
    v = 110.0  # 1.68 kWh/t: the most damaged class reaches the threshold
    e = 0.5 * v * v / 3.6e3  # kWh/t
    mix = MixtureArrays(weights=np.array([[1.0]]), means_m_s=np.array([[v]]),
                        sigmas_m_s=np.array([[0.0]]))
    nd = 5
    op = impact_operator(edges, mix, AbT10Breakage(ORE), TavaresDamage(ORE), nd, 3)
    crossed = []
    for d_class in range(nd):
        d = d_class * ORE.damage_threshold / nd
        d_new = hand_chain([e], size, d0=d)[0]
        pb = 1.0 - math.exp(-ORE.b_t_per_kwh * e * size / (ORE.l_ref_mm * (1.0 - d)))
        crossed.append(d_new >= ORE.damage_threshold)
        surv = 0.0 if crossed[-1] else 1.0 - pb
        assert op.survive[0, :, d_class].sum() == pytest.approx(surv, rel=1e-4, abs=1e-12)
        assert op.fragments[0, 0, d_class] == pytest.approx(1.0 - surv, rel=1e-4, abs=1e-12)
    assert crossed == [False, False, False, False, True]
    # survivors land at the hand damage (the mean of the linear split between nodes;
    # damage above the last node stays in the last class)
    nodes = np.arange(nd) * ORE.damage_threshold / nd
    for d_class in range(nd):
        col = op.survive[0, :, d_class]
        d_new = hand_chain([e], size, d0=nodes[d_class])[0]
        if col.sum() > 0 and d_new < nodes[-1]:
            assert col @ nodes / col.sum() == pytest.approx(d_new, rel=1e-4)
