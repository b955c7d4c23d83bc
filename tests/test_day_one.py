"""Small things a user meets on day one (issue 40 item 7)."""

from __future__ import annotations

import os
import re
import stat
from pathlib import Path

import pytest

from msmill.cli.main import run as cli
from msmill.psd import PSD

ROOT = Path(__file__).resolve().parents[1]


def test_outputs_follow_the_umask(tmp_path, capsys):
    from msmill.cli.output import atomic_output, atomic_write_bytes

    old = os.umask(0o022)
    try:
        with atomic_output(tmp_path / "out") as stage:
            (stage / "a.csv").write_text("x\n")
        single = atomic_write_bytes(tmp_path / "one.json", b"{}")
    finally:
        os.umask(old)
    assert stat.S_IMODE((tmp_path / "out").stat().st_mode) == 0o755  # colleagues on a shared drive can read
    assert stat.S_IMODE(single.stat().st_mode) == 0o644


def test_psd_stats_reads_predicts_own_product_table(tmp_path, capsys):
    out = tmp_path / "p"
    assert cli(["predict", str(ROOT / "examples" / "ug2.toml"), "--out", str(out), "--no-plots"]) == 0
    p80 = re.search(r"P80 \(mm\)\s*│\s*([\d.]+)", capsys.readouterr().out).group(1)
    table = next(out.glob("*_product.csv"))
    assert cli(["psd", "stats", str(table)]) == 0
    shown = float(re.search(r"P80\s*│\s*([\d.]+) mm", capsys.readouterr().out).group(1))
    assert shown == pytest.approx(float(p80), rel=5e-3)
    import pandas as pd

    assert PSD.from_frame(pd.read_csv(table)).p80_mm == pytest.approx(float(p80), rel=5e-3)


def test_the_smallest_time_limit_printed_is_accepted(capsys):
    assert cli(["dem", "run", "default", "--size-mm", "20", "--max-time-s", "0.1", "--out", "unused"]) == 2
    shown = float(re.search(r"at least ([\d.]+) s", capsys.readouterr().err).group(1))
    from msmill.dem.mill.checks import check_run_inputs
    from msmill.dem.mill.run import RunSettings
    from msmill.machine import Machine

    check_run_inputs(Machine.default(), RunSettings(max_time_s=shown), 20.0)  # no error


@pytest.mark.parametrize("args,field", [
    (["optimize", "--bound", "speed_rpm=1200:1900", "--n-grid", "0"], "--n-grid"),
    (["optimize", "--bound", "speed_rpm=1200:1900", "--n-grid", "1000000"], "--n-grid"),
    (["optimize", "--bound", "speed_rpm=1200:1900", "--target-p80-mm", "-3"], "--target-p80-mm"),
    (["optimize", "--bound", "speed_rpm=1200:1900", "--target-p80-mm", "nan"], "--target-p80-mm"),
    (["optimize", "--bound", "speed_rpm=1200:1900", "--target-passing", "2:150"], "--target-passing (percent)"),
    (["optimize", "--bound", "speed_rpm=1200:1900", "--bound", "speed_rpm=1300:1400"], "--bound"),
    (["sweep", "--var", "speed_rpm=1200:1900:8", "--var", "speed_rpm=1200:1900:3"], "--var"),
    (["sweep", "--var", "speed_rpm=1200:1900:1000", "--var", "feed_tph=10:60:1000"], "--var"),
])
def test_sweep_and_optimize_refuse_nonsense_before_computing(args, field, capsys):
    cmd, *rest = args
    assert cli([cmd, str(ROOT / "examples" / "ug2.toml"), *rest]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: {field}:") and err.count("\n") == 1, err


def test_a_resource_limit_is_raised_by_its_environment_variable(monkeypatch):
    from msmill.errors import MsmillInputError
    from msmill.validate import limit

    with pytest.raises(MsmillInputError, match="MSMILL_LIMIT_SWEEP_POINTS"):
        limit(20_000, "--var", "sweep_points")
    monkeypatch.setenv("MSMILL_LIMIT_SWEEP_POINTS", "50000")
    limit(20_000, "--var", "sweep_points")


def test_the_psd_plot_shades_what_rests_on_extrapolated_statistics():
    import matplotlib

    matplotlib.use("Agg")
    from msmill.machine import OperatingPoint
    from msmill.model import Mill
    from msmill.plots.model import plot_psds

    feed = PSD.from_passing([2, 4.75, 9.5, 19, 31.5], [2, 6, 18, 58, 100])
    res = Mill("UG2", "default", band_samples=0).run(feed, OperatingPoint(feed_tph=30, speed_rpm=1500, gate_deg=40),
                                                     timeseries=False)
    mask = res.extrapolated_classes
    assert mask is not None and mask.any() and not mask.all()
    assert res.extrapolated_product_pct == pytest.approx(100 * res.product_psd.fractions[mask].sum())
    labels = plot_psds(res).get_legend_handles_labels()[1]
    assert labels.count("stage statistics extrapolated in size") == 1
