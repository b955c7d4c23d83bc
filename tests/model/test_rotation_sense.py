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
    up = Machine.default().with_rotation_sense("up_up")
    assert P.named_parameter_path("default", "f", Machine.default()) == P.default_surrogate_path()
    assert P.named_parameter_path("default", "f", None) == P.default_surrogate_path()
    with pytest.raises(MsmillInputError, match=r"^f: got 'default'; allowed: a surrogate file of rotation sense "
                                               r"'up_up' \(none is shipped yet"):
        P.named_parameter_path("default", "f", up)
    # a machine of its own geometry is no sense of the default: "default" stays the shipped surrogate
    own = up.model_copy(update={"headroom_m": 0.25})
    assert P.named_parameter_path("default", "f", own) == P.default_surrogate_path()
    shutil.copy(P.default_surrogate_path(), tmp_path / "up_up.json")
    monkeypatch.setattr(P, "default_surrogate_path_dir", lambda: tmp_path)
    assert P.named_parameter_path("default", "f", up) == tmp_path / "up_up.json"


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
    f.write_text(src.replace("[stage_parameters]", '[machine]\nrotation_sense = "up_up"\n\n[stage_parameters]'))
    rf = RunFile.from_toml(f)
    assert rf.machine_obj().rotation_sense == "up_up"
    with pytest.raises(MsmillInputError, match=r"^r.toml.stage_parameters.file: got 'default'; allowed: .*'up_up'"):
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
