"""validate: K-S ~ 0 on model-made surveys, larger with the wrong ore; calibrate recovers L_ref.

All surveys here are SYNTHETIC, made by the model itself (msmill.model.synthetic).
"""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import pytest

from msmill.errors import OutOfDomainWarning
from msmill.model.fitting import calibrate_surveys
from msmill.model.synthetic import model_surveys
from msmill.model.validation import SurveyModel, measured_ks, validate
from msmill.psd import PSD

FEEDS = {"coarse": {"size_mm": [2.36, 4.75, 9.5, 13.2, 19.0, 26.5, 31.5],
                    "passing_pct": [2.0, 6.0, 18.0, 32.0, 58.0, 88.0, 100.0]},
         "fine": {"size_mm": [1.18, 2.36, 4.75, 9.5, 13.2, 19.0, 26.5],
                  "passing_pct": [3.0, 7.0, 16.0, 42.0, 63.0, 90.0, 100.0]}}
POINTS = [(30.0, 1500.0, 40.0), (30.0, 1700.0, 60.0)]


def specs(tag="s"):
    return [(f"{tag}{j}-{fk}", FEEDS[fk], tph, {"speed_rpm": rpm, "gate_deg": gate})
            for j, (tph, rpm, gate) in enumerate(POINTS) for fk in FEEDS]


@pytest.fixture(scope="module")
def clean_surveys():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", OutOfDomainWarning)
        return model_surveys("UG2", specs(), {"l_ref_mm": 20.0}, 0.0, np.random.default_rng(0))


def test_measured_ks_is_zero_for_identical_and_ignores_the_pan():
    a = PSD.from_passing([0.1, 1.0, 10.0], [5.0, 40.0, 100.0])
    assert measured_ks(a, a) == 0.0
    b = PSD.from_passing([0.1, 1.0, 10.0], [5.0, 60.0, 100.0])
    assert measured_ks(a, b) == pytest.approx(0.2)


def test_validate_near_zero_on_model_made_surveys_and_larger_for_the_wrong_ore(clean_surveys):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", OutOfDomainWarning)
        good = validate(clean_surveys, ores={"UG2": SurveyModel("UG2", clean_surveys).with_ore(l_ref_mm=20.0)})
        wrong = validate(clean_surveys, ores={"UG2": "Platreef"})
    # floor from reading two piecewise-linear curves on different sieves (docs/validation.md)
    assert good.table["ks"].max() < 0.012
    assert wrong.table["ks"].min() > 0.1
    assert list(good.summary["n"]) == [4]
    assert set(good.summary["best_id"]) <= set(good.table["id"])


def test_calibrate_recovers_l_ref_from_noisy_surveys_within_its_standard_error():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", OutOfDomainWarning)
        surveys = model_surveys("UG2", specs("n"), {"l_ref_mm": 20.0}, 0.05, np.random.default_rng(3))
        cal = calibrate_surveys(SurveyModel("UG2", surveys))  # starts from the default 29 mm
    L, se = cal.params["l_ref_mm"], cal.jackknife_std_errors["l_ref_mm"]
    assert 0 < se < 0.05 * 20.0
    assert abs(L - 20.0) < 3 * se, (L, se)  # made with the posterior mean: the surveys' scatter alone
    # the total adds the surrogate's posterior spread (8 samples of the stage parameters)
    assert cal.stage_samples == 8 and cal.stage_std_errors["l_ref_mm"] > 0
    assert cal.std_errors["l_ref_mm"] == pytest.approx(np.hypot(se, cal.stage_std_errors["l_ref_mm"]))
    assert cal.interpolation_ks < 1e-3
    assert cal.table["ks_fit"].mean() < cal.table["ks_before"].mean() / 3
    assert (cal.table["ks_cv"] >= cal.table["ks_fit"] - 1e-3).all()


def test_calibrate_refuses_b_with_l_ref(clean_surveys):
    from msmill.errors import MsmillInputError

    with pytest.raises(MsmillInputError, match="b/L_ref"):
        calibrate_surveys(SurveyModel("UG2", clean_surveys), fit=("l_ref_mm", "b_t_per_kwh"))


def test_calibrate_several_parameters_on_exact_solves():
    # one operating point, noise-free: A (start 71.8 %) from products made with A = 60 %
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", OutOfDomainWarning)
        sv = model_surveys("UG2", specs()[:2], {"A_pct": 60.0, "l_ref_mm": 20.0}, 0.0, np.random.default_rng(1))
        model = SurveyModel("UG2", sv)
        model.ore = model.with_ore(l_ref_mm=20.0)
        cal = calibrate_surveys(model, fit=("A_pct",), cross_validate=False, stage_samples=0)
    assert cal.params["A_pct"] == pytest.approx(60.0, rel=0.02)
    assert cal.table["ks_fit"].max() < 0.012


@pytest.mark.slow
def test_interval_covers_plants_whose_stage_parameters_are_posterior_draws():
    # issue 41: the plant's real stage parameters are not the surrogate's posterior mean. Surveys made with
    # each of 8 posterior draws (seed 5) and calibrated with the mean: the jackknife s.e. (the surveys'
    # scatter) alone misses L_ref = 20 by over 2 s.e. in most plants; the 95 % interval of the total (with
    # the stage parameters' part from 8 other draws, t quantiles of its Welch-Satterthwaite dof) covers at
    # least 6 of 8 (7.6 expected; P(<= 5 of 8) = 0.6 % for a true 95 % interval). 98-run surrogate: 3 of 8
    # and 7 of 8 within 2 s.e.; 121-run surrogate: 5 of 8 within 2 s.e. (|z| 2.08, 2.68, 2.88 outside), 6 of
    # 8 in the t interval (about 2.3 s.e. at 7-8 dof); the 122-run surrogate (a 3.12 mm run added) passes
    # too. One draw alone is no test: which one lands where
    # changes with every rebuild of the surrogate.
    from msmill.model.providers import load_provider, posterior_samples

    z_jack, covered = [], []
    for world in posterior_samples(load_provider("default"), 8, seed=5):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", OutOfDomainWarning)
            surveys = model_surveys("UG2", specs("n"), {"l_ref_mm": 20.0}, 0.05, np.random.default_rng(3),
                                    stage_parameters=world)
            cal = calibrate_surveys(SurveyModel("UG2", surveys))
        z_jack.append((cal.params["l_ref_mm"] - 20.0) / cal.jackknife_std_errors["l_ref_mm"])
        lo, hi = cal.interval("l_ref_mm")
        covered.append(lo <= 20.0 <= hi)
        assert 7.0 <= cal.dof["l_ref_mm"] <= 14.0  # between the larger part's 7 and both parts' 14
    assert np.sum(np.abs(z_jack) < 2.0) <= 4, z_jack
    assert np.sum(covered) >= 6, covered


def test_interval_uses_t_quantiles_of_the_welch_satterthwaite_dof():
    from msmill.model.fitting import SurveyCalibration, welch_satterthwaite_dof

    assert welch_satterthwaite_dof([(1.0, 7)]) == pytest.approx(7.0)
    assert welch_satterthwaite_dof([(1.0, 7), (1.0, 7)]) == pytest.approx(14.0)  # equal parts add their dof
    assert welch_satterthwaite_dof([(3.0, 7), (0.1, 7)]) == pytest.approx(7.0, rel=3e-3)  # the larger decides
    assert welch_satterthwaite_dof([(float("nan"), 7), (2.0, 5)]) == pytest.approx(5.0)
    assert welch_satterthwaite_dof([]) == float("inf")
    cal = SurveyCalibration("UG2", ("l_ref_mm",), {"l_ref_mm": 20.0}, {"l_ref_mm": 1.0}, {}, "ssq", None, 0.0,
                            0.0, 1, dof={"l_ref_mm": 7.0})
    lo, hi = cal.interval("l_ref_mm")
    assert hi - 20.0 == pytest.approx(2.3646, abs=1e-4) and 20.0 - lo == pytest.approx(hi - 20.0)  # t(0.975, 7)
    assert cal.interval("l_ref_mm", 0.90)[1] - 20.0 == pytest.approx(1.8946, abs=1e-4)  # t(0.95, 7)
    normal = dataclasses.replace(cal, dof={})
    assert normal.interval("l_ref_mm")[1] - 20.0 == pytest.approx(1.95996, abs=1e-4)


def test_posterior_sample_members_are_fixed_draws():
    from msmill.errors import MsmillInputError
    from msmill.model.providers import PosteriorSample, load_provider, posterior_samples

    prov = load_provider("default")
    a, b = posterior_samples(prov, 3, seed=1)[:2]
    sizes = np.array([5.0, 10.0, 20.0])
    pa = a.stage_parameters(sizes, [1500.0] * prov.n_stages, 30.0, 40.0)
    assert a.stage_parameters(sizes, [1500.0] * prov.n_stages, 30.0, 40.0) is pa  # the same draw each time
    pb = b.stage_parameters(sizes, [1500.0] * prov.n_stages, 30.0, 40.0)
    assert not np.allclose(pa.hit_probability, pb.hit_probability)
    with pytest.raises(MsmillInputError, match="posterior samples"):
        PosteriorSample(load_provider("table"), 0, 2)
