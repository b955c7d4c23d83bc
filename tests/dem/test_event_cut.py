"""The statistics read the contacts from a lookback before the window, not the whole record.

A fine-rock run records about 10 million contacts per simulated second; joining all of them for the
adaptive window's first check ran a 24 GiB machine out of memory (fine run 123, 3.5 mm, 37.7 t/h).
"""

import warnings
from dataclasses import replace

import pandas as pd
import pytest

from msmill.dem.mill.run import RunSettings, design_point, run_mill, save_run, stats_from_dir
from msmill.dem.mill.stats import StatsSettings, compute_statistics
from msmill.errors import MsmillInputError, OutOfDomainWarning
from msmill.machine import Machine, OperatingPoint

MACHINE = Machine.default().model_copy(update={"n_stages": 2})
SETTINGS = RunSettings(max_time_s=0.6, chunk_s=0.05, steady_window_s=0.1, rel_tol=0.5, trend_tol=5.0,
                       balance_tol=5.0, snapshot_every_s=0.005, adaptive=False, measure_s=0.15)
LOOKBACK = StatsSettings(event_lookback_s=0.1, with_filling_transport=False)


@pytest.fixture(scope="module")
def run():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", OutOfDomainWarning)
        op = OperatingPoint(feed_tph=60, speed_rpm=700, bottom_speed_factor=1.0, gate_deg=40)
        return run_mill(MACHINE, op, size_mm=20.0, mode="slice", settings=SETTINGS, stats_settings=LOOKBACK)


def _stages(ms):
    return [st.model_dump(mode="json") for st in ms.run.stages]


def test_events_since_are_the_record_filtered_by_onset(run):
    sim = run.scene.sim
    full = sim.events()
    assert full["time_s"].is_monotonic_increasing and len(full) > 200
    for since_s in (0.0, 0.25, float(full["time_s"].iloc[len(full) // 2])):
        cut = full[full["time_s"] >= since_s].reset_index(drop=True)
        pd.testing.assert_frame_equal(sim.events(since_s), cut)
    assert sim.events(sim.time_s + 1.0).empty


def test_a_run_holds_the_contacts_from_the_lookback_and_its_statistics_equal_those_of_the_whole_record(run):
    t0, _ = run.window_s
    cut_s = t0 - LOOKBACK.event_lookback_s
    assert cut_s > 0.1  # the cut drops part of the record
    full = run.scene.sim.events()
    assert run.events["time_s"].min() >= cut_s
    assert len(run.events) == int((full["time_s"] >= cut_s).sum()) < len(full)
    # the whole record with the same lookback gives the same statistics: compute_statistics cuts it itself
    sc = run.scene
    whole = compute_statistics(sc.machine, design_point(run.scene.machine, run.scene.op, run.scene.size_mm), full, run.removed, run.timeseries, run.snapshots,
                               run.window_s, rock_density_kg_m3=sc.rock.density_kg_m3, settings=LOOKBACK)
    assert _stages(whole) == _stages(run.stats)
    # a run without the filling transport (a window check) holds the snapshots from the cut on only,
    # and its statistics are those from every snapshot
    every = sc.sim.snapshots()
    assert run.snapshots["time_s"].min() >= cut_s - 1e-9 and len(run.snapshots) < sum(len(sn) for _, sn in every)
    check = compute_statistics(sc.machine, design_point(sc.machine, sc.op, sc.size_mm), full, run.removed,
                               run.timeseries, every, run.window_s, rock_density_kg_m3=sc.rock.density_kg_m3,
                               settings=LOOKBACK)
    assert _stages(check) == _stages(run.stats)
    prov = run.stats.run.provenance["stats"]
    assert prov["event_cut_s"] == pytest.approx(cut_s)


def test_passes_across_the_cut_are_counted(run):
    """Cut at the window start: passes already under way lose their earlier hits and are counted."""
    sc = run.scene
    full = sc.sim.events()
    args = (sc.machine, design_point(run.scene.machine, run.scene.op, run.scene.size_mm), full, run.removed, run.timeseries, run.snapshots, run.window_s)
    at_start = compute_statistics(*args, rock_density_kg_m3=sc.rock.density_kg_m3,
                                  settings=replace(LOOKBACK, event_lookback_s=0.0))
    whole = compute_statistics(*args, rock_density_kg_m3=sc.rock.density_kg_m3,
                               settings=replace(LOOKBACK, event_lookback_s=None))
    def n_primary(ms):
        return sum(len(ms.samples[s]["primary_velocity_m_s"]) for s in ms.samples)

    # a pass under way at the cut lost its first rotor hit: a later hit of it is taken as a primary
    assert n_primary(at_start) > n_primary(whole)
    assert at_start.run.provenance["stats"]["n_passes_from_event_cut"] > 0
    assert whole.run.provenance["stats"]["n_passes_from_event_cut"] == 0
    assert whole.run.provenance["stats"]["event_cut_s"] is None


def test_a_saved_run_recomputes_its_statistics_and_refuses_a_window_before_its_contacts(run, tmp_path):
    out = save_run(run, tmp_path / "run")
    again = stats_from_dir(out, LOOKBACK)
    assert _stages(again) == _stages(run.stats)
    t0, t1 = run.window_s
    with pytest.raises(MsmillInputError, match="window_s"):
        stats_from_dir(out, LOOKBACK, window_s=(t0 - 0.05, t1))
    with pytest.raises(MsmillInputError, match="window_s"):
        stats_from_dir(out, replace(LOOKBACK, event_lookback_s=None))


def test_a_negative_lookback_is_refused():
    with pytest.raises(MsmillInputError, match="event_lookback_s"):
        StatsSettings(event_lookback_s=-0.1)
