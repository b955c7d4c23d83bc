"""Streams and hold-up per time slot of a whole record (how a run settles after its start)."""

import warnings

import numpy as np
import pytest

from msmill.dem.mill.run import RunSettings, run_mill
from msmill.dem.mill.stats import _streams, slot_streams, snapshot_lag, stage_of_z, tagged_moves
from msmill.errors import MsmillInputError
from msmill.machine import Machine, OperatingPoint

MACHINE = Machine.default().model_copy(update={"n_stages": 2})
SHORT = RunSettings(max_time_s=0.6, chunk_s=0.1, steady_window_s=0.1, rel_tol=0.5, trend_tol=5.0, balance_tol=5.0,
                    measure_s=0.2, snapshot_every_s=0.005, start="table",
                    start_residence_s=[0.3, 0.3, 0.2])  # a 2-stage machine: no stage table; a given residence
RHO = 2700.0


@pytest.fixture(scope="module")
def run():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        op = OperatingPoint(feed_tph=60, speed_rpm=700, bottom_speed_factor=1.0, gate_deg=40.0)
        return run_mill(MACHINE, op, size_mm=20.0, mode="slice", settings=SHORT)


def _lag(run):
    return snapshot_lag(run.snapshots["time_s"].to_numpy(), run.stats.run.characteristic_time_s)


def test_slots_hold_the_mass_of_their_snapshots_and_fractions_that_add_up(run):
    lag, slot = _lag(run), 0.1
    tab = slot_streams(MACHINE, run.snapshots, run.removed, lag, slot_s=slot, rock_density_kg_m3=RHO)
    assert set(tab["stage"]) == {0, 1, 2}
    assert np.allclose(tab["slot_start_s"] / slot, np.round(tab["slot_start_s"] / slot))
    # hold-up: brute force over the snapshots of one slot
    snaps = run.snapshots
    s0 = 0.2
    times = np.unique(snaps["time_s"][(snaps["time_s"] >= s0 - 1e-9) & (snaps["time_s"] < s0 + slot - 1e-9)])
    for c in range(MACHINE.n_stages + 1):
        per = [float((RHO * 4 / 3 * np.pi * snaps["radius_m"][(snaps["time_s"] == t).to_numpy()
                      & (stage_of_z(MACHINE, snaps["z_m"].to_numpy()) == c)] ** 3).sum()) for t in times]
        row = tab[(np.isclose(tab["slot_start_s"], s0)) & (tab["stage"] == c)]
        assert float(row["holdup_kg"].iloc[0]) == pytest.approx(np.mean(per), rel=1e-12)
    # streams: the tagged moves whose tag time lies in the slot
    pairs = tagged_moves(MACHINE, snaps, run.removed, lag, RHO)
    ref = _streams(pairs[(pairs["time_s"] >= s0 - 1e-9) & (pairs["time_s"] < s0 + slot - 1e-9)], ["stage_from"])
    for c in ref.index:
        row = tab[(np.isclose(tab["slot_start_s"], s0)) & (tab["stage"] == c)].iloc[0]
        assert row["tagged_kg"] == pytest.approx(ref.loc[c, "mass_kg"], rel=1e-12)
        assert row["pass_through"] == pytest.approx(ref.loc[c, "pass_through"], abs=1e-12)
    tagged = tab[tab["tagged_kg"] > 0]
    assert np.allclose(tagged[["kickback", "refeed", "pass_through"]].sum(axis=1), 1.0)
    assert np.all(tab.loc[tab["stage"] == 0, "kickback"].fillna(0.0) == 0.0)  # nothing above the inlet zone


def test_slots_add_up_to_the_whole_record(run):
    """Mass-weighted over the slots the streams are those of all tagged moves together."""
    lag = _lag(run)
    tab = slot_streams(MACHINE, run.snapshots, run.removed, lag, slot_s=0.15, rock_density_kg_m3=RHO)
    whole = _streams(tagged_moves(MACHINE, run.snapshots, run.removed, lag, RHO), ["stage_from"])
    for c in range(MACHINE.n_stages + 1):
        rows = tab[(tab["stage"] == c) & (tab["tagged_kg"] > 0)]
        w = rows["tagged_kg"].to_numpy()
        assert w.sum() == pytest.approx(whole.loc[c, "mass_kg"], rel=1e-12)
        for k in ("kickback", "refeed", "pass_through"):
            assert np.dot(w, rows[k]) / w.sum() == pytest.approx(whole.loc[c, k], abs=1e-12)


def test_refuses_a_slot_that_is_not_positive(run):
    with pytest.raises(MsmillInputError, match="slot_s"):
        slot_streams(MACHINE, run.snapshots, run.removed, 1, slot_s=0.0)
