"""Capacity from steady and choked points (msmill.capacity). All points here are SYNTHETIC."""

import warnings

import numpy as np
import pytest

from msmill.capacity import (
    AboveCapacityWarning,
    CapacityModel,
    EnvelopeData,
    EnvelopePoint,
    warn_if_above_capacity,
)
from msmill.errors import MsmillInputError


def true_capacity(size_mm, speed_rpm, gate_deg):
    """SYNTHETIC capacity law (t/h): more with coarser rock, faster shafts and more open gates."""
    return 15.0 + 8.0 * np.log(size_mm / 2.0) + 0.01 * (speed_rpm - 1200.0) + 0.15 * gate_deg


def synthetic_points(n=80, seed=1):
    rng = np.random.default_rng(seed)
    size = np.exp(rng.uniform(np.log(2), np.log(30), n))
    speed = rng.uniform(1200, 1900, n)
    gate = rng.uniform(0, 80, n)
    feed = rng.uniform(10, 60, n)
    cap = true_capacity(size, speed, gate)
    pts = []
    for s, f, v, g, c in zip(size, feed, speed, gate, cap, strict=True):
        choked = f > c
        pts.append(EnvelopePoint(s, f, v, g, "choked" if choked else "steady", c if choked else f))
    return pts


@pytest.fixture(scope="module")
def model():
    return CapacityModel.fit(synthetic_points())


@pytest.mark.parametrize("size,speed,gate", [(10.0, 1500.0, 40.0), (20.0, 1700.0, 20.0), (6.0, 1300.0, 60.0)])
def test_capacity_recovers_the_synthetic_law(model, size, speed, gate):
    assert model.capacity_tph(size, speed, gate) == pytest.approx(true_capacity(size, speed, gate), rel=0.15)


def test_probability_falls_through_capacity(model):
    cap = true_capacity(10.0, 1500.0, 40.0)
    p = model.probability_steady(10.0, [0.6 * cap, 1.4 * cap], 1500.0, 40.0)
    assert p[0] > 0.8 and p[1] < 0.2


def test_warning_above_capacity_and_silence_below(model):
    cap = true_capacity(10.0, 1500.0, 40.0)
    with pytest.warns(AboveCapacityWarning, match="above the predicted capacity"):
        warn_if_above_capacity(model, 10.0, 1.3 * cap, 1500.0, 40.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert warn_if_above_capacity(model, 10.0, 0.7 * cap, 1500.0, 40.0) > 0.7 * cap
        assert warn_if_above_capacity(None, 10.0, 1e3, 1500.0, 40.0) is None  # no data: no opinion


def test_needs_both_outcomes_and_ignores_not_steady():
    pts = [EnvelopePoint(10, 20, 1500, 40, "steady"), EnvelopePoint(10, 50, 1500, 40, "not_steady")]
    with pytest.raises(MsmillInputError, match="choked"):
        CapacityModel.fit(pts)


def test_envelope_json_round_trip(tmp_path):
    pts = synthetic_points(5)
    EnvelopeData(pts, {"note": "SYNTHETIC"}).to_json(tmp_path / "e.json")
    again = EnvelopeData.from_json(tmp_path / "e.json")
    assert again.points == pts
    (tmp_path / "bad.json").write_text("{}")
    with pytest.raises(MsmillInputError):
        EnvelopeData.from_json(tmp_path / "bad.json")
