"""Where the data are thin (issue 36): inside the trained box but far from every run, predictions warn."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from msmill.errors import ThinDataWarning
from msmill.machine import OperatingPoint
from msmill.model.providers import default_surrogate_path
from msmill.psd import PSD
from msmill.surrogate.persist import load


@pytest.fixture(scope="module")
def shipped():
    return load(default_surrogate_path())


def test_a_point_far_from_the_runs_is_thin_and_one_near_a_run_is_not(shipped):
    far = np.array([7.0, 58.0, 1880.0, 78.0])  # fine rock, high feed, fast, open: inside the box
    near = np.array([12.0, 35.0, 1550.0, 40.0])  # between central runs
    assert np.all((far >= shipped.domain_[:, 0]) & (far <= shipped.domain_[:, 1]))
    sup = shipped.data_support(np.vstack([far, near]))
    assert sup.thin.tolist() == [True, False]
    assert sup.spread_ratio[0] > sup.threshold > sup.spread_ratio[1]
    # the threshold is the 90 % quantile of the runs' own leave-one-out spreads: about 10 % of runs exceed it
    loo = shipped.gp_.loo_spread_ratio()
    assert np.mean(loo > sup.threshold) == pytest.approx(0.1, abs=0.02)
    # a run's own point, with the run in the fit, is less spread than without it
    at_runs = shipped.gp_.spread_ratio(shipped.training_.X)
    assert np.all(at_runs <= loo + 1e-12)


def test_predictions_warn_and_report_the_thin_share():
    from msmill.model import Mill

    feed = PSD.from_passing([6.7, 8.0, 9.5, 11.2], [0, 30, 80, 100])
    mill = Mill("UG2", "default", band_samples=0)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        far = mill.run(feed, OperatingPoint(feed_tph=58, speed_rpm=1880, gate_deg=78), timeseries=False)
    thin = [w for w in caught if issubclass(w.category, ThinDataWarning)]
    assert len(thin) == 1 and "nearest run" in str(thin[0].message) and "\n" not in str(thin[0].message)
    assert far.thin_data_feed_pct > 50 and far.summary()["thin_data_product_pct"] == far.thin_data_product_pct
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        near = mill.run(feed, OperatingPoint(feed_tph=30, speed_rpm=1500, gate_deg=40), timeseries=False)
    # near the runs the feed has no thin data; since the 2.2 mm run (issue 38) the product's 2.2-3.5 mm
    # classes are inside the trained sizes but far from every run (one run below 3.5 mm): a few % thin;
    # since the 2.0 mm run (10 t/h, gate 80) the 2.05 mm class too: 10.5 % of this product
    assert near.thin_data_feed_pct == 0.0
    assert near.thin_data_product_pct < 15.0 < far.thin_data_product_pct


def test_loo_coverage_counts_targets_inside_their_interval(shipped, monkeypatch):
    from msmill.surrogate.accuracy import COVERAGE_KINDS, loo_coverage

    cov90, cov50 = loo_coverage(shipped, 0.9), loo_coverage(shipped, 0.5)
    assert set(cov90) == set(COVERAGE_KINDS)
    assert all(0.0 <= cov50[k] <= cov90[k] <= 1.0 for k in cov90)
    mean, var = shipped.gp_.loo()
    monkeypatch.setattr(shipped.gp_, "loo", lambda: (mean, var * 1e-8))  # far too narrow: nothing covered
    assert max(loo_coverage(shipped, 0.9).values()) < 0.05
    monkeypatch.setattr(shipped.gp_, "loo", lambda: (mean, var * 1e8))  # far too wide: everything
    assert min(loo_coverage(shipped, 0.9).values()) == 1.0
