"""Statistics from hand-constructed event and snapshot tables (no engine needed)."""

import numpy as np
import pandas as pd
import pytest

from msmill.dem.mill.stats import (
    characteristic_time,
    compute_statistics,
    identify_impacts,
    stage_of_z,
)
from msmill.machine import Machine
from msmill.stageparams import DesignPoint

M2 = Machine.default().model_copy(update={"n_stages": 2})  # stage 1 axis 1.05 m, stage 2 axis 0.60 m
R = 0.005
TIMES = np.round(np.arange(0.0, 0.2001, 0.01), 4)


def _snaps():
    rows = []
    for t in TIMES:
        rows += [(t, 1, 1.05), (t, 2, 1.05)]  # A, B stay in stage 1
        rows.append((t, 3, 1.05 if t < 0.1 - 1e-9 else 0.6))  # C drops to stage 2 at 0.10
        rows.append((t, 4, 1.05 if t < 0.12 - 1e-9 else 1.5))  # D kicked into the inlet zone at 0.12
        if t < 0.13 - 1e-9:
            rows.append((t, 5, 0.6))  # E in stage 2, leaves through the outlet at 0.13
    df = pd.DataFrame(rows, columns=["time_s", "particle_id", "z_m"])
    df["x_m"] = 0.0
    df["y_m"] = 0.3
    df["vx_m_s"] = 0.0
    df["vy_m_s"] = 0.0
    df["vz_m_s"] = -7.5
    df["radius_m"] = R
    return df


def _events():
    # time, pid, kind, partner, vn, z, tag, group
    rows = [
        (0.105, 1, 1, 10, 20.0, 1.05, "flinger", 0),   # primary (rotor 0)
        (0.110, 1, 1, 1, 3.0, 1.05, "liner", -1),      # secondary
        (0.120, 1, 0, 2, 2.0, 1.05, None, -1),         # rock-rock: secondary for A (B has no primary)
        (0.130, 1, 1, 11, 5.0, 1.05, "flinger", 0),    # same rotor again: secondary
        (0.135, 1, 1, 1, 0.1, 1.05, "liner", -1),      # too slow: not counted
        (0.140, 1, 1, 12, 25.0, 1.05, "flinger", 1),   # other rotor: second primary
        (0.150, 1, 1, 1, 4.0, 1.05, "liner", -1),      # secondary of the second primary
    ]
    ev = pd.DataFrame(rows, columns=["time_s", "particle_id", "partner_kind", "partner_id", "vn_m_s", "z_m",
                                     "partner_tag", "partner_group"])
    ev["partner_tag"] = ev["partner_tag"].fillna("")
    return ev


def _run(events=None):
    removed = pd.DataFrame({"particle_id": [5], "time_s": [0.13], "radius_m": [R], "mass_kg": [1.0],
                            "tag": ["outlet"]})
    ts = pd.DataFrame({"time_s": TIMES, "n_particles": 5, "mass_kg": 2.0, "kinetic_energy_j": 0.0,
                       "mass_out_kg": 0.0})
    design = DesignPoint(size_mm=10, feed_tph=30, speed_rpm=1500, gate_deg=40, stage_speeds_rpm=[1500, 3000])
    return compute_statistics(M2, design, _events() if events is None else events, removed, ts, _snaps(),
                              window_s=(0.0, 0.2), characteristic_time_s=0.05)


def test_stage_of_z_bands():
    z = np.array([-0.01, 0.1, 0.82, 0.83, 1.27, 1.3])
    assert stage_of_z(M2, z).tolist() == [3, 2, 2, 1, 1, 0]


def test_primary_and_secondary_labels():
    ev = identify_impacts(M2, _events(), _snaps())
    a = ev[ev["particle_id"] == 1].sort_values("time_s")
    assert a["is_primary"].tolist() == [True, False, False, False, False, True, False]
    b = ev[ev["particle_id"] == 2]
    assert len(b) == 1 and b["primary_row"].iloc[0] == -1  # mirrored rock-rock row, no primary before


def test_known_counts_hit_probability_and_streams():
    st = _run().run
    s1, s2 = st.stages
    # secondary counts per primary: [3, 1] -> lambda 2
    assert s1.secondary_lambda == pytest.approx(2.0)
    assert s1.n_secondary_impacts == 4
    assert s1.secondary_count_histogram == [0, 1, 0, 1]  # one primary with 1, one with 3
    assert s1.secondary_count.mean == pytest.approx(2.0)
    assert set(s1.secondary_count_selection.candidates) >= {"poisson", "negative_binomial"}
    assert s1.n_primary_impacts == 2
    # A is hit within (t, t+0.05] for tags t = 0.06..0.13 (8 of 54 stage-1 tags)
    assert s1.primary_hit_probability == pytest.approx(8 / 54)
    assert s1.kickback == pytest.approx(5 / 54)
    assert s1.pass_through == pytest.approx(5 / 54)
    assert s2.kickback == 0.0
    assert s2.pass_through == pytest.approx(5 / 19)
    assert s1.refeed == pytest.approx(44 / 54)
    assert st.characteristic_time_s == pytest.approx(0.05)
    assert st.mass_out_rate_kg_s == pytest.approx(1.0 / 0.2)


def test_characteristic_time_from_centre_speed():
    removed = pd.DataFrame(columns=["particle_id", "time_s", "radius_m", "mass_kg", "tag"])
    ts = pd.DataFrame({"time_s": TIMES, "n_particles": 5, "mass_kg": 2.0})
    design = DesignPoint(size_mm=10, feed_tph=30, speed_rpm=1500, gate_deg=40, stage_speeds_rpm=[1500, 3000])
    st = compute_statistics(M2, design, _events(), removed, ts, _snaps(), window_s=(0.0, 0.2)).run
    # 0.45 m / 7.5 m/s = 0.06 s, a whole number of 0.01 s snapshot intervals
    assert st.mean_centre_velocity_m_s == pytest.approx(7.5)
    assert st.characteristic_time_s == pytest.approx(0.06)


def test_touches_are_dropped_as_events_but_blow_ups_drop_the_rock():
    touch = pd.DataFrame([(0.125, 1, 1, 1, -0.01, 1.05, "liner", -1)], columns=_events().columns)
    st = _run(pd.concat([_events(), touch], ignore_index=True)).run
    # the touch of rock A is ignored, A's impacts still count: same as without it
    assert st.stages[0].n_primary_impacts == 2 and st.stages[0].secondary_lambda == pytest.approx(2.0)
    assert st.provenance["stats"]["n_touch_events_vn_le_0"] == 1
    assert st.provenance["stats"]["n_rocks_dropped_as_blow_ups"] == 0
    # an impossible speed (above 3 x 59.7 + 20 m/s) drops rock A altogether
    boom = pd.DataFrame([(0.125, 1, 1, 1, 500.0, 1.05, "liner", -1)], columns=_events().columns)
    st = _run(pd.concat([_events(), boom], ignore_index=True)).run
    assert st.stages[0].n_primary_impacts == 0
    assert st.provenance["stats"]["n_rocks_dropped_as_blow_ups"] == 1


def test_destinations_refine_the_streams_and_tag_the_inlet_zone():
    st = _run().run
    s1, s2 = st.stages
    for s in (s1, s2):
        d = np.asarray(s.destinations)
        assert d.size == 4 and d.sum() == pytest.approx(1.0)
        i = s.stage
        assert d[:i].sum() == pytest.approx(s.kickback)
        assert d[i] == pytest.approx(s.refeed)
        assert d[i + 1:].sum() == pytest.approx(s.pass_through)
    assert s1.destinations[0] == pytest.approx(5 / 54)  # D into the inlet zone
    assert s2.destinations[3] == pytest.approx(5 / 19)  # E out through the outlet
    # D sits in the inlet zone from 0.12 s: its 4 tags (0.12-0.15 s) are all still there 0.05 s later
    assert st.inlet_destinations == pytest.approx([1.0, 0.0, 0.0, 0.0])
    assert st.inlet_holdup_kg == pytest.approx(2700 * 4 / 3 * np.pi * R**3 * 9 / 21)


# rocks spread over the six horizontal regions (0.1 m each along the 0.6 m casing)
Y_OF_ROCK = {1: 0.05, 2: 0.05, 3: 0.25, 4: 0.45, 5: 0.55}  # A, B: region 0; C: 2; D: 4; E: 5


def _run_full(y_of_rock=Y_OF_ROCK, radius_of_rock=None):
    snaps = _snaps()
    snaps["y_m"] = snaps["particle_id"].map(y_of_rock)
    if radius_of_rock is not None:
        snaps["radius_m"] = snaps["particle_id"].map(radius_of_rock)
    removed = pd.DataFrame({"particle_id": [5], "time_s": [0.13], "radius_m": [R], "mass_kg": [1.0],
                            "tag": ["outlet"]})
    ts = pd.DataFrame({"time_s": TIMES, "n_particles": 5, "mass_kg": 2.0})
    design = DesignPoint(size_mm=10, feed_tph=30, speed_rpm=1500, gate_deg=40, stage_speeds_rpm=[1500, 3000])
    return compute_statistics(M2, design, _events(), removed, ts, snaps, window_s=(0.0, 0.2), mode="full",
                              characteristic_time_s=0.05, size_edges_m=np.array([0.0, 0.004, 0.02]),
                              rock_density_kg_m3=3000.0)


def test_raw_transport_counts_and_masses_by_hand():
    """Un-normalised quantities: tag counts and tagged masses against a hand count.

    Lag 5 snapshots, 16 tag times (0.00-0.15 s). Stage 1: A and B at every tag
    (32), C before 0.10 s (10), D before 0.12 s (12): 54 tags. Stage 2: E before
    0.13 s (13) and C from 0.10 s (6): 19 tags.
    """
    st = _run_full()
    s1, s2 = st.run.stages
    assert (s1.n_transport_samples, s2.n_transport_samples) == (54, 19)
    m_rock = 3000.0 * 4.0 / 3.0 * np.pi * R**3
    by = st.streams_by_size.set_index("stage_from")
    assert list(by["size_class"]) == [1, 1]  # r = 5 mm falls in the (4, 20) mm radius class
    np.testing.assert_allclose(by.loc[[1, 2], "mass_kg"], [54 * m_rock, 19 * m_rock], rtol=1e-12)
    # kickback: D tagged at 0.07-0.11 s (5); pass-through: C at 0.05-0.09 s (5), E at 0.08-0.12 s (5)
    np.testing.assert_allclose(by.loc[1, ["kickback", "refeed", "pass_through"]].to_numpy(dtype=float),
                               [5 / 54, 44 / 54, 5 / 54], rtol=1e-12)
    np.testing.assert_allclose(by.loc[2, ["kickback", "refeed", "pass_through"]].to_numpy(dtype=float),
                               [0.0, 14 / 19, 5 / 19], rtol=1e-12)


def test_region_weights_and_streams_by_hand():
    """Region weights: rock-snapshots per region (21 snapshots, 0.00-0.20 s); region streams: tags."""
    s1, s2 = _run_full().run.stages
    # stage 1: A, B 21 + 21 (region 0), C 10 (region 2), D 12 (region 4) of 64
    np.testing.assert_allclose(s1.region_weights, np.array([42, 0, 10, 0, 12, 0]) / 64, rtol=1e-12)
    # stage 2: C 11 (region 2, from 0.10 s), E 13 (region 5, before 0.13 s) of 24
    np.testing.assert_allclose(s2.region_weights, np.array([0, 0, 11, 0, 0, 13]) / 24, rtol=1e-12)
    avg1 = [s1.kickback, s1.refeed, s1.pass_through]
    avg2 = [s2.kickback, s2.refeed, s2.pass_through]
    want1 = [[0, 1, 0], avg1, [0, 0.5, 0.5], avg1, [5 / 12, 7 / 12, 0], avg1]
    want2 = [avg2, avg2, [0, 1, 0], avg2, avg2, [0, 8 / 13, 5 / 13]]
    np.testing.assert_allclose(s1.region_streams, want1, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(s2.region_streams, want2, rtol=1e-12, atol=1e-15)


def test_region_weights_are_solid_volumes_by_hand():
    """Two rock sizes: A has twice the radius (8 x the volume) of B, C, D and E.

    Rocks at y = 0.15 (A, region 1), 0.05 (B, region 0), 0.25 (C, region 2),
    0.45 (D, region 4), 0.55 (E, region 5); regions are 0.1 m wide from y = 0.
    Stage 1, rock-snapshots x volume (units of B's volume): A 21 x 8 = 168,
    B 21, C 10, D 12 of 211. Stage 2: C 11, E 13 of 24.
    """
    s1, s2 = _run_full({1: 0.15, 2: 0.05, 3: 0.25, 4: 0.45, 5: 0.55},
                       {1: 2 * R, 2: R, 3: R, 4: R, 5: R}).run.stages
    np.testing.assert_allclose(s1.region_weights, np.array([21, 168, 10, 0, 12, 0]) / 211, rtol=1e-12)
    np.testing.assert_allclose(s2.region_weights, np.array([0, 0, 11, 0, 0, 13]) / 24, rtol=1e-12)


def test_hit_window_edges_by_hand():
    """A tag at t counts as hit when a primary impact of its stage falls in (t, t + tau].

    tau = 0.05 s, stage-1 tags every 0.01 s from 0.00 to 0.15 s (54 in all). A's
    primary at 0.100 s is in the windows of the tags at 0.05-0.09 s (5: the tag at
    0.10 s itself is not, the one at 0.05 s is, at the closed end); B's at 0.155 s
    in those of the tags at 0.11-0.15 s (5). 10 of 54.
    """
    rows = [(0.100, 1, 1, 10, 20.0, 1.05, "flinger", 0), (0.155, 2, 1, 11, 20.0, 1.05, "flinger", 1)]
    events = pd.DataFrame(rows, columns=_events().columns)
    s1, s2 = _run(events).run.stages
    assert s1.n_primary_impacts == 2
    assert s1.primary_hit_probability == pytest.approx(10 / 54, rel=1e-12)
    assert s2.primary_hit_probability == 0.0


def test_characteristic_time_hand_table():
    """tau = stage spacing / mean speed of rocks inside the stages (others excluded)."""
    assert M2.stage_spacing_m == pytest.approx(0.45)
    rows = [  # time, pid, z (m), (vx, vy, vz) m/s
        (0.0, 1, 1.05, (3.0, 4.0, 0.0)),     # stage 1, 5 m/s
        (0.0, 2, 0.60, (0.0, 0.0, -10.0)),   # stage 2, 10 m/s
        (0.0, 3, 1.50, (50.0, 0.0, 0.0)),    # inlet zone: not counted
        (0.0, 4, -0.05, (0.0, 60.0, 0.0)),   # below the outlet: not counted
        (0.01, 1, 1.00, (6.0, 0.0, 8.0)),    # stage 1, 10 m/s
        (0.01, 2, 0.55, (0.0, 0.0, -15.0)),  # stage 2, 15 m/s
    ]
    snaps = pd.DataFrame([(t, p, z, *v) for t, p, z, v in rows],
                         columns=["time_s", "particle_id", "z_m", "vx_m_s", "vy_m_s", "vz_m_s"])
    tau, speed = characteristic_time(M2, snaps)
    assert speed == pytest.approx(10.0)  # (5 + 10 + 10 + 15) / 4
    assert tau == pytest.approx(0.045)
    # rounded to whole snapshot intervals: 0.045 / 0.02 = 2.25 -> 2 intervals; never below 1
    assert characteristic_time(M2, snaps, 0.02)[0] == pytest.approx(0.04)
    assert characteristic_time(M2, snaps, 0.1)[0] == pytest.approx(0.1)


def test_velocity_mean_error_is_by_batch_means():
    """Impacts clustered in time: the error of the mean is that of the batch means, not std / sqrt(n)."""
    from msmill.dem.mill.stats import _mean_se

    levels = np.array([20.0, 22.0, 19.0, 23.0, 21.0])  # one level per fifth of the window
    t = np.linspace(0.0, 1.0, 1000, endpoint=False)
    v = levels[(t * 5).astype(int)]
    se = _mean_se(v, t, (0.0, 1.0), 5)
    assert se == pytest.approx(levels.std(ddof=1) / np.sqrt(5), rel=1e-12)
    assert se > 10 * v.std(ddof=1) / np.sqrt(v.size)  # the independent-sample error understates it
    # all samples in one batch: no batch estimate, the independent-sample error
    early = t < 0.1
    w = v[early] + np.random.default_rng(1).normal(0.0, 1.0, early.sum())
    assert _mean_se(w, t[early], (0.0, 1.0), 5) == pytest.approx(w.std(ddof=1) / np.sqrt(w.size), rel=1e-12)
    assert np.isnan(_mean_se(v[:1], t[:1], (0.0, 1.0), 5))
