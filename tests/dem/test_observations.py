"""The paper's observations as statistical statements (msmill.dem.mill.observations) on synthetic runs."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from msmill.dem.mill.observations import (
    Z_AGREE,
    RunStreams,
    evaluate,
    group_mean,
    leave_one_seed_out,
    pick_default,
    read_study,
    refeed_falls_with_size,
    report_lines,
    run_dir_name,
    scatter_over_error,
    stage_stream,
    stream_table_lines,
    top_least_kickback,
)
from msmill.errors import MsmillInputError

SIZES = (10.0, 20.0, 30.0)
SPEEDS = (1250.0, 1850.0)
OFFSETS = (-0.01, 0.0, 0.01)  # per-seed offsets: between-seed sd 0.01


def _run(config: str, size: float, rpm: float, seed: int, paper_like: bool, se: float = 0.002) -> RunStreams:
    """Five stages whose streams follow (or reverse) the paper's three observations exactly, plus a seed offset."""
    d = OFFSETS[seed]
    x = math.log2(size / 20.0)
    if paper_like:
        kick = [0.05, 0.30, 0.28, 0.25, 0.20]
        passing = 0.30 + (0.20 if rpm > 1500 else 0.0)
        refeed1 = 0.40 - 0.20 * x
    else:
        kick = [0.30, 0.10, 0.12, 0.15, 0.20]
        passing = 0.50 - (0.20 if rpm > 1500 else 0.0)
        refeed1 = 0.40 + 0.20 * x
    streams = []
    for s in range(5):
        k = kick[s] + d
        p = passing + d if s else 1.0 - k - refeed1 - d
        streams.append([k, 1.0 - k - p, p])
    streams[0] = [kick[0] + d, refeed1 + d, 1.0 - kick[0] - refeed1 - 2 * d]
    return RunStreams(config, size, rpm, seed, np.array(streams), np.full((5, 3), se))


def _study(se: float = 0.002) -> list[RunStreams]:
    return [_run(c, size, rpm, seed, c == "paper", se=se) for c in ("paper", "reversed") for size in SIZES
            for rpm in SPEEDS for seed in range(3)]


def test_group_mean_takes_the_larger_of_scatter_and_sampling_error():
    q = stage_stream("kickback", 1)
    spread = [RunStreams("c", 20, 1250, i, np.array([[v, 0.5, 0.5 - v]] * 2), np.full((2, 3), 0.01))
              for i, v in enumerate((0.1, 0.3))]
    g = group_mean(spread, q)
    assert g.value == pytest.approx(0.2)
    assert g.between_sd == pytest.approx(math.sqrt(0.02))
    assert g.se == pytest.approx(0.1)  # sqrt(0.02 / 2): the scatter dominates
    tight = [RunStreams("c", 20, 1250, i, np.array([[0.2, 0.5, 0.3]] * 2), np.full((2, 3), 0.05)) for i in range(2)]
    assert group_mean(tight, q).se == pytest.approx(0.05 / math.sqrt(2))  # the sampling error dominates
    one = group_mean(tight[:1], q)  # one seed: its sampling error alone
    assert (one.value, one.se, one.n) == (pytest.approx(0.2), pytest.approx(0.05), 1)
    assert math.isnan(one.between_sd)


def test_paper_like_runs_agree_and_reversed_ones_disagree():
    verdicts = evaluate(_study())
    good, bad = verdicts["paper"], verdicts["reversed"]
    assert all(s.agrees for s in good.statements.values())
    assert not any(s.agrees for s in bad.statements.values())
    assert all(s.signed_z < -Z_AGREE for s in bad.statements.values())
    # the effects are the ones built in
    tk = good.statements["top_least_kickback"]
    assert tk.decision.effect == pytest.approx(0.15)  # stage 5 (0.20) is the closest to stage 1 (0.05)
    assert good.statements["pass_rises_with_speed"].decision.effect == pytest.approx(0.20 * 4 / 5)  # stage 1 fixed
    assert good.statements["refeed_falls_with_size"].decision.effect == pytest.approx(-0.20)
    assert pick_default(verdicts).config == "paper"
    lines = report_lines(verdicts)
    assert lines[-1] == "default=paper agreeing=3/3"
    assert ("config=reversed top_least_kickback=disagree pass_rises_with_speed=disagree "
            "refeed_falls_with_size=disagree") in lines


def test_a_trend_with_the_paper_sign_but_within_the_noise_does_not_agree():
    verdicts = evaluate(_study(se=0.4))  # sampling errors of 0.4 per run: the built-in trends are not significant
    st = verdicts["paper"].statements["refeed_falls_with_size"]
    assert st.decision.effect == pytest.approx(-0.20)
    assert 0 < st.signed_z < Z_AGREE
    assert not st.agrees


def test_stage_one_must_be_below_every_other_stage():
    runs = [_run("paper", size, rpm, seed, True) for size in SIZES for rpm in SPEEDS for seed in range(3)]
    # stage 4 now kicks back less than stage 1 at every point
    low4 = []
    for r in runs:
        s = r.streams.copy()
        s[3] = [0.01, s[3, 1] + s[3, 0] - 0.01, s[3, 2]]
        low4.append(RunStreams(r.config, r.size_mm, r.speed_rpm, r.seed, s, r.sampling_se))
    st = top_least_kickback(low4)
    assert not st.agrees
    assert st.decision is st.details["stage4"]
    assert st.decision.effect == pytest.approx(-0.04)


def test_refeed_slope_with_two_sizes_and_bad_input():
    runs = [_run("paper", size, 1250.0, seed, True) for size in (10.0, 30.0) for seed in range(2)]
    st = refeed_falls_with_size(runs)
    assert st.decision.effect == pytest.approx(-0.20)
    with pytest.raises(MsmillInputError, match="stream"):
        stage_stream("kick", 1)
    with pytest.raises(MsmillInputError, match="two rock sizes"):
        refeed_falls_with_size(runs[:2])
    with pytest.raises(MsmillInputError, match="streams"):
        RunStreams("c", 20, 1250, 0, np.zeros((5, 2)), np.zeros((5, 2)))


def test_read_study_from_exports(tmp_path):
    for r in _study():
        d = tmp_path / r.config / run_dir_name(r.size_mm, r.speed_rpm, r.seed)
        d.mkdir(parents=True)
        stages = [{"stage": i + 1, **dict(zip(("kickback", "refeed", "pass_through"), row, strict=True)),
                   "sampling_error": {"kickback": 0.002, "refeed": 0.002, "pass_through": 0.002}}
                  for i, row in enumerate(r.streams.tolist())]
        (d / "statistics.json").write_text(json.dumps({"design": {"size_mm": r.size_mm, "speed_rpm": r.speed_rpm},
                                                       "stages": stages[::-1], "outcome": "steady"}))
        (d / "provenance.json").write_text(json.dumps({"config": r.config, "inputs": {"seed": r.seed}}))
    (tmp_path / "paper" / "10mm_1250rpm_seed9.partial").mkdir()
    runs = read_study(tmp_path)
    assert len(runs) == 36
    assert report_lines(evaluate(runs))[-1] == "default=paper agreeing=3/3"
    with pytest.raises(MsmillInputError, match="root"):
        read_study(tmp_path / "missing")


def test_stream_table_has_one_row_per_point():
    lines = stream_table_lines(_study())
    assert len(lines) == 2 + 2 * len(SIZES) * len(SPEEDS)
    row = next(ln for ln in lines if ln.startswith("| paper | 10 | 1850 | 3 |"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[4:9] == ["0.05", "0.30", "0.28", "0.25", "0.20"]  # kickback per stage
    assert cells[14] == "0.60"  # stage-1 refeed at 10 mm: 0.40 + 0.20


def test_leave_one_seed_out_keeps_the_pick():
    assert leave_one_seed_out(_study()) == {0: ("paper", 3), 1: ("paper", 3), 2: ("paper", 3)}


def test_ties_go_to_the_configuration_whose_runs_stay_steady():
    runs = _study()
    same = [RunStreams("choking", r.size_mm, r.speed_rpm, r.seed, r.streams, r.sampling_se,
                       outcome="choked" if (r.size_mm, r.seed) == (30.0, 2) else "steady")
            for r in runs if r.config == "paper"]
    verdicts = evaluate(runs + same)
    assert verdicts["choking"].agreeing == verdicts["paper"].agreeing == 3
    assert verdicts["choking"].n_excluded == 2
    assert pick_default(verdicts).config == "paper"
    assert pick_default({"choking": verdicts["choking"]}).config == "choking"


def test_scatter_over_error_is_the_seed_sd_over_the_reported_error():
    ratio = scatter_over_error(_study())  # seed offsets -0.01, 0, 0.01 (sd 0.01) against errors 0.002
    assert ratio["kickback"] == (pytest.approx(5.0), 2 * len(SIZES) * len(SPEEDS) * 5)
