"""energy_t10: fragments that keep getting finer past the energy that breaks every rock (issue 41 item 4).

Single-impact tests here are SYNTHETIC, made by the sub-models themselves without noise; stage parameters
are the SYNTHETIC table of conftest.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from test_fitting_impacts import make_tests

from msmill.model import Mill
from msmill.model.fitting import (
    FITTABLE,
    build_breakage,
    compare_submodels,
    fit_impact_tests,
    single_impact_product,
)
from msmill.model.mill import breakage_parameters
from msmill.model.submodels import EnergyT10Breakage, simulate_lab_test
from msmill.psd import SizeGrid

GRID = SizeGrid.geometric(0.038, 32.0)
TOP = np.eye(GRID.n_classes)[-1]  # all feed in the top class
SIEVE = GRID.n_classes // 2  # a sieve far below the parent


def passing_at_sieve(brk, speed_m_s):
    return float(np.cumsum(single_impact_product(brk, GRID, TOP, speed_m_s))[SIEVE])


def test_fragments_keep_getting_finer_after_every_rock_breaks():
    bp = dataclasses.replace(breakage_parameters("UG2"), l_ref_mm=2.0)  # strong rock made weak: x of Eq. 11 > 50
    speeds = (150.0, 300.0, 600.0)
    brk = {n: build_breakage(n, bp, {"fineness_ratio": 0.002} if n == "energy_t10" else {}) for n in FITTABLE}
    for b in brk.values():  # every rock breaks at the slowest of them
        assert float(b.probability(np.array([0.5 * 150.0**2 / 3600.0]), np.array([GRID.mids_mm[-1]]),
                                   np.zeros(1))[0]) > 1 - 1e-9
    for name, b in brk.items():
        p = [passing_at_sieve(b, v) for v in speeds]
        if name == "energy_t10":
            assert p[0] + 0.02 < p[1] and p[1] + 0.02 < p[2], p  # finer at every step up in energy
        else:
            assert p[2] - p[0] < 1e-3, (name, p)  # saturated: the same product at 150 and 600 m/s


def test_fineness_ratio_one_is_ab_t10_and_large_is_jk_t10():
    bp = breakage_parameters("UG2")
    for v in (15.0, 45.0, 120.0):
        ab = single_impact_product(build_breakage("ab_t10", bp, {}), GRID, TOP, v)
        jk = single_impact_product(build_breakage("jk_t10", bp, {}), GRID, TOP, v)
        one = single_impact_product(build_breakage("energy_t10", bp, {"fineness_ratio": 1.0}), GRID, TOP, v)
        big = single_impact_product(build_breakage("energy_t10", bp, {"fineness_ratio": 1e6}), GRID, TOP, v)
        assert np.max(np.abs(one - ab)) < 1e-12 and np.max(np.abs(big - jk)) < 1e-9


def test_population_t10_of_a_drop_weight_test():
    # one impact per rock: population t10 = P_b * A (1 - exp(-c x)), x = b E L / L_ref
    bp = dataclasses.replace(breakage_parameters("UG2"), fineness_ratio=0.25)
    brk = EnergyT10Breakage(bp)
    e, size = np.array([0.05, 0.4, 2.0, 8.0]), np.full(4, 20.0)
    x = bp.b_t_per_kwh * e * size / bp.l_ref_mm
    expect = -np.expm1(-x) * bp.A_pct * -np.expm1(-0.25 * x)
    assert simulate_lab_test(brk, size, e) == pytest.approx(expect, rel=0.02)


def test_fit_recovers_the_fineness_ratio_and_the_comparison_prefers_it():
    true = {"A_pct": 64.0, "l_ref_mm": 21.0, "fineness_ratio": 0.15}
    bp = breakage_parameters("Platreef")
    tests = make_tests("Platreef", build_breakage("energy_t10", bp, true), (20.0, 50.0, 100.0, 200.0))
    fit = fit_impact_tests(tests, "Platreef", "energy_t10")
    for k, v in true.items():
        assert fit.params[k] == pytest.approx(v, rel=0.02), (k, fit.params)
    assert fit.identified and not fit.on_bound
    held = compare_submodels(tests, "Platreef").groupby("submodel")["ks_held_out"].mean()
    assert held["energy_t10"] < 0.01 and held["energy_t10"] < 0.5 * held.drop("energy_t10").min(), held


@pytest.mark.filterwarnings("ignore::msmill.errors.ExtrapolationWarning")  # the SYNTHETIC table stops at 30 mm
def test_usable_in_the_mill_model(provider, feed, op):
    ore = breakage_parameters("UG2")
    ab = Mill(ore, provider, breakage="ab_t10", band_samples=0).run(feed, op)
    one = Mill(dataclasses.replace(ore, fineness_ratio=1.0), provider, breakage="energy_t10",
               band_samples=0).run(feed, op)
    assert np.max(np.abs(one.product_psd.passing_pct - ab.product_psd.passing_pct)) < 1e-9
    slow = Mill(dataclasses.replace(ore, fineness_ratio=0.1), provider, breakage="energy_t10", band_samples=0)
    res = slow.run(feed, op)
    fine = res.product_psd.passing_at(4.0)
    assert fine < 0.5 * ab.product_psd.passing_at(4.0)  # fragments less fine at the mill's energies (1.5 vs 6.3 %)
    mc = Mill(dataclasses.replace(ore, fineness_ratio=0.1), provider, breakage="energy_t10",
              solver="monte_carlo", seed=1).run(feed, op)
    assert mc.product_psd.passing_at(4.0) == pytest.approx(fine, rel=0.1)  # both solvers use the fragment index
    default = Mill(ore, provider, breakage="energy_t10", band_samples=0).run(feed, op)
    assert any("fineness ratio" in n and "default" in n for n in default.notes)
