"""The other bounding rule below the DEM's sizes (issue 38): statistics held at the smallest covered size."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from msmill.machine import OperatingPoint
from msmill.model import Mill
from msmill.model.providers import HeldBelow, TableProvider, default_table_path, smallest_covered_mm
from msmill.psd import PSD, SizeGrid

GRID = SizeGrid.geometric(0.038, 40.0)
OP = OperatingPoint(feed_tph=30, speed_rpm=1500, gate_deg=40)


@pytest.fixture(scope="module")
def table():
    return TableProvider.from_file(default_table_path())


def test_held_parameters_are_the_smallest_covered_sizes(table):
    lo = table.covered_sizes_mm[0]
    sizes = np.array([lo / 8, lo / 2, lo, 2 * lo])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        held = HeldBelow(table).stage_parameters(sizes)
        own = table.stage_parameters(sizes)
        at_lo = table.stage_parameters(np.full(4, lo))
    np.testing.assert_array_equal(held.sizes_mm, sizes)
    for k in range(2):  # below: the values at lo
        np.testing.assert_allclose(held.hit_probability[:, k], at_lo.hit_probability[:, 0], rtol=1e-12)
        np.testing.assert_allclose(held.secondary_lambda[:, k], at_lo.secondary_lambda[:, 0], rtol=1e-12)
    np.testing.assert_allclose(held.hit_probability[:, 2:], own.hit_probability[:, 2:], rtol=1e-12)  # above: own
    assert not np.allclose(own.hit_probability[:, 0], at_lo.hit_probability[:, 0])  # the table does extrapolate
    np.testing.assert_array_equal(held.extrapolated, own.extrapolated)
    assert smallest_covered_mm(own, table) == lo
    assert smallest_covered_mm(table.stage_parameters(np.array([lo, 2 * lo])), table) is None


def test_a_prediction_reports_both_rules(table):
    feed = PSD.from_passing([0.1, 1, 5, 10, 20, 40], [1, 5, 20, 40, 70, 100], GRID)
    mill = Mill("UG2", table, grid=GRID, envelope=None)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = mill.run(feed, OP, timeseries=False)
        held = Mill("UG2", HeldBelow(table), grid=GRID, envelope=None).run(feed, OP, timeseries=False,
                                                                           held_below=False)
        off = mill.run(feed, OP, timeseries=False, held_below=False)
    assert res.held_below_mm == table.covered_sizes_mm[0]
    assert res.held_below_p80_mm == pytest.approx(held.p80_mm, rel=1e-12)
    assert res.held_below_passing_75um_pct == pytest.approx(float(held.product_psd.passing_at(0.075)), rel=1e-12)
    # the rule matters for the fines
    assert res.held_below_passing_75um_pct != pytest.approx(float(res.product_psd.passing_at(0.075)), rel=1e-3)
    assert res.p80_mm == off.p80_mm and np.isnan(off.held_below_p80_mm)
    assert any(n.startswith("rule below the DEM's sizes") for n in res.notes)
    s = res.summary()
    assert s["held_below_p80_mm"] == res.held_below_p80_mm and "passing_75um_pct" in s
