"""A saved run's steady state by today's criterion, on its own time series (no DEM run needed)."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
import tomli_w

from msmill.dem.mill.run import RunSettings, saved_run_feed_kg_s, saved_run_verdict
from msmill.dem.mill.scene import scene_extent
from msmill.machine import Machine
from msmill.steadystate import first_steady

FEED_TPH = 30.0
RESIDENCE_S = 1.2


def _filling(feed_kg_s: float, t_end_s: float) -> pd.DataFrame:
    """A well-mixed mill filling from empty: H = F T (1 - exp(-t/T)), product out = F t - H (kg)."""
    t = np.linspace(0.0, t_end_s, 2001)
    h = feed_kg_s * RESIDENCE_S * (1.0 - np.exp(-t / RESIDENCE_S))
    return pd.DataFrame({"time_s": t, "n_particles": h / 0.01, "mass_kg": h, "mass_out_kg": feed_kg_s * t - h})


def _saved(tmp_path, scale_recorded: float | None, scale_series: float, t_end_s: float = 6.0):
    m = Machine.default()
    (tmp_path / "machine.toml").write_text(m.to_toml(), encoding="utf-8")
    result = {"steady_state_time_s": -1.0, "window_start_s": t_end_s - 0.5, "window_end_s": t_end_s}
    if scale_recorded is not None:
        result["feed_scale"] = scale_recorded
    doc = {"design": {"size_mm": 20.0, "feed_tph": FEED_TPH, "gate_deg": 40.0, "speed_rpm": 1500.0,
                      "stage_speeds_rpm": [1500.0] * 4 + [3000.0], "mode": "slice"},
           "feed": {"sizes_mm": [20.0], "mass_fractions": [1.0]}, "result": result}
    (tmp_path / "run.toml").write_text(tomli_w.dumps(doc), encoding="utf-8")
    ts = _filling(FEED_TPH / 3.6 * scale_series, t_end_s)
    ts.to_parquet(tmp_path / "timeseries.parquet")
    return tmp_path, ts


def test_onset_is_the_run_protocols_test_on_the_saved_series(tmp_path):
    d, ts = _saved(tmp_path, scale_recorded=0.25, scale_series=0.25)
    v = saved_run_verdict(d)
    expect = first_steady(ts["time_s"].to_numpy(), ts["mass_kg"].to_numpy(), ts["mass_out_kg"].to_numpy(),
                          FEED_TPH / 3.6 * 0.25, RunSettings().criterion())
    assert v.outcome == "steady"
    assert v.onset_s == pytest.approx(expect[0], abs=1e-12)
    # the hold-up slope F exp(-t/T) falls to 10 % of the feed at T ln 10: the onset cannot be before ~ that - 2W
    assert v.onset_s >= RESIDENCE_S * np.log(10.0) - 2 * RunSettings().steady_window_s - 1e-9


def test_feed_rate_is_the_scenes_not_the_full_mills(tmp_path):
    """Runs saved before the feed scale was recorded take it from the scene (as stats_from_dir does)."""
    scale = scene_extent(Machine.default(), np.array([20.0]), "slice")[3]
    d, _ = _saved(tmp_path, scale_recorded=None, scale_series=scale)
    assert saved_run_feed_kg_s(d) == pytest.approx(FEED_TPH / 3.6 * scale, rel=1e-12)
    assert saved_run_verdict(d).outcome == "steady"


def test_a_series_at_another_feed_rate_is_not_steady(tmp_path):
    """Product at half the scene's feed rate fails the mass balance however flat the hold-up is."""
    d, _ = _saved(tmp_path, scale_recorded=0.5, scale_series=0.25)
    v = saved_run_verdict(d)
    assert v.onset_s is None and v.outcome == "choked"


def test_model_and_dem_onsets_agree_on_the_same_filling(tmp_path):
    """The model's time_to_steady_state (t, t/h, its own steps) and a saved DEM run (kg, 1 ms) judge alike."""
    from msmill.model.result import time_to_steady_state

    d, _ = _saved(tmp_path, scale_recorded=1.0, scale_series=1.0)
    dem = saved_run_verdict(d).onset_s
    dt_s = 0.03
    t = np.arange(1, int(6.0 / dt_s) + 1) * dt_s
    holdup_t = FEED_TPH / 3600.0 * RESIDENCE_S * (1.0 - np.exp(-t / RESIDENCE_S))
    product_tph = FEED_TPH * (1.0 - np.exp(-(t - dt_s / 2) / RESIDENCE_S))  # mean rate over each step
    model = time_to_steady_state(t, product_tph, FEED_TPH, holdup_t=holdup_t)
    assert dem is not None and np.isfinite(model)
    # the criterion's grid step (W / 20) and the model's step bound the difference
    assert abs(model - dem) <= RunSettings().steady_window_s / 20 + dt_s


def test_a_short_old_record_is_never_judged_choked():
    from msmill.dem.mill.run import retrospective_outcome

    # a record ending before today's limit cannot tell a choke from a mill still filling
    assert retrospective_outcome("choked", 4.4, 8.1) == "not_steady"
    # a record as long as the limit can
    assert retrospective_outcome("choked", 8.1, 8.1) == "choked"
    for outcome in ("steady", "not_steady"):
        assert retrospective_outcome(outcome, 2.0, 8.1) == outcome
