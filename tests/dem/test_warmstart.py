"""Warm start from a finished run: rotor phase, rescaling, refusals (small fast scene)."""

import warnings

import numpy as np
import pytest

from msmill.dem.mill.run import RunSettings, run_mill
from msmill.dem.mill.scene import build_scene
from msmill.dem.mill.warmstart import WarmStart, place_warm_start
from msmill.dem.simulation import DemRuntimeWarning
from msmill.errors import MsmillInputError, OutOfDomainWarning
from msmill.machine import Machine, OperatingPoint

MACHINE = Machine.default().model_copy(update={"n_stages": 2})
SHORT = RunSettings(max_time_s=0.6, chunk_s=0.1, steady_window_s=0.1, rel_tol=0.5, trend_tol=5.0, balance_tol=5.0,
                    measure_s=0.2, snapshot_every_s=0.005)


def _op(feed, rpm, gate=40.0):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", OutOfDomainWarning)
        return OperatingPoint(feed_tph=feed, speed_rpm=rpm, bottom_speed_factor=1.0, gate_deg=gate)


@pytest.fixture(scope="module")
def source():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", OutOfDomainWarning)
        return WarmStart.from_run(run_mill(MACHINE, _op(60, 700), size_mm=20.0, mode="slice", settings=SHORT))


def _scene(feed, rpm, size=20.0, gate=40.0):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", OutOfDomainWarning)
        return build_scene(MACHINE, _op(feed, rpm, gate), size_mm=size, mode="slice", max_overlap_fraction=0.05)


def test_warm_hold_up_starts_clear_of_the_plates(source):
    sc = _scene(40, 800)
    rep = place_warm_start(sc, source)
    assert rep["n_turned_back"] > 0 and rep["n_placed"] > 0
    # hold-up scales with the feed rate: 40/60 of the source's, to within one rock
    rock_kg = 2700 * np.pi / 6 * 0.02**3
    assert rep["placed_kg"] == pytest.approx(rep["target_kg"], abs=rock_kg)
    assert rep["target_kg"] == pytest.approx(40 / 60 * source.particles["radius_m"].pipe(
        lambda r: (2700 * 4 / 3 * np.pi * r**3).sum()), rel=1e-9)
    with warnings.catch_warnings():
        warnings.simplefilter("error", DemRuntimeWarning)  # a rock inside a plate overlaps far beyond 5 %
        sc.sim.run(0.005, max_relative_speed_m_s=sc.max_impact_speed_m_s, safety=0.2, progress=False)


def test_finer_rock_and_speed_rescale(source):
    sc = _scene(60, 1400, size=19.5)  # still the two-row slice of 20 mm rock
    rep = place_warm_start(sc, source)
    assert rep["size_ratio"] == pytest.approx(0.975)
    assert rep["speed_ratio"] == pytest.approx(2.0)
    assert np.allclose(sc.sim.snapshot()["radius_m"], 0.00975)
    # the same positions hold fewer kilograms of finer rock: the rest comes from the feed
    assert rep["placed_fraction"] == pytest.approx(0.975**3, abs=0.05)


def test_warm_start_refuses_other_gate_coarser_rock_and_used_scene(source):
    with pytest.raises(MsmillInputError, match="gate"):
        place_warm_start(_scene(60, 700, gate=20.0), source)
    with pytest.raises(MsmillInputError, match="size"):
        place_warm_start(_scene(60, 700, size=24.0), source)
    sc = _scene(60, 700)
    place_warm_start(sc, source)
    with pytest.raises(MsmillInputError, match="fresh"):
        place_warm_start(sc, source)
