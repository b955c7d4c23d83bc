"""Single-impact fitting recovers the parameters of each breakage sub-model from whole product PSDs.

Tests are SYNTHETIC, made by the sub-models themselves (no noise), so the fit must recover the
generating parameters up to the 4-decimal rounding of the written passing values.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from msmill.model.experiments import experiment_from_dict
from msmill.model.fitting import (
    FITTABLE,
    _direct_columns,
    build_breakage,
    compare_submodels,
    fit_impact_tests,
    impact_grid,
    single_impact_product,
)
from msmill.model.mill import breakage_parameters
from msmill.model.synthetic import SIEVES_MM, synthetic_impact_test
from msmill.psd import PSD, SizeGrid

FEEDS = {"13x16": {"size_mm": [13.2, 16.0], "passing_pct": [0.0, 100.0]},
         "26x32": {"size_mm": [26.5, 31.5], "passing_pct": [0.0, 100.0]}}


def make_tests(ore, brk, speeds):
    out = []
    for fk, feed in FEEDS.items():
        for v in speeds:
            draft = experiment_from_dict({"kind": "single_impact", "id": "d", "ore": ore, "source": "d",
                                          "impact_speed_m_s": v, "feed": feed,
                                          "product": {"size_mm": list(SIEVES_MM),
                                                      "passing_pct": list(np.linspace(0, 100, len(SIEVES_MM)))}})
            grid = impact_grid([draft])
            frac = single_impact_product(brk, grid, draft.feed_psd.rebin(grid).fractions, v)
            out.append(synthetic_impact_test(f"{fk}-{v:g}", ore, feed, v, PSD(grid, frac, validate=False), 0.0,
                                             np.random.default_rng(0), "SYNTHETIC test"))
    return out


TRUE = {
    "ab_t10": {"A_pct": 64.0, "l_ref_mm": 21.0},
    "vogel_swebrec": {"A_pct": 59.0, "b_t_per_kwh": 0.5358, "e_min_kwh_t": 0.03, "swebrec_b": 2.2},
}


@pytest.mark.parametrize("name", list(TRUE))
def test_fit_recovers_known_parameters(name):
    bp = breakage_parameters("Platreef")
    brk = build_breakage(name, bp, TRUE[name])
    tests = make_tests("Platreef", brk, (15.0, 30.0, 45.0))
    fit = fit_impact_tests(tests, "Platreef", name)
    for k, v in TRUE[name].items():
        assert fit.params[k] == pytest.approx(v, rel=0.01), (k, fit.params)
    assert max(fit.ks.values()) < 0.01


def test_whole_psd_separates_probability_and_fineness():
    # same t10 = A * P_b at every energy is reachable by trading A against L_ref; the whole PSD is not
    bp = breakage_parameters("UG2")
    brk = build_breakage("ab_t10", dataclasses.replace(bp, l_ref_mm=20.0), {})
    tests = make_tests("UG2", brk, (20.0, 40.0))
    start = fit_impact_tests(tests, "UG2", "ab_t10", start={"A_pct": 90.0, "l_ref_mm": 60.0})
    assert start.params["A_pct"] == pytest.approx(71.8, rel=0.01)
    assert start.params["l_ref_mm"] == pytest.approx(20.0, rel=0.01)


def test_held_out_comparison_prefers_the_generating_submodel():
    bp = breakage_parameters("Platreef")
    brk = build_breakage("vogel_swebrec", bp, TRUE["vogel_swebrec"])
    tests = make_tests("Platreef", brk, (15.0, 30.0, 45.0))
    held = compare_submodels(tests, "Platreef")
    mean = held.groupby("submodel")["ks_held_out"].mean()
    assert mean["vogel_swebrec"] < 0.01 < mean["ab_t10"]


@pytest.mark.parametrize("name", sorted(FITTABLE))
def test_fitted_columns_are_each_submodels_own_forward_model(name):
    # a fit evaluates the appearance columns directly (no tables); they must be the sub-model's own,
    # t10 convention included: jk_t10 (t10 = A) was once fitted with ab_t10's t10 = A P_b columns
    bk = build_breakage(name, breakage_parameters("UG2"), {})
    grid = SizeGrid.geometric(0.05, 40.0)
    pb = np.linspace(0.05, 0.95, grid.n_classes)
    direct = _direct_columns(bk, grid, pb)
    forward = bk.fragments(grid.edges_mm, np.arange(grid.n_classes), pb)
    assert direct.shape == forward.shape
    assert np.max(np.abs(direct - forward)) < 2e-3, name  # the forward model's tables interpolate in P_b
