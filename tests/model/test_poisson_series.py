"""The stage operator of the expected-value solver against a direct Poisson series sum.

After a primary impact the survivors receive ``K ~ Poisson(lambda)`` secondary
impacts; fragments take no further impacts within the step. Summing the
series term by term, ``sum_K p_K S^K`` for the survivors and
``sum_K p_K sum_{m<K} F S^m`` for the fragments, is independent of the
matrix-exponential closed form the solver uses. All parameters SYNTHETIC.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import poisson

from msmill.model.expected_value import impact_operator, stage_operator
from msmill.model.parameters import MixtureArrays
from msmill.model.submodels import (
    AbT10Breakage,
    BreakageParameters,
    ImpactStatistics,
    TavaresDamage,
)
from msmill.psd import SizeGrid

GRID = SizeGrid.geometric(1.0, 40.0, ratio=2.0)
ORE = BreakageParameters("SYNTHETIC", A_pct=65.0, b_t_per_kwh=1.2, l_ref_mm=20.0, damage_threshold=0.6)
ND, NODES, K_MAX = 3, 4, 80


def _stats(rng, n):
    def mix():
        w = rng.dirichlet(np.ones(2), size=(1, n))
        return MixtureArrays(w, rng.uniform(10, 60, (1, n, 2)), rng.uniform(1, 10, (1, n, 2)))

    return ImpactStatistics(rng.uniform(0.2, 0.9, (1, n)), mix(), rng.uniform(0.5, 5.0, (1, n)), mix())


def _direct_series(stats):
    """G, expected secondary impacts per tonne, by summing the Poisson series term by term."""
    n, nd = GRID.n_classes, ND
    brk, dmg = AbT10Breakage(ORE), TavaresDamage(ORE)
    sub = lambda m: MixtureArrays(m.weights[0], m.means_m_s[0], m.sigmas_m_s[0])  # noqa: E731
    prim = impact_operator(GRID.edges_mm, sub(stats.primary_velocity), brk, dmg, nd, NODES)
    sec = impact_operator(GRID.edges_mm, sub(stats.secondary_velocity), brk, dmg, nd, NODES)
    G = np.zeros((n, nd, n, nd))
    count = np.zeros((n, nd))
    for j in range(n):
        h, lam = stats.hit_probability[0, j], stats.secondary_lambda[0, j]
        p = poisson.pmf(np.arange(K_MAX + 1), lam)
        tail = poisson.sf(np.arange(K_MAX + 1), lam)  # P(K > m): the m-th secondary happens
        for e in range(nd):
            x = prim.survive[j, :, e].copy()  # survivors of the primary, by damage class
            surv = np.zeros(nd)
            frag = prim.fragments[:, j, e].copy()
            for m in range(K_MAX + 1):
                surv += p[m] * x
                frag += tail[m] * (sec.fragments[:, j, :] @ x)
                count[j, e] += tail[m] * x.sum()
                x = sec.survive[j] @ x
            G[j, :, j, e] += h * surv
            G[:, 0, j, e] += h * frag
            G[j, e, j, e] += 1.0 - h
            count[j, e] *= h
    return G.reshape(n * nd, n * nd), count.reshape(-1)


@pytest.mark.parametrize("seed", [0, 1])
def test_stage_operator_equals_direct_poisson_series(seed):
    stats = _stats(np.random.default_rng(seed), GRID.n_classes)
    op = stage_operator(GRID.edges_mm, stats, 0, AbT10Breakage(ORE), TavaresDamage(ORE), ND, NODES)
    G, count = _direct_series(stats)
    np.testing.assert_allclose(op.G, G, rtol=0, atol=1e-11)
    np.testing.assert_allclose(op.secondary_count, count, rtol=1e-9, atol=1e-12)


def test_no_secondaries_when_lambda_is_zero():
    rng = np.random.default_rng(3)
    stats = _stats(rng, GRID.n_classes)
    stats = ImpactStatistics(stats.hit_probability, stats.primary_velocity,
                             np.zeros_like(stats.secondary_lambda), stats.secondary_velocity)
    op = stage_operator(GRID.edges_mm, stats, 0, AbT10Breakage(ORE), TavaresDamage(ORE), ND, NODES)
    G, count = _direct_series(stats)
    np.testing.assert_allclose(op.G, G, atol=1e-13)
    assert np.all(op.secondary_count == 0.0) and np.all(count == 0.0)
