"""Campaign export in git: a campaign continues on a fresh store from the export folder alone;
the shipped default surrogate and the named parameter sources ("default", "table")."""

from __future__ import annotations

import json
import warnings
from dataclasses import replace

import pytest

from msmill.machine import Machine
from msmill.pipeline.export import (
    CAMPAIGNS_FILE,
    default_export_dir,
    export_campaign,
    read_export,
    restore_campaigns,
    split_runs,
)
from msmill.pipeline.store import Store
from msmill.pipeline.store.transfer import ingest_paths
from msmill.stageparams import DesignPoint

MACHINE = Machine.default()


def _point(size_mm: float, feed_tph: float = 30.0) -> DesignPoint:
    return DesignPoint(size_mm=size_mm, feed_tph=feed_tph, speed_rpm=1500.0, gate_deg=40.0,
                       stage_speeds_rpm=[1500.0] * 4 + [3000.0])


@pytest.fixture
def exported(tmp_path, table_runs):
    """A store with 3 done runs (one full-mill) and a campaign with 2 pending points, exported."""
    st = Store(f"sqlite:///{tmp_path / 'a.sqlite'}")
    for run in table_runs[:2]:
        st.record_run(run, MACHINE, wall_s=100.0)
    full = table_runs[2].model_copy(update={"mode": "full"})  # synthetic full-mill twin
    st.record_run(full, MACHINE, wall_s=900.0)
    st.create_campaign("c", MACHINE, run_settings={"max_time_s": 2.0}, max_attempts=4,
                       options={"size_range_mm": [6.0, 30.0], "raw_dir": "/somewhere/raw"})
    st.add_points("c", [table_runs[0].design, _point(17.0, 45.0)])
    runs, cpath = export_campaign(st, tmp_path / "export")
    st.close()
    return tmp_path / "export", runs, cpath


def test_export_holds_runs_and_campaign_definitions(exported):
    folder, runs, cpath = exported
    assert len(runs) == 3 and cpath.name == CAMPAIGNS_FILE
    doc = json.loads(cpath.read_text())
    (c,) = doc["campaigns"]
    assert c["options"]["size_range_mm"] == [6.0, 30.0] and c["max_attempts"] == 4 and len(c["pending"]) == 2
    got = read_export(folder)
    slices, fulls = split_runs(got)
    assert len(slices) == 2 and len(fulls) == 1 and {r.wall_s for r in slices} == {100.0}
    for p in runs:  # no raw data in git: statistics and references only
        assert p.stat().st_size < 40_000


def test_a_fresh_store_continues_from_the_export_alone(exported, tmp_path):
    folder, _, _ = exported
    st = Store(f"sqlite:///{tmp_path / 'b.sqlite'}")
    res = ingest_paths(st, [folder])
    assert [r.status for r in res] == ["added"] * 3
    lines = restore_campaigns(st, folder, raw_dir=None)
    assert lines == ["campaign c: re-created, 1 pending runs planned"]
    info = st.campaign("c")
    assert info.run_settings == {"max_time_s": 2.0} and "raw_dir" not in info.options
    planned = st.runs(campaign="c", status="planned")
    # the pending point already done (ingested) is not planned again; the new one is
    assert [(r.design.size_mm, r.design.feed_tph) for r in planned] == [(17.0, 45.0)]
    assert restore_campaigns(st, folder) == ["campaign c: already in the store"]
    assert [r.status for r in ingest_paths(st, [folder])] == ["exists"] * 3
    st.close()


def test_packaged_export_ingests_from_the_installed_package(tmp_path):
    folder = default_export_dir()
    assert folder.is_dir(), "the campaign export is shipped in msmill/data/campaigns/default"
    st = Store(f"sqlite:///{tmp_path / 'c.sqlite'}")
    res = ingest_paths(st, [folder], allow_not_steady=True)
    assert res and all(r.status == "added" for r in res)
    assert len(st.runs(status="done")) == len(read_export(folder))
    st.close()


def test_default_is_the_shipped_surrogate_and_table_stays_by_name():
    from msmill.model.providers import TableProvider, default_surrogate_path, load_provider
    from msmill.surrogate.provider import SurrogateProvider

    assert default_surrogate_path() is not None
    wrapped = load_provider("default")  # the surrogate, with the shipped table's filling curves (cold runs)
    prov = wrapped.provider
    assert isinstance(prov, SurrogateProvider) and prov.source.startswith("shipped default surrogate")
    assert wrapped.source.startswith("shipped default surrogate") and wrapped.surrogate is prov.surrogate
    p = prov.surrogate.provenance_
    for key in ("git_commit", "loo", "domain", "runs", "package_versions", "command"):
        assert key in p
    assert p["loo"]["n_runs"] == prov.surrogate.training_.n_runs == len(p["runs"])
    assert isinstance(load_provider("table"), TableProvider)


def test_missing_shipped_surrogate_falls_back_to_the_table_with_a_note(monkeypatch):
    from msmill.model import providers

    monkeypatch.setattr(providers, "default_surrogate_path", lambda: None)
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        prov = providers.load_provider("default")
    assert isinstance(prov, providers.TableProvider)
    assert any("shipped default surrogate" in str(x.message) and "'table'" in str(x.message) for x in w)


def test_runs_outside_the_design_space_do_not_train(exported):
    """A steady capacity probe at 100 t/h stays in the export (for the envelope) but is not training data."""
    folder, _, _ = exported
    slices, fulls = split_runs(read_export(folder))
    one, other = slices

    def moved(run, **design):
        return replace(run, statistics=run.statistics.model_copy(
            update={"design": run.statistics.design.model_copy(update=design)}))

    probe = moved(one, feed_tph=100.0)
    assert split_runs([probe, other, *fulls]) == ([other], fulls)
    edge = moved(one, feed_tph=60.0, gate_deg=0.0)
    assert split_runs([edge])[0] == [edge]  # the bounds belong to the design space


def test_a_failed_point_stays_failed_in_a_store_restored_from_the_export(tmp_path, table_runs):
    """A point whose attempts all failed is exported with its error and restored as failed (not planned),
    so the planner of the next session counts it as pending rather than proposing it again."""
    st = Store(f"sqlite:///{tmp_path / 'a.sqlite'}")
    st.record_run(table_runs[0], MACHINE, wall_s=100.0)
    st.create_campaign("c", MACHINE, max_attempts=1)
    bad, later = _point(3.51, 37.7), _point(17.0, 45.0)
    st.add_points("c", [bad, later])
    (claim,) = st.claim("c", 1, "w", "tok")
    assert st.fail(claim.run_id, "tok", "KilledWorker: worker died 4 times") == "failed"
    export_campaign(st, tmp_path / "export")
    st.close()

    fresh = Store(f"sqlite:///{tmp_path / 'b.sqlite'}")
    ingest_paths(fresh, [tmp_path / "export"])
    lines = restore_campaigns(fresh, tmp_path / "export")
    assert lines == ["campaign c: re-created, 1 pending runs planned, 1 failed points kept failed"]
    (f,) = fresh.runs(campaign="c", status="failed")
    assert (f.design.size_mm, f.design.feed_tph) == (3.51, 37.7) and f.attempts == 1
    assert "KilledWorker" in f.error
    assert [r.design.size_mm for r in fresh.runs(campaign="c", status="planned")] == [17.0]
    assert fresh.retry_failed("c") == 1  # still re-plannable by hand
    fresh.close()


def test_a_campaign_run_goes_back_to_its_campaign_and_the_re_export_is_unchanged(tmp_path, table_runs):
    """A fresh store ingests an export's runs without campaigns; restoring the campaigns gives each run
    back to the campaign its document names, so the campaign counts it and a re-export (what the loop
    commits every session) rewrites every document byte for byte (it used to write ``campaign: null``)."""
    st = Store(f"sqlite:///{tmp_path / 'a.sqlite'}")
    st.record_run(table_runs[1], MACHINE, wall_s=50.0)  # a run of no campaign stays of none
    st.create_campaign("c", MACHINE)
    st.add_points("c", [table_runs[0].design])
    (claim,) = st.claim("c", 1, "w", "tok")
    st.complete(claim.run_id, "tok", table_runs[0], wall_s=100.0, engine="msmill.dem 0.1.0", package_version="0.1.0",
                git_commit="0" * 40)  # what a worker records
    export_campaign(st, tmp_path / "export")
    st.close()
    before = {p.name: p.read_bytes() for p in (tmp_path / "export").iterdir()}
    assert sorted(r.campaign or "" for r in read_export(tmp_path / "export")) == ["", "c"]

    fresh = Store(f"sqlite:///{tmp_path / 'b.sqlite'}")
    ingest_paths(fresh, [tmp_path / "export"])
    restore_campaigns(fresh, tmp_path / "export")
    assert fresh.counts("c")["done"] == 1 and len(fresh.runs(status="done")) == 2
    export_campaign(fresh, tmp_path / "export")
    assert {p.name: p.read_bytes() for p in (tmp_path / "export").iterdir()} == before
    # a store that already has the campaign (a second session) adopts the runs it ingests too
    again = Store(f"sqlite:///{tmp_path / 'c.sqlite'}")
    again.create_campaign("c", MACHINE)
    ingest_paths(again, [tmp_path / "export"])
    assert restore_campaigns(again, tmp_path / "export") == ["campaign c: already in the store, 1 ingested runs "
                                                             "given back to it"]
    assert again.counts("c")["done"] == 1
    fresh.close()
    again.close()
