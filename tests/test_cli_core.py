"""CLI tests of ``msmill ore``, ``msmill psd`` and ``msmill breakage`` (via run() + capsys)."""

from __future__ import annotations

import tomllib
from pathlib import Path

import pytest

from msmill.cli.main import run

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def _ok(capsys, argv):
    code = run(argv)
    out = capsys.readouterr()
    assert code == 0, out.err
    return out.out


def _bad(capsys, argv, field):
    code = run(argv)
    out = capsys.readouterr()
    assert code == 2
    lines = [ln for ln in out.err.splitlines() if ln.strip()]
    assert len(lines) == 1, out.err
    assert lines[0].startswith(f"error: {field}"), lines[0]
    return lines[0]


def test_ore_list(capsys):
    out = _ok(capsys, ["ore", "list"])
    assert "UG2" in out and "Platreef" in out and "71.8" in out and "0.5358" in out
    assert "DEFAULT" in out


def test_ore_show_flags_default_l_ref(capsys):
    out = _ok(capsys, ["ore", "show", "ug2"])
    assert "Table 1" in out
    assert "DEFAULT" in out and "not calibrated" in out
    assert "msmill ore calibrate" in out


def test_ore_show_unknown(capsys):
    _bad(capsys, ["ore", "show", "UG3"], "ore")


def test_ore_calibrate_example(capsys, tmp_path):
    out_toml = tmp_path / "ug2_cal.toml"
    out = _ok(capsys, ["ore", "calibrate", str(EXAMPLES / "dropweight_synthetic.csv"), "--ore", "UG2",
                       "--out", str(out_toml)])
    assert "l_ref_mm" in out and "fitted" in out and "R^2" in out and "residuals" in out
    data = tomllib.loads(out_toml.read_text())
    assert 18.0 < data["breakage"]["l_ref_mm"] < 22.0
    # the calibrated ore loads back and no longer reports a default L_ref
    out = _ok(capsys, ["ore", "show", str(out_toml)])
    assert "DEFAULT" not in out


def test_ore_calibrate_fit_ab(capsys):
    out = _ok(capsys, ["ore", "calibrate", str(EXAMPLES / "dropweight_synthetic.csv"), "--fit-ab",
                       "--l-ref-mm", "20", "--no-residuals"])
    assert "b_t_per_kwh" in out and "b/L_ref" in out


def test_ore_calibrate_bad_csv(capsys, tmp_path):
    p = tmp_path / "bad.csv"
    p.write_text("size_mm,ecs_kwh_t,t10_pct\n10,0.1,5\n10,0.2,150\n")
    _bad(capsys, ["ore", "calibrate", str(p)], "bad.csv.t10_pct[row 2]")
    _bad(capsys, ["ore", "calibrate", str(tmp_path / "missing.csv")], "path")
    _bad(capsys, ["ore", "calibrate", str(p), "--fit-a", "--fit-ab"], "--fit-a/--fit-ab")


def test_psd_stats(capsys):
    out = _ok(capsys, ["psd", "stats", str(EXAMPLES / "feed_example.csv"), "-p", "90"])
    assert "P50" in out and "P80" in out and "P90" in out
    assert "Rosin-Rammler" in out and "x63_mm = 15" in out and "Gates-Gaudin-Schuhmann" in out


def test_psd_stats_bad(capsys, tmp_path):
    p = tmp_path / "feed.csv"
    p.write_text("size_mm,passing_pct\n1,50\n2,40\n")
    _bad(capsys, ["psd", "stats", str(p)], "passing_pct")
    p.write_text("size,passing_pct\n1,50\n2,100\n")
    _bad(capsys, ["psd", "stats", str(p)], "columns")


def test_breakage_table(capsys):
    out = _ok(capsys, ["breakage", "table", "--ore", "UG2", "--size-mm", "10", "--velocity", "40",
                       "--breakage", "ab_t10"])
    # 40 m/s -> 800 J/kg = 0.2222 kWh/t; P_b = 1 - exp(-1.67*0.2222*10/29) = 0.1201; t10 = 8.625 %
    assert "800 J/kg" in out and "0.2222 kWh/t" in out
    assert "0.1201" in out and "8.625" in out
    assert "t75" in out and "fragment PSD" in out and "DEFAULT" in out


def _rows(out):
    rows = {}
    for line in out.splitlines():
        cells = [c.strip() for c in line.strip("│ ").split("│")]
        if len(cells) == 2:
            rows[cells[0]] = cells[1]
    return rows


def test_breakage_table_follows_the_default_submodels_convention(capsys):
    # issue 41: the default model (jk_t10) breaks a rock into fragments of t10 = A; the table printed A P_b
    from msmill.model.submodels import DEFAULTS

    assert DEFAULTS["breakage"] == "jk_t10"
    rows = _rows(_ok(capsys, ["breakage", "table", "--ore", "UG2", "--size-mm", "10", "--velocity", "40"]))
    assert rows["t10 = A (jk_t10, broken rock)"] == "71.8 %"
    assert rows["t10 of the population (broken and unbroken)"] == "8.625 %"  # A P_b: the JK law
    # the fragments printed are the model's own: jk_t10's column for this parent
    paper = _rows(_ok(capsys, ["breakage", "table", "--ore", "UG2", "--size-mm", "10", "--velocity", "40",
                               "--breakage", "ab_t10"]))
    p80 = lambda r: float(r["fragment P80 / P50"].split(" / ")[0])  # noqa: E731
    assert p80(rows) < 0.5 * p80(paper)  # t10 = 71.8 % is a much finer fragment PSD than 8.6 %
    _bad(capsys, ["breakage", "table", "--breakage", "vogel_swebrec"], "--breakage")


def test_breakage_table_energy_t10_uses_the_ores_fineness_ratio(capsys, own_ore_file):
    # x = 1.67 * 0.2222 * 10 / 29 = 0.12797; t10 = 71.8 (1 - exp(-0.1 x)) = 0.91296 %
    path = own_ore_file(fineness_ratio=0.1)
    from msmill.ore import Ore

    assert Ore.from_toml(path).fineness_ratio == 0.1 and Ore.from_toml(path).to_dict()["breakage"]["fineness_ratio"] == 0.1
    rows = _rows(_ok(capsys, ["breakage", "table", "--ore", str(path), "--size-mm", "10", "--velocity", "40",
                              "--breakage", "energy_t10"]))
    assert rows["t10 = A (1 - exp(-c x)), c = 0.1 (energy_t10, broken rock)"] == "0.913 %"
    out = _ok(capsys, ["breakage", "table", "--size-mm", "10", "--velocity", "40", "--breakage", "energy_t10"])
    assert "fineness ratio of UG2 is the default 1" in " ".join(out.split())  # said where the user looks


def test_breakage_table_caps_tn_at_100(capsys):
    """A hard impact: t10 = 71.8 % gives t2 = 19.6 t10^0.425 = 121 % and t4 = 3.75 t10^0.803 = 116 %.

    Both are shown capped at 100 %; t25 = 0.469 t10^1.027 = 37.8 % is below the cap.
    (200 m/s -> 20 kJ/kg = 5.556 kWh/t; P_b = 1 - exp(-1.67 x 5.556 x 40 / 29) = 1 - 3e-6.)
    """
    out = _ok(capsys, ["breakage", "table", "--ore", "UG2", "--size-mm", "40", "--velocity", "200"])
    rows = _rows(out)
    assert rows["t10 = A (jk_t10, broken rock)"] == "71.8 %"
    assert 19.6 * 71.8**0.425 > 120 and 3.75 * 71.8**0.803 > 115
    assert rows["t2"] == "100 %" and rows["t4"] == "100 %"
    # the packaged fit's constants agree with the rounded (0.469, 1.027) to 5e-3
    assert float(rows["t25"].removesuffix(" %")) == pytest.approx(0.469 * 71.8**1.027, rel=5e-3)


def test_breakage_table_custom_grid(capsys):
    out = _ok(capsys, ["breakage", "table", "--ore", "platreef", "--size-mm", "20", "--velocity", "60",
                       "--grid-min-mm", "0.5", "--grid-max-mm", "40"])
    assert "Platreef" in out


@pytest.mark.parametrize(
    ("argv", "field"),
    [
        (["--velocity", "-1"], "--velocity"),
        (["--size-mm", "0"], "--size-mm"),
        (["--grid-min-mm", "50"], "--grid-min-mm"),
        (["--grid-max-mm", "5"], "--grid-max-mm"),
        (["--damage", "1.5"], "--damage"),
        (["--ore", "nope"], "ore"),
    ],
)
def test_breakage_table_bad_input(capsys, argv, field):
    _bad(capsys, ["breakage", "table", *argv], field)
