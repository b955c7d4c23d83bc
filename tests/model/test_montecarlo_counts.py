"""Monte-Carlo impact rounds against hand counts (all parameters SYNTHETIC).

One stage, every parcel hit once (hit probability 1, everything passes
through after one step, ``impacted="all"``), a single impact speed (sigma 0)
and rock that never breaks by ``P_b`` (:class:`NoBreakage`): the impacted
tonnes per round then follow from the secondary-count distribution alone,

- no damage: every primary survivor gets ``K ~ Poisson(lambda)`` secondary
  impacts, so secondary tonnes = ``lambda`` x primary tonnes;
- Tavares damage with the threshold between the damage after one and after
  two impacts: the first secondary impact breaks the rock, so secondary
  tonnes = ``P(K >= 1) = 1 - exp(-lambda)`` x primary tonnes; with the
  threshold at or below the damage of one impact, none.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from msmill.model.montecarlo import MonteCarloSolver
from msmill.model.parameters import MixtureArrays
from msmill.model.submodels import (
    BreakageParameters,
    ImpactStatistics,
    NoBreakage,
    NoDamage,
    TavaresDamage,
    specific_energy_kwh_t,
)
from msmill.psd import SizeGrid

GRID = SizeGrid.geometric(0.1, 40.0, ratio=2.0)
N = GRID.n_classes
PARENT = N - 2  # every feed parcel in one class
V_M_S = 60.0
TONNES_PER_STEP = 0.5
N_STEPS, COLLECT_FROM = 25, 5  # 20 collected steps, each with one step's feed in the stage
ORE = BreakageParameters("SYNTHETIC", A_pct=65.0, b_t_per_kwh=1.2, l_ref_mm=20.0)


def _run(lam: float, damage, parcels: int = 2000):
    streams = np.zeros((1, N, 3))
    streams[..., 2] = 1.0  # pass-through: one step in the stage, one round of impacts
    one = np.ones((1, N, 1))
    mix = MixtureArrays(one, V_M_S * one, 0.0 * one)
    stats = ImpactStatistics(np.ones((1, N)), mix, np.full((1, N), lam), mix)
    feed = np.zeros(N)
    feed[PARENT] = 1.0
    run = MonteCarloSolver(parcels, seed=11).run(GRID.edges_mm, streams, stats, NoBreakage(), damage, feed,
                                                TONNES_PER_STEP, N_STEPS, COLLECT_FROM, impacted="all")
    primary = float(run.counts["primary_t"][0])
    assert primary == pytest.approx(TONNES_PER_STEP * (N_STEPS - COLLECT_FROM), rel=1e-12)
    return primary, float(run.counts["secondary_t"][0]), run


def test_no_secondary_impacts_when_the_count_is_zero():
    _, secondary, run = _run(0.0, NoDamage())
    assert secondary == 0.0
    assert run.counts["secondary_kwh"][0] == 0.0


def test_secondary_tonnes_are_lambda_times_primary_tonnes():
    primary, secondary, run = _run(2.5, NoDamage())
    # 40 000 parcels, Var K = 2.5: the ratio's standard error is 0.008
    assert secondary / primary == pytest.approx(2.5, abs=0.04)
    e = float(specific_energy_kwh_t(V_M_S))
    assert run.counts["secondary_kwh"][0] == pytest.approx(secondary * e, rel=1e-12)


def _damage_chain() -> tuple[float, float]:
    dam = TavaresDamage(ORE)
    e = specific_energy_kwh_t(np.array([V_M_S]))
    size = np.array([GRID.mids_mm[PARENT]])
    d1 = dam.after_impact(e, size, np.zeros(1))
    d2 = dam.after_impact(e, size, d1)
    return float(d1[0]), float(d2[0])


def _tavares(threshold: float) -> TavaresDamage:
    return TavaresDamage(BreakageParameters("SYNTHETIC", A_pct=65.0, b_t_per_kwh=1.2, l_ref_mm=20.0,
                                            damage_threshold=threshold))


def test_threshold_breaks_at_the_first_secondary_impact():
    d1, d2 = _damage_chain()
    assert 0.05 < d1 < d2 < 0.95  # a real damage step per impact
    lam = 2.0
    primary, secondary, _ = _run(lam, _tavares(0.5 * (d1 + d2)))
    # P(K >= 1) = 1 - exp(-2) = 0.8647; standard error of the ratio ~0.002
    assert secondary / primary == pytest.approx(1.0 - math.exp(-lam), abs=0.01)


def test_threshold_reached_by_the_primary_impact_leaves_no_secondaries():
    d1, _ = _damage_chain()
    _, secondary, _ = _run(3.0, _tavares(d1))  # d >= threshold breaks (at equality too)
    assert secondary == 0.0
