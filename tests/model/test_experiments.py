"""Experiment / survey files: round trip and one-line errors naming the file and the field."""

from __future__ import annotations

import tomllib
import warnings

import numpy as np
import pytest
import tomli_w

from msmill.cli.main import run
from msmill.errors import MsmillInputError, OutOfDomainWarning
from msmill.model.experiments import read_experiment, read_experiments, write_experiment

SURVEY = {
    "kind": "survey", "id": "s1", "ore": "UG2", "source": "SYNTHETIC test survey",
    "feed": {"rate_tph": 30.0, "size_mm": [2.0, 4.75, 9.5, 19.0, 31.5], "passing_pct": [2.0, 6.0, 18.0, 58.0, 100.0]},
    "operating": {"speed_rpm": 1500.0, "bottom_speed_factor": 2.0, "gate_deg": 40.0},
    "product": {"size_mm": [0.075, 0.6, 2.36, 9.5, 19.0, 31.5], "passing_pct": [1.0, 5.0, 15.0, 50.0, 85.0, 100.0]},
    "measured": {"power_kw": 40.0},
}
IMPACT = {
    "kind": "single_impact", "id": "t1", "ore": "Platreef", "source": "SYNTHETIC test", "impact_speed_m_s": 25.0,
    "feed": {"size_mm": [13.2, 16.0], "passing_pct": [0.0, 100.0]},
    "product": {"size_mm": [0.6, 2.36, 9.5, 13.2, 16.0], "passing_pct": [2.0, 6.0, 20.0, 40.0, 100.0]},
}


def write(tmp_path, name, doc):
    p = tmp_path / name
    p.write_text(tomli_w.dumps(doc), encoding="utf-8")
    return p


@pytest.mark.parametrize("doc", [SURVEY, IMPACT], ids=["survey", "single_impact"])
def test_round_trip(tmp_path, doc):
    e = read_experiment(write(tmp_path, "a.toml", doc))
    out = write_experiment(e, tmp_path / "b.toml")
    again = read_experiment(out)
    assert tomllib.loads(out.read_text()) == doc
    assert again.to_dict() == e.to_dict() == doc
    assert np.allclose(again.product_psd.passing_pct, e.product_psd.passing_pct)
    table = dict(zip(doc["product"]["size_mm"], doc["product"]["passing_pct"], strict=True))
    assert again.product_psd.passing_at(9.5) == pytest.approx(table[9.5])


def test_survey_fields(tmp_path):
    e = read_experiment(write(tmp_path, "a.toml", SURVEY))
    assert (e.kind, e.feed_tph, e.power_kw) == ("survey", 30.0, 40.0)
    assert e.operating_point().stage_speeds(5) == [1500.0] * 4 + [3000.0]


def _bad(doc, path, value):
    d = {k: (dict(v) if isinstance(v, dict) else v) for k, v in doc.items()}
    *head, last = path
    tgt = d
    for k in head:
        tgt = tgt[k]
    if value is None:
        del tgt[last]
    else:
        tgt[last] = value
    return d


@pytest.mark.parametrize(("path", "value", "field"), [
    (("feed", "rate_tph"), -3.0, "bad.toml.feed.rate_tph"),
    (("product",), None, "bad.toml.product"),
    (("ore",), "UG3", "bad.toml.ore"),
    (("kind",), "plant", "bad.toml.kind"),
    (("product", "passing_pct"), [1.0, 5.0, 15.0, 10.0, 85.0, 100.0], "bad.toml.product"),
    (("product", "size_mm"), [0.075, 0.6, 2.36], "bad.toml.product"),
    (("operating", "gate_deg"), 95.0, "bad.toml.operating.gate_deg"),
    (("colour",), "red", "bad.toml.colour"),
])
def test_errors_name_file_and_field(tmp_path, path, value, field):
    p = write(tmp_path, "bad.toml", _bad(SURVEY, path, value))
    with pytest.raises(MsmillInputError) as exc:
        read_experiment(p)
    msg = str(exc.value)
    assert msg.startswith(field), msg
    assert "\n" not in msg


def test_folder_errors(tmp_path):
    with pytest.raises(MsmillInputError, match="folder"):
        read_experiments(tmp_path)  # empty
    write(tmp_path, "a.toml", SURVEY)
    write(tmp_path, "b.toml", SURVEY)
    with pytest.raises(MsmillInputError, match=r"b\.toml\.id"):
        read_experiments(tmp_path)


def test_cli_bad_file_exits_2_one_line(tmp_path, capsys):
    write(tmp_path, "bad.toml", _bad(SURVEY, ("feed", "rate_tph"), -3.0))
    assert run(["validate", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: bad.toml.feed.rate_tph")


def test_outside_design_space_warns(tmp_path):
    p = write(tmp_path, "a.toml", _bad(SURVEY, ("operating", "speed_rpm"), 2100.0))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        read_experiment(p)
    assert any(issubclass(w.category, OutOfDomainWarning) for w in caught)


def test_product_from_csv_file(tmp_path):
    (tmp_path / "prod.csv").write_text("# SYNTHETIC\nsize_mm,passing_pct\n0.075,1\n0.6,5\n2.36,15\n9.5,50\n"
                                       "19,85\n31.5,100\n", encoding="utf-8")
    doc = {**SURVEY, "product": {"file": "prod.csv"}}
    e = read_experiment(write(tmp_path, "a.toml", doc))
    inline = read_experiment(write(tmp_path, "b.toml", SURVEY))
    assert np.allclose(e.product_psd.passing_pct, inline.product_psd.passing_pct)
    with pytest.raises(MsmillInputError, match=r"^c\.toml\.product\.file"):
        read_experiment(write(tmp_path, "c.toml", {**SURVEY, "product": {"file": "missing.csv"}}))
