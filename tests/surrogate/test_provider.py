"""The surrogate as a stage-parameter provider: domain warnings, speed contract, uncertainty band, CLI."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from msmill.cli.main import run
from msmill.errors import OutOfDomainWarning, SummaryNote
from msmill.machine import OperatingPoint
from msmill.model import Mill
from msmill.model.providers import load_provider
from msmill.model.submodels import SpeedScaledImpacts
from msmill.providers_base import StageParameterProvider
from msmill.psd import PSD, SizeGrid
from msmill.surrogate.provider import SurrogateProvider

SPEEDS = [1500.0] * 4 + [3000.0]


@pytest.fixture(scope="module")
def provider(fitted):
    return SurrogateProvider(fitted)


def caught(fn):
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        out = fn()
    # sizes outside the trained ones are a SummaryNote (every feed has fines), the rest OutOfDomainWarning
    return out, [str(x.message) for x in w if issubclass(x.category, (OutOfDomainWarning, SummaryNote))]


def test_inside_the_training_domain_is_silent_and_valid(provider):
    p, msgs = caught(lambda: provider.stage_parameters(np.array([6.0, 10.0, 25.0]), SPEEDS, 30.0, 40.0))
    assert msgs == []
    assert isinstance(provider, StageParameterProvider)
    np.testing.assert_allclose(p.streams.sum(axis=-1), 1.0)
    np.testing.assert_allclose(p.primary_velocity.weights.sum(axis=-1), 1.0)
    assert np.all((p.hit_probability > 0) & (p.hit_probability < 1)) and np.all(p.secondary_lambda > 0)
    assert p.velocities_at_requested_speeds and p.streams.shape == (5, 3, 3)


def test_at_a_training_run_it_reproduces_the_run(provider, table_runs):
    r = table_runs[2]
    p = provider.stage_parameters(np.array([r.design.size_mm]), SPEEDS, 30.0, 40.0)
    for s, st in enumerate(r.stages):  # within the run's own sampling error (the GP smooths through noise)
        se = np.array([st.sampling_error[k] for k in ("kickback", "refeed", "pass_through")])
        assert np.all(np.abs(p.streams[s, 0] - st.streams) <= 3 * se + 0.01)
        se_hit = st.sampling_error["primary_hit_probability"]
        assert p.hit_probability[s, 0] == pytest.approx(st.primary_hit_probability, abs=3 * se_hit + 0.01)


def test_out_of_domain_says_by_how_much(provider):
    _, msgs = caught(lambda: provider.stage_parameters(np.array([3.0, 10.0, 60.0]), SPEEDS, 45.0, 70.0))
    text = " ".join(msgs)
    assert "2 of 3 size classes outside the trained 6-30 mm" in text
    assert "down to 3 mm, 2x below the smallest" in text and "up to 60 mm, 2x above the largest" in text
    assert "feed_tph 45 t/h is 15 t/h outside the trained 30-30" in text
    assert "gate_deg 70 deg is 30 deg outside" in text
    _, msgs = caught(lambda: provider.stage_parameters(np.array([10.0]), SPEEDS, 70.0, 40.0))
    assert "feed_tph lies 10 t/h outside the design space 10-60" in " ".join(msgs)


def test_speed_recipe_warns_per_stage(provider):
    speeds = [1500.0] * 4 + [3600.0]  # bottom stage at 2.4x instead of the trained 2x
    _, msgs = caught(lambda: provider.stage_parameters(np.array([10.0]), speeds, 30.0, 40.0))
    text = " ".join(msgs)
    assert "stage 5 speed 3600 rpm" in text and "600 rpm outside the 3000-3000 rpm" in text
    assert "stage 1" not in text


def test_speed_scaled_does_not_rescale_surrogate_velocities(provider):
    p = provider.stage_parameters(np.array([10.0]), SPEEDS, 30.0, 40.0)
    stats = SpeedScaledImpacts().impacts(p, np.array(SPEEDS) * 1.2)
    np.testing.assert_array_equal(stats.primary_velocity.means_m_s, p.primary_velocity.means_m_s)
    # a table's parameters (flag False) are rescaled as before
    import dataclasses

    q = dataclasses.replace(p, velocities_at_requested_speeds=False)
    stats = SpeedScaledImpacts().impacts(q, np.array(SPEEDS) * 1.2)
    np.testing.assert_allclose(stats.primary_velocity.means_m_s, 1.2 * p.primary_velocity.means_m_s)


def test_samples_scatter_about_the_mean(provider):
    sizes = np.array([8.0, 20.0])
    mean = provider.stage_parameters(sizes, SPEEDS, 30.0, 40.0)
    samples = provider.sample_stage_parameters(sizes, 64, SPEEDS, 45.0, 40.0, seed=1)
    hit = np.array([s.hit_probability for s in samples])
    assert len(samples) == 64 and hit.std(axis=0).min() > 0
    inside = provider.sample_stage_parameters(sizes, 64, SPEEDS, 30.0, 40.0, seed=1)
    far = np.array([s.hit_probability for s in samples]).std(axis=0)
    near = np.array([s.hit_probability for s in inside]).std(axis=0)
    # 15 t/h away from every run: more uncertain (targets the GP found flat stay as they are)
    assert np.all(far > 0.9 * near) and np.median(far / near) > 1.2
    assert np.median(np.array([s.hit_probability for s in inside]), axis=0) == pytest.approx(
        mean.hit_probability, abs=0.02)


@pytest.fixture(scope="module")
def grid():
    return SizeGrid.geometric(0.5, 45.0)


def test_mill_with_surrogate_has_a_band_bracketing_p80(provider, grid):
    feed = PSD.from_passing([6, 10, 20, 30, 45], [0, 10, 40, 70, 100], grid=grid)
    mill = Mill("UG2", provider, grid=grid, band_samples=16)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", OutOfDomainWarning)
        res = mill.run(feed, OperatingPoint(feed_tph=30, speed_rpm=1500, gate_deg=40), timeseries=False)
        far = mill.run(feed, OperatingPoint(feed_tph=50, speed_rpm=1500, gate_deg=40), timeseries=False)
    lo, hi = res.p80_band_mm
    assert lo < res.p80_mm < hi and res.band_samples == 16
    assert far.p80_band_mm[1] - far.p80_band_mm[0] > hi - lo
    t = res.psd_table
    assert np.all(t["product_passing_pct_p05"] <= t["product_passing_pct"] + 1e-9)
    assert np.all(t["product_passing_pct_p95"] >= t["product_passing_pct"] - 1e-9)
    table = Mill("UG2", "table", grid=grid)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", OutOfDomainWarning)
        assert table.run(feed, OperatingPoint(feed_tph=30, speed_rpm=1500, gate_deg=40),
                         timeseries=False).p80_band_mm is None


def test_load_provider_recognises_a_surrogate_file(saved):
    assert isinstance(load_provider(saved), SurrogateProvider)


def test_cli_fit_score_plan(tmp_path, capsys, saved):
    out = tmp_path / "s.json"
    assert run(["surrogate", "fit", "default", "--out", str(out), "--restarts", "0",
                "--plot", str(tmp_path / "loo.png")]) == 0
    text = capsys.readouterr().out
    assert "leave-one-out accuracy per stage" in text and "mean KL velocities" in text
    assert "every run has feed_tph = 30" in text
    assert out.is_file() and (tmp_path / "loo.png").stat().st_size > 1000
    assert run(["surrogate", "score", str(saved)]) == 0
    assert "KL primary v" in capsys.readouterr().out
    assert run(["surrogate", "plan", str(saved), "--batch", "3", "--n-initial", "4",
                "--out", str(tmp_path / "b.csv")]) == 0
    assert "believer" in capsys.readouterr().out
    assert len((tmp_path / "b.csv").read_text().splitlines()) == 4
    assert run(["surrogate", "fit", str(tmp_path / "nope.json")]) == 2
    assert "error: sources" in capsys.readouterr().err


RUN = """
title = "surrogate"
[ore]
name = "UG2"
[feed]
rate_tph = 30.0
size_mm = [4.75, 9.5, 19.0, 26.5]
passing_pct = [6.0, 18.0, 58.0, 100.0]
[operating]
speed_rpm = 1500.0
gate_deg = 40.0
[stage_parameters]
file = "{path}"
[model]
band_samples = 8
[grid]
min_mm = 0.5
[output]
dir = "out"
plots = false
"""


def test_predict_prints_and_writes_the_band(tmp_path, saved, capsys):
    p = tmp_path / "run.toml"
    p.write_text(RUN.format(path=saved), encoding="utf-8")
    assert run(["predict", str(p)]) == 0
    assert "P80 5-95 % band (mm, 8 GP samples)" in capsys.readouterr().out
    header = (tmp_path / "out" / "product.csv").read_text().splitlines()[0]
    assert header.endswith("product_passing_pct_p05,product_passing_pct_p95")
