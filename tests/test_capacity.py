"""Capacity from steady and choked points (msmill.surrogate.capacity). Points here are SYNTHETIC or HAND-MADE, except
the shipped envelope's (our DEM campaign)."""

import functools
import json
import warnings

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from msmill.errors import MsmillInputError
from msmill.surrogate.capacity import (
    AboveCapacityWarning,
    CapacityModel,
    EnvelopeData,
    EnvelopePoint,
    check_capacity,
    default_capacity_model,
    default_envelope_path,
    load_capacity,
    warn_if_above_capacity,
)


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


# ------------------------------------------------------------------ censored model, envelope files, shipped envelope
HAND = [EnvelopePoint(s, f, 1500.0, 40.0, "steady") for s in (10, 20, 30) for f in (10.0, 15.0)] + \
       [EnvelopePoint(s, f, 1500.0, 40.0, "choked", 20.0) for s in (10, 20, 30) for f in (25.0, 40.0)]


def test_censored_capacity_lies_between_what_passed_and_what_choked():
    """HAND-MADE points: 15 t/h passed, 25 t/h choked passing 20 t/h, so 20 <= capacity < 25."""
    m = CapacityModel.fit(HAND)
    assert 19.0 < m.capacity_tph(20.0, 1500.0, 40.0) < 25.5
    assert m.probability_steady(20.0, m.capacity_tph(20.0, 1500.0, 40.0), 1500.0, 40.0)[0] == pytest.approx(0.5)
    assert m.probability_steady(20.0, 12.0, 1500.0, 40.0)[0] > 0.9 > 0.1 > m.probability_steady(20.0, 35.0, 1500.0,
                                                                                                 40.0)[0]


@settings(max_examples=40, deadline=None)
@given(st.floats(4, 40), st.floats(1100, 2000), st.floats(0, 90), st.floats(2, 100), st.floats(1.01, 3))
def test_censored_probability_falls_with_feed(size, speed, gate, feed, factor):
    p = _synthetic_model().probability_steady(size, [feed, feed * factor], speed, gate)
    assert 0 <= p[1] <= p[0] <= 1
    if 1e-9 < p[0] < 1 - 1e-9:  # strictly, where the probability is not saturated
        assert p[1] < p[0]


@functools.lru_cache(maxsize=1)
def _synthetic_model():
    return CapacityModel.fit(synthetic_points(40, seed=3))


def test_envelope_file_round_trip_rebuilds_the_model(tmp_path):
    m = CapacityModel.fit(HAND)
    m.to_envelope(HAND, {"note": "HAND-MADE"}).to_json(tmp_path / "e.json")
    env = EnvelopeData.from_json(tmp_path / "e.json")
    assert env.points == HAND and env.counts() == {"steady": 6, "choked": 6, "not_steady": 0}
    args = ([8.0, 20.0, 33.0], [12.0, 22.0, 30.0], [1400.0, 1500.0, 1700.0], [20.0, 40.0, 60.0])
    for again in (load_capacity(tmp_path / "e.json"), load_capacity(tmp_path / "e.json", refit=True)):
        np.testing.assert_allclose(again.probability_steady(*args), m.probability_steady(*args), rtol=1e-6)
    doc = json.loads((tmp_path / "e.json").read_text())
    doc["model"]["params"]["coefficients"]["log_capacity_at_ref"] += 0.5  # stored parameters the points do not give
    (tmp_path / "bad.json").write_text(json.dumps(doc))
    with pytest.warns(UserWarning, match="differ from the stored"):
        load_capacity(tmp_path / "bad.json", refit=True)


def test_classifier_envelope_round_trip(tmp_path):
    m = CapacityModel.fit(HAND, method="classifier")
    m.to_envelope(HAND, {}).to_json(tmp_path / "c.json")
    again = load_capacity(tmp_path / "c.json")
    assert again.method == "classifier"
    np.testing.assert_allclose(again.probability_steady(20.0, [12.0, 30.0], 1500.0, 40.0),
                               m.probability_steady(20.0, [12.0, 30.0], 1500.0, 40.0), rtol=1e-6)


def test_message_says_capacity_feed_excess_and_probability():
    chk = check_capacity(CapacityModel.fit(HAND), 20.0, 30.0, 1500.0, 40.0)
    msg = chk.message()
    assert chk.above and "\n" not in msg
    assert f"capacity {chk.capacity_tph:.1f} t/h" in msg and "feed 30 t/h" in msg
    assert f"by {30.0 - chk.capacity_tph:.1f} t/h" in msg and f"probability of steady flow {chk.probability_steady:.2f}" in msg
    assert "extrapolated in speed_rpm" in check_capacity(CapacityModel.fit(HAND), 20.0, 30.0, 1800.0, 40.0).message()


def test_shipped_envelope_matches_the_shipped_export():
    """The shipped envelope was built from the shipped export (rebuild both together: scripts/build_envelope.py)."""
    from msmill.pipeline.export import default_export_dir, read_export

    path = default_envelope_path()
    runs = read_export(default_export_dir())
    # an export with steady runs always has an envelope: a capacity model with a choke, lower bounds without
    assert path is not None or not any(r.outcome == "steady" for r in runs), "build the envelope"
    if path is None:
        return
    env = EnvelopeData.from_json(path)
    assert {r["content_hash"] for r in env.provenance["runs"] if r["source"].startswith("export:")} == \
        {r.content_hash for r in runs}
    assert env.counts()["choked"] == sum(r.outcome == "choked" for r in runs) == env.provenance["counts"]["choked"]
    for key in ("command", "msmill_version", "git_commit", "date_utc", "inputs"):
        assert key in env.provenance
    m = default_capacity_model()
    # no choked run: the envelope states lower bounds (what steady runs passed), else the censored model
    assert m.method == ("censored" if env.counts()["choked"] else "demonstrated")
    assert m.n_choked == env.counts()["choked"]
    for p in env.points:  # every choked run's feed is above the capacity's lower bound, its throughput
        if p.outcome == "choked":
            assert m.probability_steady(p.size_mm, p.feed_tph, p.speed_rpm, p.gate_deg)[0] < \
                m.probability_steady(p.size_mm, p.throughput_tph, p.speed_rpm, p.gate_deg)[0]


def test_warning_threshold_is_the_capacity_itself():
    m = CapacityModel.fit(HAND)
    c = m.capacity_tph(20.0, 1500.0, 40.0)
    assert check_capacity(m, 20.0, 1.03 * c, 1500.0, 40.0).above
    assert not check_capacity(m, 20.0, 0.97 * c, 1500.0, 40.0).above


def test_capacity_is_uncertain_where_no_run_was_made():
    """HAND-MADE runs all at 1500 rpm and gate 40: the speed and gate slopes are the priors' there."""
    m = CapacityModel.fit(HAND)
    _, sd_at = m.log_capacity(20.0, 1500.0, 40.0)
    _, sd_off = m.log_capacity(20.0, 1900.0, 0.0)
    assert sd_off[0] > sd_at[0] + 0.5  # prior sd 1 per unit on two slopes, about 1.1 units away on each
    assert m.outside(20.0, 1900.0, 0.0) == ["speed_rpm", "gate_deg"]


# ---------------------------------------------------------------- "demonstrated": no run choked (lower bounds)
#: HAND-MADE steady runs (size mm, feed t/h, speed rpm, gate deg); none choked
STEADY_ONLY = [EnvelopePoint(20.0, 100.0, 1500.0, 10.0, "steady"), EnvelopePoint(24.0, 300.0, 1550.0, 30.0, "steady"),
               EnvelopePoint(20.0, 900.0, 1500.0, 60.0, "steady"), EnvelopePoint(40.0, 2000.0, 1500.0, 0.0, "steady"),
               EnvelopePoint(20.0, 5000.0, 1900.0, 0.0, "steady"), EnvelopePoint(20.0, 50.0, 1500.0, 5.0, "not_steady")]


def _bound_by_hand(size, speed, gate):
    """The lower bound from STEADY_ONLY written out: feed halved per unit distance (1.5x size, 250 rpm, 5 deg of
    gate closing; opening costs nothing)."""
    out = []
    for p in STEADY_ONLY:
        if p.outcome != "steady":
            continue
        d = np.hypot(np.hypot(np.log(p.size_mm / size) / np.log(1.5), (p.speed_rpm - speed) / 250.0),
                     max(p.gate_deg - gate, 0.0) / 5.0)
        out.append(p.feed_tph * 0.5 ** d)
    return max(out)


def test_demonstrated_bound_is_each_runs_feed_halved_per_unit_distance():
    m = CapacityModel.fit(STEADY_ONLY, method="demonstrated")
    assert m.lower_bound and m.n_steady == 5 and m.n_choked == 0
    for q in [(20.0, 1500.0, 40.0), (20.0, 1500.0, 62.0), (28.0, 1500.0, 5.0), (7.0, 1200.0, 0.0), (30, 1900, 80)]:
        assert m.capacity_tph(*q) == pytest.approx(_bound_by_hand(*q), rel=1e-12)
    # at a run's own point the bound is at least its feed: the 60 deg run's 900 t/h holds at 60 deg and above
    assert m.capacity_tph(20.0, 1500.0, 60.0) >= 900.0 and m.capacity_tph(20.0, 1500.0, 80.0) >= 900.0
    assert m.capacity_tph(20.0, 1500.0, 55.0) == pytest.approx(max(900.0 / 2, _bound_by_hand(20, 1500, 55)))
    cap = m.capacity_tph(20.0, 1500.0, 40.0)
    p = m.probability_steady(20.0, [0.99 * cap, cap, 1.01 * cap], 1500.0, 40.0)
    assert p[0] == p[1] == 1.0 and np.isnan(p[2])  # unknown above the bound, not a choke


@settings(max_examples=60, deadline=None)
@given(st.floats(10, 40), st.floats(1200, 1900), st.floats(0, 80), st.floats(0, 30))
def test_demonstrated_never_falls_as_the_gates_open(size, speed, gate, more):
    m = CapacityModel.fit(STEADY_ONLY, method="demonstrated")
    a, b = m.capacity_tph(size, speed, gate), m.capacity_tph(size, speed, gate + more)
    assert b >= a * (1 - 1e-12)


@settings(max_examples=60, deadline=None)
@given(st.floats(2, 30), st.floats(1200, 1900), st.floats(0, 80), st.floats(-1, 1), st.integers(0, 2))
def test_demonstrated_bound_has_no_jumps(size, speed, gate, step, which):
    """A small move changes the bound by at most the halving over that distance (log Lipschitz): no jumps from
    one nearest run to another (the old nearest-run box went 2520 -> 407 t/h between 1461 and 1476 rpm)."""
    m = CapacityModel.fit(STEADY_ONLY, method="demonstrated")
    q = np.array([size, speed, gate])
    units = np.array([np.log(1.5), 250.0, 5.0])
    moved = q.copy()
    if which == 0:
        moved[0] = size * np.exp(0.01 * step)
        dist = abs(0.01 * step) / units[0]
    else:
        moved[which] += 0.01 * step * units[which]
        dist = abs(0.01 * step)
    a, b = m.capacity_tph(*q), m.capacity_tph(*moved)
    assert abs(np.log(b / a)) <= dist * np.log(2.0) + 1e-9


def test_demonstrated_bound_only_rises_with_another_run():
    m = CapacityModel.fit(STEADY_ONLY, method="demonstrated")
    more = CapacityModel.fit([*STEADY_ONLY, EnvelopePoint(12.0, 40.0, 1300.0, 20.0, "steady")], method="demonstrated")
    for q in [(12.0, 1300.0, 20.0), (20.0, 1500.0, 40.0), (6.0, 1200.0, 0.0)]:
        assert more.capacity_tph(*q) >= m.capacity_tph(*q)
    assert more.capacity_tph(12.0, 1300.0, 20.0) >= 40.0


def test_demonstrated_warns_above_and_says_the_capacity_is_unknown_there():
    m = CapacityModel.fit(STEADY_ONLY, method="demonstrated")
    cap = m.capacity_tph(20.0, 1500.0, 40.0)
    chk = check_capacity(m, 20.0, cap + 150.0, 1500.0, 40.0)
    msg = chk.message()
    assert chk.above and chk.lower_bound and "\n" not in msg
    assert "above the feed the DEM has shown" in msg and f"{cap:.0f} t/h" in msg and "unknown" in msg
    assert "halved per 1.5x in rock size" in msg
    below = check_capacity(m, 20.0, cap - 50.0, 1500.0, 40.0)
    assert not below.above and f"capacity at least {cap:.0f} t/h" in below.message()
    with pytest.warns(AboveCapacityWarning, match="feed the DEM has shown"):
        warn_if_above_capacity(m, 20.0, cap + 150.0, 1500.0, 40.0)


def test_demonstrated_envelope_round_trip_and_points_only_file(tmp_path):
    m = CapacityModel.fit(STEADY_ONLY, method="demonstrated")
    m.to_envelope(STEADY_ONLY, {"note": "HAND-MADE"}).to_json(tmp_path / "e.json")
    again = load_capacity(tmp_path / "e.json")
    assert again.method == "demonstrated" and again.capacity_tph(20.0, 1500.0, 40.0) == m.capacity_tph(20.0, 1500.0, 40.0)
    EnvelopeData(STEADY_ONLY).to_json(tmp_path / "points.json")  # no model entry, no choke: demonstrated
    assert load_capacity(tmp_path / "points.json").method == "demonstrated"
    with pytest.raises(MsmillInputError, match="steady"):
        CapacityModel.fit([p for p in STEADY_ONLY if p.outcome != "steady"], method="demonstrated")
