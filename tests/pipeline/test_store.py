"""Training store on SQLite and PostgreSQL: schema, round trips, ingest/export, concurrent claims."""

from __future__ import annotations

import json
import threading

import numpy as np
import pandas as pd
import pytest
import tomli_w
from hypothesis import given, settings
from hypothesis import strategies as st_

from msmill.errors import MsmillInputError
from msmill.machine import Machine
from msmill.pipeline.store import Store
from msmill.pipeline.store.hashing import canonical_statistics, file_sha256, statistics_hash
from msmill.pipeline.store.queue import new_token
from msmill.pipeline.store.transfer import export_runs, ingest_paths
from msmill.stageparams import DesignPoint, GaussianMixture, RunStatistics, StageStatistics

MACHINE = Machine.default()


def make_stats(size_mm: float = 30.0, seed: int = 0, steady: bool = True, feed_tph: float = 30.0) -> RunStatistics:
    """Valid, varied statistics (synthetic numbers: these tests check storage, not physics)."""
    rng = np.random.default_rng(seed)
    n = MACHINE.n_stages
    stages = []
    for s in range(1, n + 1):
        k, r, _ = rng.dirichlet([1, 2, 3])
        w = rng.dirichlet([1, 1])
        stages.append(StageStatistics(
            stage=s, kickback=k, refeed=r, pass_through=1 - k - r, primary_hit_probability=rng.uniform(),
            primary_velocity=GaussianMixture(weights=[w[0], 1 - w[0]], means_m_s=list(rng.uniform(5, 40, 2)),
                                             sigmas_m_s=list(rng.uniform(0.5, 5, 2))),
            primary_velocity_kl=float(rng.uniform(0, 0.1)), secondary_lambda=float(rng.uniform(0, 3)),
            secondary_velocity=GaussianMixture.single(float(rng.uniform(1, 20)), 2.0),
            n_primary_impacts=int(rng.integers(0, 500)), n_secondary_impacts=int(rng.integers(0, 900)),
            n_transport_samples=int(rng.integers(1, 900)), mean_holdup_kg=float(rng.uniform(0, 3)),
            sampling_error={"kickback": float(rng.uniform(0, 0.05))}))
    design = DesignPoint(size_mm=size_mm, feed_tph=feed_tph, speed_rpm=1500.0, gate_deg=40.0,
                         stage_speeds_rpm=[1500.0] * (n - 1) + [3000.0])
    return RunStatistics(design=design, characteristic_time_s=0.03 + 0.001 * seed, stages=stages,
                         steady_state_time_s=0.5 if steady else None, measurement_window_s=0.5,
                         mass_out_rate_kg_s=float(rng.uniform(0.5, 2)), provenance={"seed": seed, "date": str(seed)})


def write_run_folder(folder, stats: RunStatistics, seed: int = 0) -> None:
    """A run folder in the layout of ``msmill.dem.mill.run.save_run`` (small hand-made tables)."""
    folder.mkdir(parents=True)
    stats.to_json(folder / "statistics.json")
    MACHINE.to_toml(folder / "machine.toml")
    (folder / "run.toml").write_text(tomli_w.dumps({"run": {"seed": seed, "max_time_s": 1.0},
                                                    "result": {"wall_s": 12.5}}))
    pd.DataFrame({"time_s": [0.1, 0.2], "particle_id": [1, 2]}).to_parquet(folder / "events.parquet")


def same_numbers(a: RunStatistics, b: RunStatistics) -> bool:
    da, db = canonical_statistics(a), canonical_statistics(b)
    da.pop("provenance"), db.pop("provenance")
    return da == db


# --------------------------------------------------------------------------- schema
def test_migrations_create_exactly_the_orm_schema(store):
    from alembic.autogenerate import compare_metadata
    from alembic.runtime.migration import MigrationContext

    from msmill.pipeline.store.schema import Base

    assert store.revision() == store.head()
    with store.engine.connect() as conn:
        diff = compare_metadata(MigrationContext.configure(conn), Base.metadata)
    assert diff == []
    Store(store.url).close()  # reopening a current store is a no-op
    assert store.revision() == store.head()


def test_default_url_and_env(monkeypatch, tmp_path):
    from msmill.pipeline.store.core import default_url

    monkeypatch.delenv("MSMILL_DB", raising=False)
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path))
    assert default_url() == f"sqlite:///{tmp_path / 'msmill' / 'store.sqlite'}"
    monkeypatch.setenv("MSMILL_DB", "sqlite:///x.db")
    assert default_url() == "sqlite:///x.db"


# --------------------------------------------------------------------------- round trips
def test_record_and_query_round_trip(store):
    runs = {}
    for i, size in enumerate([20.0, 30.0, 40.0]):
        st = make_stats(size, seed=i)
        run_id, created = store.record_run(st, MACHINE, seed=i, source_path=f"/x/{i}")
        assert created
        runs[run_id] = st
    for run_id, st in runs.items():
        back = store.statistics(run_id)
        assert back == st  # every field, provenance included
        rec = store.run(run_id)
        assert rec.design == st.design and rec.status == "done" and rec.outcome == "steady"
        assert rec.content_hash == statistics_hash(st, store.runs()[0].machine_hash)
    # per-stage columns, queryable by stage
    tab = store.stage_table(stage=3)
    assert len(tab) == 3 and set(tab["stage"]) == {3}
    for _, row in tab.iterrows():
        s3 = runs[int(row["run_id"])].stages[2]
        assert row["kickback"] == s3.kickback and row["secondary_lambda"] == s3.secondary_lambda
        assert row["primary_velocity_mean_m_s"] == pytest.approx(s3.primary_velocity.mean(), rel=1e-12)
        assert row["n_primary_impacts"] == s3.n_primary_impacts
    # design-variable filters
    assert [r.design.size_mm for r in store.runs(filters={"size_mm": (25.0, None)})] == [30.0, 40.0]
    assert [r.design.size_mm for r in store.runs(filters={"size_mm": (None, 30.0)})] == [20.0, 30.0]
    with pytest.raises(MsmillInputError):
        store.runs(filters={"colour": (0, 1)})
    # the machine comes back from its hash
    assert store.run_machine(next(iter(runs))) == MACHINE


def test_not_steady_runs_are_refused_unless_allowed(store):
    st = make_stats(steady=False)
    with pytest.raises(MsmillInputError, match="outcome"):
        store.record_run(st, MACHINE)
    run_id, _ = store.record_run(st, MACHINE, allow_not_steady=True)
    assert store.run(run_id).outcome == "not_steady"
    assert store.training_runs() == []
    assert [r.id for r, _ in store.training_runs(steady_only=False)] == [run_id]


def test_training_runs_and_surrogate_table(store):
    ids = [store.record_run(make_stats(s, seed=k), MACHINE)[0] for k, s in enumerate([20.0, 30.0])]
    data = store.training_runs(machine_hash=store.run(ids[0]).machine_hash[:8])
    assert [r.id for r, _ in data] == ids and data[1][1] == store.statistics(ids[1])
    sid = store.add_surrogate("gp-test", "gp", ids, hyperparameters={"length_scale": [1.0, 2.0]},
                              metrics={"rmse": 0.1}, versions={"msmill": "0.1"}, artifact=b"\x00model",
                              machine_hash=data[0][0].machine_hash)
    [row] = store.surrogates("gp-test")
    assert row["id"] == sid and row["run_ids"] == ids and row["artifact"] == b"\x00model"
    assert row["hyperparameters"] == {"length_scale": [1.0, 2.0]} and row["metrics"] == {"rmse": 0.1}


# --------------------------------------------------------------------------- ingest / export
def test_ingest_is_idempotent_by_content_hash(store, tmp_path):
    for i in range(3):
        write_run_folder(tmp_path / "runs" / f"r{i}", make_stats(20.0 + 10 * i, seed=i), seed=i)
    first = ingest_paths(store, [tmp_path / "runs"])
    assert [r.status for r in first] == ["added"] * 3
    again = ingest_paths(store, [tmp_path / "runs", tmp_path / "runs" / "r1"])
    assert [r.status for r in again] == ["exists"] * 4
    assert len(store.runs()) == 3
    assert set(store.count_stage_rows().values()) == {MACHINE.n_stages}
    rec = store.run(first[0].run_id)
    assert rec.seed == 0 and rec.wall_s == 12.5 and rec.run_settings == {"seed": 0, "max_time_s": 1.0}
    [raw] = store.raw_files(rec.id)
    assert raw["kind"] == "events" and raw["sha256"] == file_sha256(tmp_path / "runs" / "r0" / "events.parquet")
    # statistics recomputed from the same data (new provenance) are the same run
    st = make_stats(20.0, seed=0).model_copy(update={"provenance": {"date": "later"}})
    write_run_folder(tmp_path / "again", st)
    assert ingest_paths(store, [tmp_path / "again"])[0].status == "exists"
    # a not-steady folder is skipped with the reason, or taken when allowed
    write_run_folder(tmp_path / "ns", make_stats(50.0, seed=9, steady=False))
    [skip] = ingest_paths(store, [tmp_path / "ns"])
    assert skip.status == "skipped" and "not_steady" in skip.reason
    assert ingest_paths(store, [tmp_path / "ns"], allow_not_steady=True)[0].status == "added"


def test_export_then_ingest_gives_identical_statistics(store, tmp_path):
    originals = [make_stats(20.0 + 5 * i, seed=i) for i in range(3)]
    for i, st in enumerate(originals):
        store.record_run(st, MACHINE, seed=i, git_commit=f"abc{i}")
    paths = export_runs(store, tmp_path / "export")
    assert len(paths) == 3 and all(json.loads(p.read_text())["kind"] == "msmill_run" for p in paths)
    other = Store(f"sqlite:///{tmp_path / 'other.sqlite'}")
    res = ingest_paths(other, [tmp_path / "export"])
    assert [r.status for r in res] == ["added"] * 3
    got = {other.run(r.run_id).design.size_mm: (other.run(r.run_id), other.statistics(r.run_id)) for r in res}
    for i, st in enumerate(originals):
        rec, back = got[st.design.size_mm]
        assert back == st and rec.git_commit == f"abc{i}" and rec.seed == i
    # and back into the source store: nothing new
    assert {r.status for r in ingest_paths(store, [tmp_path / "export"])} == {"exists"}
    # the export is stable text: exporting again writes the same bytes
    again = export_runs(other, tmp_path / "export2")
    a = {p.name: json.loads(p.read_text())["statistics"] for p in paths}
    b = {p.name: json.loads(p.read_text())["statistics"] for p in again}
    assert a == b
    other.close()


def test_reexport_replaces_a_document_written_before_the_schema_grew(store, tmp_path):
    """An export made before the statistics gained an optional field hashes differently today:
    ingesting and exporting it again must leave the run once, under its new name."""
    store.record_run(make_stats(20.0, seed=1), MACHINE, seed=1)
    store.record_run(make_stats(25.0, seed=2), MACHINE, seed=2)
    folder = tmp_path / "export"
    first = export_runs(store, folder)
    doc = json.loads(first[0].read_text())
    del doc["statistics"]["mass_out_rate_kg_s"]          # an optional field the old schema lacked
    old_hash = "0" * 64
    doc["content_hash"] = old_hash
    first[0].unlink()
    (folder / f"run-{old_hash[:16]}.json").write_text(json.dumps(doc))
    unrelated = folder / "run-ffffffffffffffff.json"     # another run, not in this store: kept
    other_doc = json.loads(first[1].read_text())
    other_doc["statistics"]["characteristic_time_s"] = 0.5
    unrelated.write_text(json.dumps(other_doc))
    fresh = Store(f"sqlite:///{tmp_path / 'fresh.sqlite'}")
    fresh.record_run(make_stats(25.0, seed=2), MACHINE, seed=2)
    ingest_paths(fresh, [folder / f"run-{old_hash[:16]}.json"])
    written = export_runs(fresh, folder)
    names = sorted(p.name for p in folder.glob("run-*.json"))
    assert f"run-{old_hash[:16]}.json" not in names
    assert unrelated.name in names and all(p.name in names for p in written)
    assert len(names) == len(written) + 1
    fresh.close()


# --------------------------------------------------------------------------- campaign queue
def _campaign(store, n_points: int, name: str = "c", max_attempts: int = 3):
    store.create_campaign(name, MACHINE, run_settings={"max_time_s": 0.5}, max_attempts=max_attempts)
    designs = [make_stats(10.0 + i, seed=0).design for i in range(n_points)]
    assert store.add_points(name, designs) == (n_points, 0)
    assert store.add_points(name, designs[:2]) == (0, min(2, n_points))  # planning is idempotent
    return designs


def test_two_drivers_racing_claim_each_run_once(store):
    n = 24
    _campaign(store, n)
    claimed: dict[str, list[int]] = {}
    barrier = threading.Barrier(2)

    def driver(tag: str) -> None:
        own = Store(store.url)  # its own engine and connections, like a second process
        token = new_token()
        got: list[int] = []
        barrier.wait()
        while True:
            cl = own.claim("c", 1, f"driver {tag}", token)
            if not cl:
                break
            for c in cl:
                got.append(c.run_id)
                assert own.complete(c.run_id, token, make_stats(c.design.size_mm, seed=c.run_id))
        claimed[tag] = got
        own.close()

    threads = [threading.Thread(target=driver, args=(t,)) for t in "ab"]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    a, b = claimed["a"], claimed["b"]
    assert not set(a) & set(b)
    assert sorted(a + b) == [r.id for r in store.runs(campaign="c")]
    assert store.counts("c")["done"] == n
    assert all(r.attempts == 1 for r in store.runs(campaign="c"))
    assert set(store.count_stage_rows().values()) == {MACHINE.n_stages}


def test_lost_claim_cannot_record_and_stale_runs_are_replanned(store):
    _campaign(store, 3)
    ta, tb = new_token(), new_token()
    [c] = store.claim("c", 1, "driver a", ta)
    assert store.replan_stale("c", stale_s=3600) == 0  # fresh heartbeat: left alone
    assert store.heartbeat([c.run_id], ta) == 1
    assert store.replan_stale("c", stale_s=0) == 1  # driver a "died"
    [c2] = store.claim("c", 1, "driver b", tb)
    assert c2.run_id == c.run_id and c2.attempt == 2
    stats = make_stats(c.design.size_mm, seed=1)
    assert not store.complete(c.run_id, ta, stats)  # a's late result is refused
    assert store.heartbeat([c.run_id], ta) == 0
    assert store.complete(c.run_id, tb, stats)
    assert not store.complete(c.run_id, tb, stats)  # never recorded twice
    assert store.count_stage_rows() == {c.run_id: MACHINE.n_stages}
    assert "heartbeat stale" in store.run(c.run_id).error
    # a done run is never claimed again
    assert c.run_id not in [x.run_id for x in store.claim("c", 10, "driver b", tb)]


def test_a_result_whose_design_point_differs_from_the_planned_one_is_refused(store):
    """The store keeps a run's design point once (its row); the DEM's statistics must agree with it."""
    _campaign(store, 1)
    t = new_token()
    [c] = store.claim("c", 1, "driver a", t)
    other = make_stats(c.design.size_mm * 1.01, seed=1)  # e.g. the DEM ran a rounded or other size
    with pytest.raises(MsmillInputError, match=r"statistics\.design\.size_mm"):
        store.complete(c.run_id, t, other)
    assert store.run(c.run_id).status == "running" and store.count_stage_rows() == {}  # nothing written
    assert store.complete(c.run_id, t, make_stats(c.design.size_mm, seed=1))


def test_failed_runs_keep_errors_and_retry_up_to_the_limit(store):
    _campaign(store, 1, max_attempts=2)
    tok = new_token()
    for attempt, expect in [(1, "planned"), (2, "failed")]:
        [c] = store.claim("c", 1, "d", tok)
        assert c.attempt == attempt
        assert store.fail(c.run_id, tok, f"boom {attempt}") == expect
    assert store.claim("c", 1, "d", tok) == []
    rec = store.runs(campaign="c")[0]
    assert rec.status == "failed" and "boom 1" in rec.error and "boom 2" in rec.error
    assert store.retry_failed("c") == 1 and store.counts("c")["planned"] == 1
    [c] = store.claim("c", 1, "d", tok)
    assert store.release(c.run_id, tok) and store.run(c.run_id).attempts == 0


def test_campaign_settings_are_validated(store):
    from msmill.pipeline.campaign import run_settings_dict

    assert run_settings_dict({"max_time_s": "1.5", "seed": 3}, defaults={}) == {"max_time_s": 1.5, "seed": 3}
    with pytest.raises(MsmillInputError, match="no_such_setting"):
        run_settings_dict({"no_such_setting": 1})
    # --set adaptive=false from the command line arrives as the word: it must not become True
    assert run_settings_dict({"adaptive": "false"}, defaults={}) == {"adaptive": False}
    assert run_settings_dict({"adaptive": "True"}, defaults={}) == {"adaptive": True}
    with pytest.raises(MsmillInputError, match="adaptive"):
        run_settings_dict({"adaptive": "maybe"})
    with pytest.raises(MsmillInputError, match="start"):
        run_settings_dict({"start": "hot"})
    with pytest.raises(MsmillInputError):
        store.create_campaign("x", MACHINE, mode="half")
    store.create_campaign("x", MACHINE)
    with pytest.raises(MsmillInputError):
        store.create_campaign("x", MACHINE)
    with pytest.raises(MsmillInputError, match="campaign"):
        store.counts("nope")


# --------------------------------------------------------------------------- properties
@settings(max_examples=15, deadline=None)
@given(seed=st_.integers(0, 2**31), size_mm=st_.floats(1.0, 200.0), feed_tph=st_.floats(1.0, 100.0))
def test_any_statistics_round_trip_and_hash_ignores_provenance(tmp_path_factory, seed, size_mm, feed_tph):
    store = Store(f"sqlite:///{tmp_path_factory.mktemp('h') / 's.sqlite'}")
    stats = make_stats(size_mm, seed=seed, feed_tph=feed_tph)
    run_id, created = store.record_run(stats, MACHINE)
    assert created and store.statistics(run_id) == stats
    moved = stats.model_copy(update={"provenance": {"elsewhere": True}})
    assert store.record_run(moved, MACHINE) == (run_id, False)
    other = make_stats(size_mm, seed=seed + 1, feed_tph=feed_tph)
    assert store.record_run(other, MACHINE)[1]  # different numbers: a different run
    [row] = store.stage_table(stage=MACHINE.n_stages).query(f"run_id == {run_id}").to_dict("records")
    assert row["pass_through"] == stats.stages[-1].pass_through and row["size_mm"] == stats.design.size_mm
    store.close()


def test_outcome_comes_from_the_run_protocol_field() -> None:
    """A choked run's statistics (RunStatistics.outcome) are recorded as choked, whatever its steady-state time."""
    from msmill.pipeline.store.hashing import outcome_of

    st = make_stats(20.0)
    assert outcome_of(st) == "steady"
    assert outcome_of(st.model_copy(update={"outcome": "choked"})) == "choked"
    assert outcome_of(st.model_copy(update={"outcome": "not_steady"})) == "not_steady"
