"""The expected-value solver's average over the impact-velocity mixture, by independent means.

The mean impact energy ``E[v^2 / 2]`` of a Gaussian mixture is
``sum_k w_k (mu_k^2 + sigma_k^2) / 2`` exactly (Gauss-Hermite with >= 2 nodes
integrates it exactly); the mean breakage probability is checked against
scipy ``quad`` of Eq. 11 over the mixture density. All parameters SYNTHETIC.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.integrate import quad
from scipy.stats import norm

from msmill.model.expected_value import impact_operator
from msmill.model.parameters import MixtureArrays
from msmill.model.submodels import AbT10Breakage, BreakageParameters, NoDamage

ORE = BreakageParameters("SYNTHETIC", A_pct=65.0, b_t_per_kwh=1.2, l_ref_mm=20.0)
W, MU, SIG = np.array([0.3, 0.7]), np.array([25.0, 45.0]), np.array([4.0, 7.0])
KWH_T_PER_J_KG = 1.0 / 3600.0


def _operator(n_nodes: int):
    edges = np.array([14.0, 16.0])
    mix = MixtureArrays(W[None], MU[None], SIG[None])
    return impact_operator(edges, mix, AbT10Breakage(ORE), NoDamage(), 1, n_nodes)


@pytest.mark.parametrize("n_nodes", [2, 5, 12])
def test_mean_energy_is_exact(n_nodes):
    want = float(np.sum(W * (MU**2 + SIG**2)) / 2.0 * KWH_T_PER_J_KG)
    assert _operator(n_nodes).mean_energy_kwh_t[0] == pytest.approx(want, rel=1e-12)


def test_mean_breakage_probability_equals_quadrature_of_eq11():
    size = math.sqrt(14.0 * 16.0)

    def pb(v):
        e = 0.5 * max(v, 0.0) ** 2 * KWH_T_PER_J_KG
        return 1.0 - math.exp(-ORE.b_t_per_kwh * e * size / ORE.l_ref_mm)

    want = sum(w * quad(lambda v, m=m, s=s: pb(v) * norm.pdf(v, m, s), m - 12 * s, m + 12 * s,
                        epsabs=1e-13)[0] for w, m, s in zip(W, MU, SIG, strict=True))
    op = _operator(16)
    assert 1.0 - op.survive[0, 0, 0] == pytest.approx(want, rel=1e-6)
    assert op.fragments[:, 0, 0].sum() == pytest.approx(want, rel=1e-6)
