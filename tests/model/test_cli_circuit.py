"""``msmill circuit``: the shipped example end to end, its sieve tables, one-line errors, nothing half-written."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from msmill.cli.main import run

pytestmark = pytest.mark.filterwarnings("ignore::UserWarning")

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "ug2_closed_circuit.toml"


def test_example_circuit_summary_and_tables(tmp_path, capsys):
    assert run(["circuit", str(EXAMPLE), "--out", str(tmp_path / "out"), "--band-samples", "16"]) == 0
    text = capsys.readouterr().out
    assert "circulating load 5-95 % band (%, 16 GP samples)" in text
    assert "product P80 5-95 % band" in text and "kWh/t" in text and "capacity" in text
    out = tmp_path / "out"
    streams = pd.read_csv(out / "streams.csv")
    assert set(streams["stream"]) == {"fresh_feed", "mill_product", "oversize", "undersize"}
    tph = dict(zip(streams["stream"], streams["tph"], strict=True))
    assert tph["undersize"] == pytest.approx(20.0, rel=1e-9)  # the product carries the fresh feed
    assert tph["mill_product"] == pytest.approx(tph["fresh_feed"] + tph["oversize"], rel=1e-9)
    for name, rate in tph.items():
        t = pd.read_csv(out / f"stream_{name}.csv")
        assert t["retained_tph"].sum() == pytest.approx(rate, rel=1e-9)
        assert t["retained_pct"].sum() == pytest.approx(100.0, rel=1e-9)
        assert (t["retained_pct"] >= 0).all() and np.all(np.diff(t["passing_pct"]) <= 1e-12)
        assert t["passing_pct"].iloc[0] == pytest.approx(100.0)  # the top sieve passes everything
        assert {4.75, 0.075} <= set(t["sieve_mm"])  # the standard sqrt(2) series
    band = pd.read_csv(out / "band_samples.csv")
    assert len(band) == 16 and band["circulating_load_pct"].std() > 0


@pytest.mark.parametrize("edit,field", [
    (lambda t: t.replace('d50c_mm = 6.0', 'd50c_mm = -6.0'), "units[2].d50c_mm"),
    (lambda t: t.replace('name = "screen"\ntype', 'name = "mill"\ntype'), "units[2].name"),
    (lambda t: t.replace('to = "product"', 'to = "nowhere"'), "streams[3].to"),
])
def test_bad_circuit_file_is_one_line_and_writes_nothing(tmp_path, capsys, edit, field):
    p = tmp_path / "c.toml"
    p.write_text(edit(EXAMPLE.read_text()), encoding="utf-8")
    assert run(["circuit", str(p), "--out", str(tmp_path / "out"), "--band-samples", "0"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and f"c.toml.{field}" in err and "\n" not in err
    assert not (tmp_path / "out").exists()


def test_band_samples_option_is_checked(tmp_path, capsys):
    shutil.copy(EXAMPLE, tmp_path / "c.toml")
    assert run(["circuit", str(tmp_path / "c.toml"), "--band-samples", "1"]) == 2
    assert "--band-samples" in capsys.readouterr().err
    assert not (tmp_path / "c_output").exists()
