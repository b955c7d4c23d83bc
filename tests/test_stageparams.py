import json

import pytest

from msmill.errors import MsmillInputError
from msmill.stageparams import GaussianMixture, RunStatistics


def _stage(i, kick=0.1, refeed=0.5, pt=0.4):
    return {
        "stage": i,
        "kickback": kick,
        "refeed": refeed,
        "pass_through": pt,
        "primary_hit_probability": 0.3,
        "primary_velocity": {"weights": [1.0], "means_m_s": [30.0], "sigmas_m_s": [3.0]},
        "secondary_lambda": 2.0,
        "secondary_velocity": {"weights": [0.6, 0.4], "means_m_s": [2.0, 9.0], "sigmas_m_s": [1.0, 2.0]},
    }


def _run(**over):
    d = {
        "design": {"size_mm": 10, "feed_tph": 30, "speed_rpm": 1500, "gate_deg": 40,
                   "stage_speeds_rpm": [1500, 3000]},
        "characteristic_time_s": 0.06,
        "stages": [_stage(1), _stage(2)],
    }
    d.update(over)
    return d


def test_round_trip(tmp_path):
    rs = RunStatistics.from_dict(_run())
    p = tmp_path / "s.json"
    rs.to_json(p)
    again = RunStatistics.from_json(p)
    assert again == rs
    assert again.n_stages == 2


def test_streams_must_sum_to_one():
    bad = _run(stages=[_stage(1, 0.2, 0.5, 0.4), _stage(2)])
    with pytest.raises(MsmillInputError, match=r"stages\.0.*must be 1"):
        RunStatistics.from_dict(bad)


def test_schema_version_checked():
    with pytest.raises(MsmillInputError, match="schema_version"):
        RunStatistics.from_dict({**_run(), "schema_version": 99})


def test_stage_numbering_and_speed_count():
    with pytest.raises(MsmillInputError, match="numbered"):
        RunStatistics.from_dict(_run(stages=[_stage(2), _stage(1)]))
    with pytest.raises(MsmillInputError, match="one speed per stage"):
        RunStatistics.from_dict(_run(stages=[_stage(1)]))


def test_bad_json_is_one_line(tmp_path):
    p = tmp_path / "bad.json"
    p.write_text("{not json")
    with pytest.raises(MsmillInputError) as info:
        RunStatistics.from_json(p)
    assert "\n" not in str(info.value)


def test_mixture_pdf_integrates_to_one():
    import numpy as np

    gm = GaussianMixture(weights=[0.3, 0.7], means_m_s=[5, 20], sigmas_m_s=[1, 4])
    v = np.linspace(-20, 60, 20001)
    assert np.trapezoid(gm.pdf(v), v) == pytest.approx(1.0, abs=1e-6)
    assert gm.mean() == pytest.approx(0.3 * 5 + 0.7 * 20)
    with pytest.raises(ValueError):
        GaussianMixture(weights=[0.5, 0.6], means_m_s=[1, 2], sigmas_m_s=[1, 1])
    json.dumps(gm.model_dump())


def test_table_sizes_ascending_and_round_trip(tmp_path):
    from msmill.stageparams import StageParameterTable

    r1 = _run()
    r2 = _run()
    r2["design"] = {**r2["design"], "size_mm": 20}
    t = StageParameterTable(runs=[RunStatistics.from_dict(r1), RunStatistics.from_dict(r2)])
    p = tmp_path / "t.json"
    t.to_json(p)
    assert StageParameterTable.from_json(p) == t
    assert list(t.sizes_mm) == [10, 20]
    with pytest.raises(ValueError, match="ascending"):
        StageParameterTable(runs=[RunStatistics.from_dict(r2), RunStatistics.from_dict(r1)])


def test_design_inputs_are_size_feed_speed_gate_for_runs_and_any_point_with_the_fields():
    import numpy as np

    from msmill.stageparams import DESIGN_INPUTS, DesignPoint, design_inputs
    from msmill.surrogate.capacity import EnvelopePoint

    d = DesignPoint(size_mm=4.5, feed_tph=20.0, speed_rpm=1500.0, gate_deg=30.0, stage_speeds_rpm=[1500.0, 1400.0])
    assert DESIGN_INPUTS == ("size_mm", "feed_tph", "speed_rpm", "gate_deg")
    assert d.inputs() == (4.5, 20.0, 1500.0, 30.0)
    e = EnvelopePoint.from_statistics(RunStatistics.from_dict(_run()))
    X = design_inputs([d, e])
    assert X.shape == (2, 4) and X[0].tolist() == [4.5, 20.0, 1500.0, 30.0]
    assert X[1].tolist() == [getattr(e, k) for k in DESIGN_INPUTS]
    assert design_inputs([]).shape == (0, 4) and np.issubdtype(design_inputs([]).dtype, np.floating)
