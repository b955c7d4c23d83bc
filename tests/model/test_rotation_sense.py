"""Rotation sense as a setting (issue 37 item 3): the machine's identity for the DEM, the shipped surrogate of
each sense, and a prediction that says when its stage statistics come from another machine."""

from __future__ import annotations

import json
import shutil
import warnings

import pytest

from msmill.errors import MsmillInputError
from msmill.machine import DEFAULT_ROTATION_SENSE, Machine, rotation_senses
from msmill.model import providers as P
from msmill.validate import InputWarning

STUDY = sorted(rotation_senses())


def test_geometry_hash_is_what_the_dem_sees():
    d = Machine.default()
    assert d.rotation_sense == DEFAULT_ROTATION_SENSE
    # the sense written out, another name or description: the same DEM runs, the same hash
    assert d.with_rotation_sense("down_down").geometry_hash() == d.geometry_hash()
    assert d.model_copy(update={"name": "x", "description": "y"}).geometry_hash() == d.geometry_hash()
    hashes = {d.with_rotation_sense(s).geometry_hash() for s in STUDY}
    assert len(hashes) == len(STUDY)  # every sense its own machine
    assert d.model_copy(update={"headroom_m": 0.25}).geometry_hash() != d.geometry_hash()


@pytest.mark.parametrize("sense", STUDY)
def test_the_study_machine_files_are_the_default_turning_each_way(sense):
    from importlib import resources

    f = resources.files("msmill").joinpath(f"data/machines/{sense}.toml")
    m = Machine.from_toml(str(f))
    assert m.rotation_sense == sense
    assert m.geometry_hash() == Machine.default().with_rotation_sense(sense).geometry_hash()


def test_an_unknown_sense_is_one_line():
    with pytest.raises(MsmillInputError, match=r"rotation_sense: got 'sideways'; allowed: .*up_up"):
        Machine.default().with_rotation_sense("sideways")
    odd = Machine.default().model_copy(update={"central_sweep": [("up", "down")] * 5})
    assert odd.rotation_sense == "custom"


def test_default_names_the_sense_surrogate_or_says_none_is_shipped(tmp_path, monkeypatch):
    up = Machine.default().with_rotation_sense("down_up")  # a sense whose surrogate is not shipped
    assert P.named_parameter_path("default", "f", Machine.default()) == P.default_surrogate_path()
    assert P.named_parameter_path("default", "f", None) == P.default_surrogate_path()
    with pytest.raises(MsmillInputError, match=r"^f: got 'default'; allowed: a surrogate file of rotation sense "
                                               r"'down_up' \(none is shipped yet"):
        P.named_parameter_path("default", "f", up)
    # a machine of its own geometry is no sense of the default: "default" stays the shipped surrogate
    own = up.model_copy(update={"headroom_m": 0.25})
    assert P.named_parameter_path("default", "f", own) == P.default_surrogate_path()
    shutil.copy(P.default_surrogate_path(), tmp_path / "down_up.json")
    monkeypatch.setattr(P, "default_surrogate_path_dir", lambda: tmp_path)
    assert P.named_parameter_path("default", "f", up) == tmp_path / "down_up.json"


def _provider_of(machine: Machine):
    prov = P.load_provider("default")
    prov.surrogate.provenance_ = {**prov.surrogate.provenance_, "machine": {
        "name": machine.name, "rotation_sense": machine.rotation_sense, "geometry_hash": machine.geometry_hash()}}
    return prov


def test_a_prediction_for_another_machine_says_its_statistics_are_not_its_own():
    from msmill.model import Mill

    prov = _provider_of(Machine.default())
    assert prov.trained_machine["rotation_sense"] == "down_down"
    with warnings.catch_warnings():
        warnings.simplefilter("error", InputWarning)
        assert Mill("UG2", prov, Machine.default(), band_samples=0).machine_note is None
    up = Machine.default().with_rotation_sense("up_up")
    with pytest.warns(InputWarning, match="another machine: default \\(rotation sense down_down\\), not this default "
                                          "\\(rotation sense up_up\\)"):
        mill = Mill("UG2", prov, up, band_samples=0)
    from msmill.psd import PSD

    feed = PSD.from_passing([4.75, 9.5, 19.0, 26.5, 31.5], [6.0, 18.0, 58.0, 88.0, 100.0])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = mill.run(feed, {"feed_tph": 30.0, "speed_rpm": 1500.0, "gate_deg": 40.0}, timeseries=False,
                       held_below=False)
    assert any("another machine" in n for n in res.notes)
    # a provider that does not record its machine (a table) cannot be checked: no note
    assert P.machine_mismatch(P.load_provider("table"), up) is None


def test_run_file_rotation_sense(tmp_path):
    from msmill.model.runfile import RunFile

    src = (P.Path(__file__).resolve().parents[2] / "examples" / "ug2.toml").read_text()
    f = tmp_path / "r.toml"
    f.write_text(src.replace("[stage_parameters]", '[machine]\nrotation_sense = "down_up"\n\n[stage_parameters]'))
    rf = RunFile.from_toml(f)
    assert rf.machine_obj().rotation_sense == "down_up"
    with pytest.raises(MsmillInputError, match=r"^r.toml.stage_parameters.file: got 'default'; allowed: .*'down_up'"):
        rf.stage_parameter_path()
    f.write_text(src.replace("[stage_parameters]", '[machine]\nrotation_sense = "left"\n\n[stage_parameters]'))
    with pytest.raises(MsmillInputError, match=r"^r.toml.machine.rotation_sense: got 'left'; allowed: down_down"):
        RunFile.from_toml(f).machine_obj()


def test_an_export_of_two_machines_is_refused(tmp_path):
    from msmill.pipeline.export import default_export_dir, read_export, runs_machine

    runs = read_export(default_export_dir())
    assert runs_machine(runs).geometry_hash() == Machine.default().geometry_hash()
    doc = json.loads(runs[0].path.read_text())
    doc["machine_toml"] = Machine.default().with_rotation_sense("up_up").to_toml()
    (tmp_path / runs[0].path.name).write_text(json.dumps(doc))
    other = read_export(tmp_path)
    with pytest.raises(MsmillInputError, match="export: got 'default \\(down_down\\), default \\(up_up\\)'"):
        runs_machine([runs[1], *other])


# ------------------------------------------------ the sense as a categorical variable of sweeps and the optimiser
def _run_file(tmp_path, stage_parameters: str):
    from msmill.model.runfile import RunFile

    src = (P.Path(__file__).resolve().parents[2] / "examples" / "ug2.toml").read_text()
    f = tmp_path / "r.toml"
    f.write_text(src.replace('file = "default"', f'file = "{stage_parameters}"'))
    return RunFile.from_toml(f)


def test_mills_by_sense_resolve_each_sense_as_the_run_file_does(tmp_path):
    from msmill.model.operating import mills_by_sense

    rf = _run_file(tmp_path, "table")
    mills = mills_by_sense(rf, ["up_up", "down_down"])
    assert list(mills) == ["up_up", "down_down"]
    assert [m.machine.rotation_sense for m in mills.values()] == ["up_up", "down_down"]
    # the stage parameters each sense's run file names: here the one table for both
    assert {m.provider.source for m in mills.values()} == {rf.stage_parameter_path().name}
    assert mills["up_up"].machine == rf.with_rotation_sense("up_up").machine_obj()
    with pytest.raises(MsmillInputError, match=r"^f: got 'sideways'; allowed: down_down, up_up"):
        mills_by_sense(rf, ["down_down", "sideways"], "f")
    with pytest.raises(MsmillInputError, match=r"^f: got 'up_up'; allowed: each rotation sense once"):
        mills_by_sense(rf, ["up_up", "up_up"], "f")


def test_a_sense_without_stage_parameters_stops_before_any_mill_is_built(tmp_path, monkeypatch):
    from msmill.model import operating
    from msmill.model.runfile import RunFile

    built = []
    real = RunFile.build
    monkeypatch.setattr(RunFile, "build", lambda self: built.append(self.machine.rotation_sense) or real(self))
    rf = _run_file(tmp_path, "default")
    with pytest.raises(MsmillInputError, match=r"^r.toml.stage_parameters.file: got 'default'; allowed: a surrogate "
                                               r"file of rotation sense 'down_up'"):
        operating.mills_by_sense(rf, ["down_down", "down_up"])
    assert built == []  # down_down's surrogate was not even loaded


@pytest.fixture(scope="module")
def table_mills(tmp_path_factory):
    from msmill.model.operating import mills_by_sense

    return mills_by_sense(_run_file(tmp_path_factory.mktemp("rf"), "table"), ["down_down", "up_up"])


def test_sweep_senses_tags_every_row(table_mills):
    from msmill.machine import OperatingPoint
    from msmill.model.operating import sweep_senses

    op = OperatingPoint(feed_tph=30.0, speed_rpm=1500.0, gate_deg=40.0)
    feed = _feed()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        t = sweep_senses(table_mills, feed, op, {"speed_rpm": [1300.0, 1700.0]})
        alone = sweep_senses(table_mills, feed, op, {})
    assert list(t.columns[:3]) == ["rotation_sense", "stage_parameters", "speed_rpm"]
    assert list(t["rotation_sense"]) == ["down_down", "down_down", "up_up", "up_up"]
    assert list(t["speed_rpm"]) == [1300.0, 1700.0, 1300.0, 1700.0]
    # one table behind both senses: the same numbers (what stage_parameter_lines says)
    assert t["p80_mm"].iloc[:2].tolist() == t["p80_mm"].iloc[2:].tolist()
    assert t["p80_mm"].iloc[0] > t["p80_mm"].iloc[1]
    assert list(alone["rotation_sense"]) == ["down_down", "up_up"] and "speed_rpm" not in alone
    with pytest.raises(MsmillInputError, match="rotation_sense and at most one of"):
        sweep_senses(table_mills, feed, op, {"speed_rpm": [1300.0], "gate_deg": [40.0]})


def _feed():
    from msmill.psd import PSD

    return PSD.from_passing([4.75, 9.5, 19.0, 26.5, 31.5], [6.0, 18.0, 58.0, 88.0, 100.0])


def test_stage_parameter_lines_say_whose_machine_the_statistics_are(table_mills):
    from msmill.model import Mill
    from msmill.model.operating import stage_parameter_lines

    lines = stage_parameter_lines(table_mills)
    assert lines[0] == "stage parameters of down_down: default.json; they do not record their machine: not checked " \
                       "against this sense"
    assert lines[1].startswith("stage parameters of up_up: default.json; they do not record their machine")
    assert lines[2].startswith("down_down, up_up rest on the same stage parameters (default.json)")
    # a surrogate of the default machine: its own sense is its machine's, another sense is told so
    prov = _provider_of(Machine.default())
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        mills = {s: Mill("UG2", prov, Machine.default().with_rotation_sense(s), band_samples=0)
                 for s in ("down_down", "up_up")}
    lines = stage_parameter_lines(mills)
    assert lines[0].endswith("; this machine's")
    assert "another machine: default (rotation sense down_down), not this default (rotation sense up_up)" in lines[1]


def test_optimize_senses_reports_each_sense_and_the_best(table_mills):
    import dataclasses

    from msmill.machine import OperatingPoint
    from msmill.model import Mill
    from msmill.model.operating import optimize_senses

    op = OperatingPoint(feed_tph=30.0, speed_rpm=1500.0, gate_deg=40.0)
    m = table_mills["down_down"]
    # a stand-in for a sense whose rock breaks more easily: it reaches the target at a lower speed and energy
    soft = Mill(dataclasses.replace(m.ore, l_ref_mm=m.ore.l_ref_mm * 0.7), m.provider, m.machine, grid=m.grid,
                envelope=None)
    mills = {"up_up": table_mills["up_up"], "down_up": soft}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        target = m.run(_feed(), op, timeseries=False).p80_mm
        r = optimize_senses(mills, _feed(), op, {"speed_rpm": (1200.0, 1900.0)}, "min_energy",
                            target_p80_mm=target, n_grid=4)
        none = optimize_senses(mills, _feed(), op, {"speed_rpm": (1200.0, 1900.0)}, "min_energy",
                               target_p80_mm=0.5, n_grid=3)
    assert r.best_sense == "down_up" and r.best is r.by_sense["down_up"]
    assert r.by_sense["down_up"].row["specific_energy_kwh_t"] < r.by_sense["up_up"].row["specific_energy_kwh_t"]
    s = r.summary()
    assert list(s["rotation_sense"]) == ["up_up", "down_up"] and list(s["best"]) == [False, True]
    assert s["meets_target"].all() and list(s["stage_parameters"]) == ["default.json"] * 2
    c = r.candidates()
    assert c.columns[0] == "rotation_sense" and set(c["rotation_sense"]) == {"up_up", "down_up"}
    assert len(c) == sum(len(x.candidates) for x in r.by_sense.values())
    assert none.best_sense is None and none.best is None and not none.summary()["meets_target"].any()
    assert none.summary()["speed_rpm"].tolist() == [1900.0, 1900.0]  # each sense's closest miss
