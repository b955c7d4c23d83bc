"""A run that hits its time limit: non-zero exit, a clear message, statistics marked and refused."""

import json
import warnings

import pytest

from msmill.dem.mill.run import RunSettings, expected_residence_s
from msmill.errors import MsmillInputError, OutOfDomainWarning
from msmill.machine import Machine
from msmill.stageparams import RunStatistics, StageParameterTable


def test_time_limit_scales_with_the_residence_time():
    rs = RunSettings(min_time_s=0.0, max_time_cap_s=1e9)
    for size in (6.0, 14.0, 30.0):
        assert rs.time_limit_s(size) == pytest.approx(2 * 0.65 + 6.0 * expected_residence_s(size))
    assert RunSettings(max_time_s=2.5).time_limit_s(10.0) == 2.5
    assert RunSettings().time_limit_s(20.0) >= 4.0  # never shorter than the old fixed limit


@pytest.fixture(scope="module")
def limited_run(tmp_path_factory):
    from msmill.cli.main import run as cli

    d = tmp_path_factory.mktemp("limited")
    m = Machine.default().model_copy(update={"n_stages": 2})
    m.to_toml(d / "m.toml")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", OutOfDomainWarning)
        code = cli(["dem", "run", str(d / "m.toml"), "--size-mm", "20", "--feed-tph", "40", "--speed-rpm", "600",
                    "--bottom-factor", "1", "--slice", "--max-time-s", "0.6", "--measure-s", "0.1",
                    "--out", str(d / "run"), "--no-progress"])
    return code, d / "run"


def test_run_hitting_its_limit_exits_non_zero_and_is_marked(limited_run, capsys):
    code, out = limited_run
    assert code in (3, 4)  # not steady or choked: a mill fed for 0.6 s from empty cannot balance its feed
    st = RunStatistics.from_json(out / "statistics.json")
    assert st.outcome in ("not_steady", "choked")
    assert st.provenance["outcome"] == st.outcome
    assert st.throughput_tph is not None and st.throughput_tph < 40.0
    with pytest.raises(MsmillInputError, match="outcome"):
        st.require_steady()
    assert st.require_steady(allow_not_steady=True) is st


def test_stage_table_refuses_not_steady_runs(limited_run):
    st = RunStatistics.from_json(limited_run[1] / "statistics.json")
    doc = {"runs": [json.loads(st.to_json())]}
    with pytest.raises(ValueError, match="refused"):
        StageParameterTable.model_validate(doc)
    assert StageParameterTable.model_validate({**doc, "allow_not_steady": True}).runs[0].outcome == st.outcome


def test_run_summary_names_outcome_window_and_the_statistic_that_set_the_window():
    from types import SimpleNamespace

    import pandas as pd

    from msmill.dem.mill.run import MillRun

    st = SimpleNamespace(mass_out_rate_kg_s=1.8, residence_time_s=1.25,
                         sampling_error_reached={"streams": 0.0123, "velocity": None})
    checks = [{"window_end_s": 3.0, "above_target": {"streams": 0.02, "velocity": None}},
              {"window_end_s": 3.5, "above_target": {}}]
    empty = pd.DataFrame()
    run = MillRun(scene=SimpleNamespace(feed_kg_s=2.0), settings=RunSettings(), events=empty, removed=empty,
                  timeseries=empty, snapshots=empty, steady_state_time_s=1.5, steady_state_detected_s=2.8,
                  window_s=(2.5, 3.5), wall_s=61.0, stats=SimpleNamespace(run=st),
                  extra={"window_checks": checks, "warm_start": {"placed_fraction": 0.97}}, outcome="steady")
    line = run.summary()
    assert line.startswith("steady, onset 1.5, detected 2.8, window 2.50-3.50 s, wall 61.0 s, out 0.90 of feed")
    assert "residence 1.25 s, warm placed 0.97, errors reached streams 0.012" in line
    assert "velocity" not in line.split("errors reached")[1].split(";")[0]  # not reached: left out
    assert line.endswith("2 checks, the last miss at 3.00 s: streams 0.020, velocity -")
    assert "wall 12.0 s" in run.summary(wall_s=12.0)
