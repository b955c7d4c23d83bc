"""CLI of the practitioner workflow on the shipped SYNTHETIC example experiments."""

from __future__ import annotations

import shutil
from pathlib import Path

import pandas as pd
import pytest

from msmill.cli.main import run
from msmill.ore import Ore

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "examples" / "experiments"


def test_validate_examples_writes_tables_and_figures(tmp_path, capsys):
    assert run(["validate", str(EXAMPLES), "--out", str(tmp_path)]) == 0
    names = {p.name for p in tmp_path.iterdir()}
    assert {"ks_by_experiment.csv", "ks_by_ore.csv", "ks_swarm.png", "overlay_UG2_best.png",
            "overlay_Platreef_worst.png"} <= names
    t = pd.read_csv(tmp_path / "ks_by_experiment.csv")
    assert len(t) == 15 and t["ks"].between(0, 1).all()
    assert t.loc[t["id"] == "ug2-p5-coarse", "outside_design_space"].item()
    assert "no-load" in capsys.readouterr().out


def test_calibrate_small_set_writes_calibrated_ore(tmp_path, capsys):
    data = tmp_path / "data"
    data.mkdir()
    for p in [*sorted(EXAMPLES.glob("ug2-p[12]-*.toml")), *sorted(EXAMPLES.glob("ug2-lab-13x16-*.toml"))]:
        shutil.copy(p, data / p.name)
    out = tmp_path / "out"
    # without posterior samples the s.e. is the surveys' scatter only, and the summary says so
    assert run(["calibrate", str(data), "--out", str(out), "--stage-samples", "0"]) == 0
    ore = Ore.from_toml(out / "UG2_calibrated.toml")
    assert not ore.l_ref_is_default
    assert abs(ore.l_ref_mm - 20.0) < 2.0  # the synthetic truth (examples/experiments/PROVENANCE.json)
    assert "msmill calibrate" in ore.sources["l_ref"]
    text = capsys.readouterr().out
    assert "fits better" in text and "leave-one-survey-out" in text
    assert "surveys' scatter only" in " ".join(text.split())
    assert (out / "impact_fits.csv").is_file()


def test_calibrate_bad_fit_name_exits_2(tmp_path, capsys):
    data = tmp_path / "data"
    data.mkdir()
    for p in sorted(EXAMPLES.glob("ug2-p1-*.toml")):
        shutil.copy(p, data / p.name)
    assert run(["calibrate", str(data), "--fit", "colour"]) == 2
    assert capsys.readouterr().err.startswith("error: fit")
    assert run(["calibrate", str(data), "--stage-samples", "1"]) == 2
    assert capsys.readouterr().err.startswith("error: --stage-samples")


def test_sweep_and_optimize(tmp_path, capsys):
    from msmill.model.runfile import RunFile

    # the example pinned to the single-point table (this test checks the tools, not the surrogate's trends)
    text = (ROOT / "examples" / "ug2.toml").read_text(encoding="utf-8")
    run_file = tmp_path / "ug2.toml"
    run_file.write_text(text.replace('file = "default"', 'file = "table"'), encoding="utf-8")
    assert run(["sweep", str(run_file), "--var", "speed_rpm=1300:1700:3", "--out", str(tmp_path / "s")]) == 0
    t = pd.read_csv(tmp_path / "s" / "sweep.csv")
    assert t["p80_mm"].is_monotonic_decreasing and t["specific_energy_kwh_t"].is_monotonic_increasing
    mill, feed, op = RunFile.from_toml(run_file).build()
    target = mill.run(feed, op.model_copy(update={"speed_rpm": 1600.0}), timeseries=False).p80_mm  # reachable
    assert run(["optimize", str(run_file), "--bound", "speed_rpm=1200:1900", "--goal", "min_energy",
                "--target-p80-mm", f"{target:.4f}", "--n-grid", "4", "--l-ref-se-mm", "3",
                "--out", str(tmp_path / "o")]) == 0
    assert "best (min_energy" in capsys.readouterr().out
    assert (tmp_path / "o" / "pareto.png").is_file()
    sens = pd.read_csv(tmp_path / "o" / "optimum_sensitivity.csv")
    # a smaller L_ref breaks more easily, so the target is reached at a lower speed
    assert sens["speed_rpm"].is_monotonic_increasing and sens["speed_rpm"].nunique() == 3
    assert run(["sweep", str(run_file), "--var", "colour=1:2"]) == 2
    capsys.readouterr()
    # a target out of reach says what the bounds reach; an optimum on a bound says so
    assert run(["optimize", str(run_file), "--bound", "speed_rpm=1200:1900", "--goal", "min_energy",
                "--target-p80-mm", "0.5", "--n-grid", "3", "--out", str(tmp_path / "o2")]) == 0
    out = capsys.readouterr().out
    assert "no setting within the bounds reaches P80 <= 0.5 mm" in out and "the closest: P80" in out
    assert "speed_rpm = 1900" in out
    assert run(["optimize", str(run_file), "--bound", "speed_rpm=1200:1900", "--goal", "min_energy",
                "--target-p80-mm", "1000", "--n-grid", "3", "--out", str(tmp_path / "o3")]) == 0
    assert "the optimum sits on a bound: speed_rpm at its low bound 1200" in capsys.readouterr().out


def test_sweep_and_optimize_respect_the_envelope(tmp_path, capsys):
    from msmill.surrogate.capacity import CapacityModel, EnvelopePoint

    # HAND-MADE envelope: 15 t/h passed, 25 and 40 t/h choked passing 20 t/h, at 10-30 mm, 1500 rpm, gate 40
    pts = [EnvelopePoint(s, f, 1500.0, 40.0, "steady") for s in (10, 20, 30) for f in (10.0, 15.0)]
    pts += [EnvelopePoint(s, f, 1500.0, 40.0, "choked", 20.0) for s in (10, 20, 30) for f in (25.0, 40.0)]
    cap = CapacityModel.fit(pts)
    cap.to_envelope(pts, {"note": "HAND-MADE"}).to_json(tmp_path / "env.json")
    text = (ROOT / "examples" / "ug2.toml").read_text(encoding="utf-8")
    run_file = tmp_path / "ug2.toml"
    run_file.write_text(text.replace('file = "default"', 'file = "table"'), encoding="utf-8")
    assert run(["sweep", str(run_file), "--var", "feed_tph=10:40:4", "--envelope", str(tmp_path / "env.json"),
                "--out", str(tmp_path / "s")]) == 0
    assert "2 of 4 points above it" in capsys.readouterr().out
    t = pd.read_csv(tmp_path / "s" / "sweep.csv")
    assert list(t["above_capacity"]) == [False, False, True, True] and list(t["feasible"]) == [True, True, False, False]
    assert run(["optimize", str(run_file), "--bound", "feed_tph=10:40", "--target-p80-mm", "1000", "--n-grid", "4",
                "--envelope", str(tmp_path / "env.json"), "--out", str(tmp_path / "o")]) == 0
    best = pd.read_csv(tmp_path / "o" / "candidates.csv").query("meets_target")["feed_tph"].max()
    assert 19 < best <= cap.capacity_tph(24.3, 1500.0, 40.0) + 0.1
    assert run(["sweep", str(run_file), "--var", "feed_tph=10:40:4", "--no-capacity-check",
                "--out", str(tmp_path / "s2")]) == 0
    assert "no DEM envelope" in capsys.readouterr().out
    assert not pd.read_csv(tmp_path / "s2" / "sweep.csv")["above_capacity"].any()


def _ug2(tmp_path, stage_parameters: str) -> Path:
    text = (ROOT / "examples" / "ug2.toml").read_text(encoding="utf-8")
    run_file = tmp_path / "ug2.toml"
    run_file.write_text(text.replace('file = "default"', f'file = "{stage_parameters}"'), encoding="utf-8")
    return run_file


def test_sweep_over_rotation_senses_says_what_each_rests_on(tmp_path, capsys, monkeypatch):
    from msmill.plots import validation

    plotted = []
    real = validation.sweep_plot
    monkeypatch.setattr(validation, "sweep_plot", lambda t, x, y, hue=None: plotted.append((x, hue)) or real(t, x, y, hue))
    run_file = _ug2(tmp_path, "table")  # the single-point table: no record of its machine, so both senses run
    assert run(["sweep", str(run_file), "--var", "rotation_sense=down_down,up_up", "--var", "speed_rpm=1300:1700:3",
                "--out", str(tmp_path / "s")]) == 0
    out = " ".join(capsys.readouterr().out.split())
    t = pd.read_csv(tmp_path / "s" / "sweep.csv")
    assert list(t["rotation_sense"]) == ["down_down"] * 3 + ["up_up"] * 3
    assert set(t["stage_parameters"]) == {"default.json"}
    # the table's statistics are the default machine's for both senses: the same numbers, and the output says why
    assert t["p80_mm"].iloc[:3].tolist() == t["p80_mm"].iloc[3:].tolist()
    assert "stage parameters of up_up: default.json; they do not record their machine" in out
    assert "down_down, up_up rest on the same stage parameters (default.json)" in out
    assert "up_up: capacity: no DEM envelope" in out  # the shipped envelope is the default machine's
    assert set(plotted) == {("speed_rpm", "rotation_sense")}  # the hue is the sense
    assert (tmp_path / "s" / "sweep_p80_mm.png").is_file()


def test_sweep_over_a_sense_without_stage_parameters_stops_in_one_line(tmp_path, capsys):
    run_file = _ug2(tmp_path, "default")
    for var in (["--var", "rotation_sense=down_down,down_up"],  # down_up: no surrogate shipped
                ["--var", "speed_rpm=1300:1700:3", "--var", "rotation_sense=down_down,down_up"]):
        assert run(["sweep", str(run_file), *var, "--out", str(tmp_path / "s")]) == 2
        cap = capsys.readouterr()
        assert cap.out == "" and len(cap.err.strip().splitlines()) == 1
        assert cap.err.startswith("error: ug2.toml.stage_parameters.file: got 'default'") and "'down_up'" in cap.err
        assert not (tmp_path / "s").exists()
    assert run(["optimize", str(run_file), "--bound", "speed_rpm=1200:1900", "--bound",
                "rotation_sense=down_up,down_down", "--goal", "min_energy", "--target-p80-mm", "18",
                "--out", str(tmp_path / "o")]) == 2
    assert "stage_parameters.file" in capsys.readouterr().err and not (tmp_path / "o").exists()
    for value, allowed in (("down_down,sideways", "allowed: down_down, up_up"),
                           ("down_down:up_up", "allowed: rotation senses separated by commas (no range)")):
        assert run(["sweep", str(run_file), "--var", f"rotation_sense={value}", "--out", str(tmp_path / "s")]) == 2
        err = capsys.readouterr().err
        assert err.startswith("error: --var rotation_sense: got ") and allowed in err and len(err.splitlines()) == 1
    assert not (tmp_path / "s").exists()


def test_optimize_over_rotation_senses_reports_each_and_the_best(tmp_path, capsys):
    run_file = _ug2(tmp_path, "table")
    assert run(["optimize", str(run_file), "--bound", "speed_rpm=1200:1900", "--bound",
                "rotation_sense=up_up,down_down", "--goal", "min_energy", "--target-p80-mm", "18", "--n-grid", "4",
                "--out", str(tmp_path / "o")]) == 0
    out = " ".join(capsys.readouterr().out.split())
    assert "rotation sense up_up: meets P80 <= 18 mm; best: speed_rpm = " in out
    assert "rotation sense down_down: meets P80 <= 18 mm" in out
    assert "best of every rotation sense: up_up (min_energy, P80 <= 18 mm)" in out  # a tie: the first given
    assert "up_up, down_down rest on the same stage parameters (default.json)" in out
    s = pd.read_csv(tmp_path / "o" / "senses.csv")
    assert list(s["rotation_sense"]) == ["up_up", "down_down"] and list(s["best"]) == [True, False]
    assert s["meets_target"].all() and (s["p80_mm"] <= 18).all()
    c = pd.read_csv(tmp_path / "o" / "candidates.csv")
    assert set(c["rotation_sense"]) == {"up_up", "down_down"}
    assert run(["optimize", str(run_file), "--bound", "speed_rpm=1200:1900", "--bound",
                "rotation_sense=up_up,down_down", "--goal", "min_energy", "--target-p80-mm", "0.5", "--n-grid", "3",
                "--out", str(tmp_path / "o2")]) == 0
    out = " ".join(capsys.readouterr().out.split())
    assert "rotation sense up_up: misses P80 <= 0.5 mm; the closest: speed_rpm = 1900" in out
    assert "no rotation sense (up_up, down_down) reaches P80 <= 0.5 mm" in out


def test_calibrate_reports_every_submodel_for_a_users_ore(tmp_path, capsys, own_ore_file):
    from msmill.model.fitting import FITTABLE

    data = tmp_path / "data"
    data.mkdir()
    for p in sorted(EXAMPLES.glob("ug2-lab-*-[13]5ms.toml")):  # 4 tests: two feeds at 15 and 35 m/s
        (data / p.name).write_text(p.read_text(encoding="utf-8").replace('ore = "UG2"', 'ore = "MyRock"'),
                                   encoding="utf-8")
    ore = own_ore_file("MyRock", folder=data)  # kept in the experiments folder: not read as an experiment
    assert run(["calibrate", str(data)]) == 2  # the experiments name an ore msmill does not know
    assert "MyRock" in capsys.readouterr().err
    out = tmp_path / "out"
    assert run(["calibrate", str(data), "--out", str(out), "--ore-file", str(ore)]) == 0
    text = capsys.readouterr().out
    assert "leave-one-test-out" in text and "identified" in text and "on a bound" in text
    t = pd.read_csv(out / "impact_fits.csv")
    assert set(t["submodel"]) == set(FITTABLE) and set(t["ore"]) == {"MyRock"}
    for _, r in t.iterrows():
        for k in FITTABLE[r["submodel"]]:
            assert r[f"lo_{k}"] <= r[k] <= r[f"hi_{k}"]
            assert r[f"se_jackknife_{k}"] > 0 and r[f"se_bootstrap_{k}"] > 0
    assert (t["ks_held_out_mean"] >= t["ks_fit_mean"] - 1e-9).all()
    # the SYNTHETIC truth (examples/experiments/PROVENANCE.json: ab_t10, A 71.8 %, L_ref 20 mm)
    ab = t.set_index("submodel").loc["ab_t10"]
    assert abs(ab["l_ref_mm"] - 20.0) < 2 * ab["se_bootstrap_l_ref_mm"]
    assert abs(ab["A_pct"] - 71.8) < 2 * ab["se_bootstrap_A_pct"]
    held = pd.read_csv(out / "MyRock_impact_heldout.csv")
    assert len(held) == 4 * len(FITTABLE)


@pytest.mark.parametrize("command", ["calibrate", "predict"])
@pytest.mark.parametrize("text,expect", [(None, "error: path"), ("name = ", "valid TOML"),
                                         ('name = "X"\ndescription = "d"\n', "error: ")])
def test_bad_ore_file_is_one_line(tmp_path, capsys, command, text, expect):
    data = tmp_path / "data"
    data.mkdir()
    for p in sorted(EXAMPLES.glob("ug2-lab-13x16-[13]5ms.toml")):
        shutil.copy(p, data / p.name)
    ore = tmp_path / "ore.toml"
    if text is not None:
        ore.write_text(text, encoding="utf-8")
    target = data if command == "calibrate" else ROOT / "examples" / "ug2.toml"
    out = tmp_path / "out"
    assert run([command, str(target), "--ore-file", str(ore), "--out", str(out)]) == 2
    err = [e for e in capsys.readouterr().err.strip().splitlines() if e]
    assert len(err) == 1 and err[0].startswith("error:") and expect in err[0], err
    assert not out.exists()


@pytest.mark.slow
def test_calibrate_recovers_the_shipped_synthetic_truth_within_its_standard_errors(tmp_path, capsys):
    # issue 41 "done when": msmill calibrate on the shipped SYNTHETIC examples (surveys made with the default
    # stage parameters, lab tests with ab_t10 and vogel_swebrec) finds what made them within the s.e. it
    # reports (PROVENANCE.json). Made with the table, the surveys gave UG2 L_ref 16.6 +- 0.7 mm for 20.
    import json

    prov = json.loads((EXAMPLES / "PROVENANCE.json").read_text(encoding="utf-8"))
    assert prov["SYNTHETIC"] and prov["stage_parameters"].startswith("default")
    out = tmp_path / "out"
    assert run(["calibrate", str(EXAMPLES), "--out", str(out)]) == 0
    sv = pd.read_csv(out / "survey_fits.csv").set_index("ore")
    for ore, true in prov["true_l_ref_mm"].items():
        r = sv.loc[ore]
        assert r["stage_samples"] == 8 and r["se"] >= r["se_jackknife"]
        assert abs(r["value"] - true) < 2 * r["se"], (ore, r.to_dict())
    lab = pd.read_csv(out / "impact_fits.csv").set_index(["ore", "submodel"])
    for (ore, sub), true in ((("UG2", "ab_t10"), prov["ug2_lab_ab_t10_true"]),
                             (("Platreef", "vogel_swebrec"), prov["platreef_lab_vogel_swebrec_true"])):
        r = lab.loc[(ore, sub)]
        assert r["identified"]
        for k, v in true.items():
            assert abs(r[k] - v) < 2 * r[f"se_bootstrap_{k}"], (ore, sub, k, r[k], r[f"se_bootstrap_{k}"])
