"""``msmill predict``: run files validated up front, one-line errors, nothing half-written."""

from __future__ import annotations

import re

import pytest
from synthetic import synthetic_table

from msmill.cli.main import run

pytestmark = pytest.mark.filterwarnings("ignore::msmill.errors.OutOfDomainWarning")

GOOD = """
title = "SYNTHETIC"
[ore]
name = "UG2"
[feed]
rate_tph = 30.0
size_mm = [4.75, 9.5, 19.0, 37.5, 45.0]
passing_pct = [3.0, 12.0, 45.0, 92.0, 100.0]
[operating]
speed_rpm = 1500.0
gate_deg = 40.0
[stage_parameters]
file = "table.json"
[output]
dir = "out"
plots = false
"""


@pytest.fixture
def folder(tmp_path):
    synthetic_table().to_json(tmp_path / "table.json")
    return tmp_path


def write(folder, text, name="run.toml"):
    p = folder / name
    p.write_text(text, encoding="utf-8")
    return p


def test_predict_writes_outputs(folder, capsys):
    p = write(folder, GOOD.replace("plots = false", "plots = true"))
    assert run(["predict", str(p)]) == 0
    out = folder / "out"
    names = {f.name for f in out.iterdir()}
    assert {"product.csv", "product_timeseries.csv", "product_stages.csv", "product_psd.png",
            "product_timeseries.png"} <= names
    text = (out / "product.csv").read_text()
    assert text.splitlines()[0].startswith("lower_mm,upper_mm,mid_mm,feed_mass_fraction")
    assert "reduction ratio" in capsys.readouterr().out


@pytest.mark.parametrize("old,new,field", [
    ("rate_tph = 30.0", "rate_tph = -3.0", "run.toml.feed.rate_tph"),
    ('name = "UG2"', 'name = "UG3"', "run.toml.ore.name"),
    ("gate_deg = 40.0", "gate_deg = 140.0", "run.toml.operating.gate_deg"),
    ('file = "table.json"', 'file = "missing.json"', "run.toml.stage_parameters.file"),
    ("[output]", '[model]\ndamage = "tavaress"\n[output]', "run.toml.model.damage"),
    ("[output]", '[model]\nsolver = "montecarlo"\n[output]', "run.toml.model.solver"),
    ("[output]", "[model]\ndamage_clases = 4\n[output]", "run.toml.model.damage_clases"),
    ("passing_pct = [3.0, 12.0, 45.0, 92.0, 100.0]", "passing_pct = [3.0, 12.0, 45.0, 30.0, 100.0]",
     "run.toml.feed.passing_pct"),
    ("speed_rpm = 1500.0", "stage_speeds_rpm = [1500.0, 3000.0]", "run.toml.operating.stage_speeds_rpm"),
])
def test_bad_run_file_is_one_line_and_writes_nothing(folder, capsys, old, new, field):
    assert old in GOOD
    p = write(folder, GOOD.replace(old, new))
    assert run(["predict", str(p)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    errors = [e for e in err if e.startswith("error:")]
    assert len(errors) == 1, err
    assert errors[0].startswith(f"error: {field}"), errors[0]
    assert not (folder / "out").exists()


def test_bad_toml_and_missing_file(folder, capsys):
    p = write(folder, "title = ")
    assert run(["predict", str(p)]) == 2
    assert run(["predict", str(folder / "nope.toml")]) == 2
    err = capsys.readouterr().err
    assert "valid TOML" in err and "existing TOML file" in err


def test_default_table_missing_is_one_line(folder, capsys, monkeypatch):
    import importlib.resources

    # pretend the package data lives in an empty folder: the packaged table is missing
    monkeypatch.setattr(importlib.resources, "files", lambda _pkg: folder / "no-package-data")
    p = write(folder, GOOD.replace('file = "table.json"', 'file = "default"'))
    assert run(["predict", str(p)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "stage_parameters.file" in err[0] and "not installed" in err[0], err


def test_rosin_rammler_feed_and_solver_override(folder):
    text = GOOD.replace("size_mm = [4.75, 9.5, 19.0, 37.5, 45.0]\npassing_pct = [3.0, 12.0, 45.0, 92.0, 100.0]",
                        "[feed.rosin_rammler]\nsize_63_mm = 20.0\nspread = 1.5\ntop_mm = 45.0")
    text = text.replace("[operating]", "\n[operating]")
    p = write(folder, text)
    assert run(["predict", str(p), "--out", str(folder / "o2")]) == 0
    assert (folder / "o2" / "product.csv").is_file()


@pytest.mark.parametrize("name", ["ug2.toml", "platreef.toml"])
def test_examples_validate(name, tmp_path):
    """The shipped examples parse and run on the shipped DEM-derived default table."""
    from pathlib import Path

    from msmill.model.runfile import RunFile

    path = Path(__file__).parents[2] / "examples" / name
    rf = RunFile.from_toml(path)
    assert rf.feed_psd().p80_mm > 1.0
    assert rf.stage_parameters.file == "default"
    assert run(["predict", str(path), "--out", str(tmp_path), "--no-plots"]) == 0


def test_bad_table_file_error_names_the_table_field(folder, capsys):
    import json

    data = json.loads((folder / "table.json").read_text())
    data["runs"][0]["stages"][1]["refeed"] = 0.9
    (folder / "table.json").write_text(json.dumps(data))
    p = write(folder, GOOD)
    assert run(["predict", str(p)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: table.json.runs.0.stages.1"), err
    assert len(err.splitlines()) == 1


def test_predict_warns_above_capacity_from_envelope(folder, capsys):
    import warnings

    from msmill.surrogate.capacity import AboveCapacityWarning, EnvelopeData, EnvelopePoint

    # SYNTHETIC envelope: at every size the mill passes 15 t/h and chokes at 25-40 t/h, passing 20 t/h
    pts = [EnvelopePoint(s, f, 1500.0, 40.0, "steady") for s in (10, 20, 30, 40) for f in (10.0, 15.0)]
    pts += [EnvelopePoint(s, f, 1500.0, 40.0, "choked", 20.0) for s in (10, 20, 30, 40) for f in (25.0, 40.0)]
    EnvelopeData(pts, {"note": "SYNTHETIC"}).to_json(folder / "envelope.json")
    p = write(folder, GOOD)
    capsys.readouterr()
    assert run(["predict", str(p), "--envelope", str(folder / "envelope.json")]) == 0
    err = capsys.readouterr().err  # the CLI prints each warning once as a 'warning:' line
    assert "warning:" in err and "above the predicted capacity" in err
    assert run(["predict", str(p), "--envelope", str(folder / "envelope.json"), "--no-capacity-check"]) == 0
    assert "above the predicted capacity" not in capsys.readouterr().err  # switched off
    low = write(folder, GOOD.replace("rate_tph = 30.0", "rate_tph = 12.0"), "low.toml")
    assert run(["predict", str(low), "--envelope", str(folder / "envelope.json")]) == 0
    assert "above the predicted capacity" not in capsys.readouterr().err
    with pytest.warns(AboveCapacityWarning, match="above the predicted capacity"):  # the library warns
        from msmill.surrogate.capacity import CapacityModel, warn_if_above_capacity

        warn_if_above_capacity(CapacityModel.fit(pts), 20.0, 30.0, 1500.0, 40.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error", AboveCapacityWarning)
        warn_if_above_capacity(CapacityModel.fit(pts), 20.0, 12.0, 1500.0, 40.0)


def test_predict_with_an_envelope_of_steady_runs_only(folder, capsys):
    """HAND-MADE envelope where no run choked: the summary gives a lower bound, and above it a warning."""
    from msmill.surrogate.capacity import EnvelopeData, EnvelopePoint

    pts = [EnvelopePoint(s, 20.0, 1500.0, 30.0, "steady") for s in (10, 20, 30, 40)]
    EnvelopeData(pts, {"note": "HAND-MADE"}).to_json(folder / "envelope.json")
    p = write(folder, GOOD)
    capsys.readouterr()
    assert run(["predict", str(p), "--envelope", str(folder / "envelope.json")]) == 0
    cap = capsys.readouterr()
    assert "feed the DEM has shown the mill to pass" in cap.err and "unknown" in cap.err
    # F80 lies between two runs' sizes, within a factor sqrt(2) of one: the bound is 20 t/h halved at most
    # 0.43 times, 14.8-20 t/h
    assert re.search(r">= 1[4-9]\.?\d* ", cap.out) and "lower bound, no run choked" in cap.out
    low = write(folder, GOOD.replace("rate_tph = 30.0", "rate_tph = 12.0"), "low.toml")
    assert run(["predict", str(low), "--envelope", str(folder / "envelope.json")]) == 0
    cap = capsys.readouterr()
    assert "feed the DEM has shown" not in cap.err and re.search(r">= 1[4-9]\.?\d* ", cap.out)



def test_predict_with_a_users_ore_file(folder, own_ore_file):
    import pandas as pd

    p = write(folder, GOOD)
    assert run(["predict", str(p), "--out", str(folder / "a")]) == 0
    # a much weaker rock (L_ref 5 mm against UG2's default): the --ore-file replaces the run file's [ore]
    assert run(["predict", str(p), "--out", str(folder / "b"), "--ore-file", str(own_ore_file(l_ref_mm=5.0))]) == 0
    a, b = (pd.read_csv(folder / d / "product.csv") for d in ("a", "b"))
    fine = a["upper_mm"] <= 1.0
    assert b.loc[fine, "product_mass_fraction"].sum() > 1.2 * a.loc[fine, "product_mass_fraction"].sum()
