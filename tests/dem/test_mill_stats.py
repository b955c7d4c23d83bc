"""Statistics from hand-constructed event and snapshot tables (no engine needed)."""

import numpy as np
import pandas as pd
import pytest

from msmill.dem.mill.stats import (
    compute_statistics,
    detect_steady_state,
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
    for s in (s1, s2):
        assert s.kickback + s.refeed + s.pass_through == pytest.approx(1.0)
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


def test_steady_state_detection():
    t = np.linspace(0, 4, 2001)
    n = 1000 * (1 - np.exp(-t / 0.4)) + np.random.default_rng(0).normal(0, 5, t.size)
    onset, detected = detect_steady_state(t, n, window_s=0.4, rel_tol=0.03, trend_tol=0.05)
    assert 0.6 < onset < 2.0 and detected == pytest.approx(onset + 0.8)
    assert detect_steady_state(t, 100 * t, window_s=0.4) is None


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
