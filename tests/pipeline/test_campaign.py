"""Campaign driver on a Dask cluster with a stand-in executor: retries, resume, no double records, CLI."""

from __future__ import annotations

import time
from typing import ClassVar

import pytest
from test_store import MACHINE, make_stats

from msmill.cli.main import run as cli
from msmill.pipeline.campaign import design_grid, run_campaign
from msmill.pipeline.store import Store
from msmill.pipeline.store.queue import new_token

FLAKY_MM, BROKEN_MM, ODD_MM = 13.0, 14.0, 17.0


def stand_in(task: dict) -> dict:
    """Executor returning synthetic statistics (no DEM): fails once at 13 mm and always at 14 mm."""
    size = task["design"]["size_mm"]
    if size == BROKEN_MM or (size == FLAKY_MM and task["attempt"] == 1):
        raise RuntimeError(f"planted failure at {size} mm, attempt {task['attempt']}")
    time.sleep(0.05)
    st = make_stats(size, seed=task["run_id"])
    outcome = "half steady" if size == ODD_MM else "steady"  # an outcome the store does not know
    return {"statistics": st.model_dump_json(), "outcome": outcome, "wall_s": 0.05, "engine": "stand-in",
            "package_version": "test", "git_commit": None, "raw_files": [], "worker": "thread"}


@pytest.fixture(scope="module")
def client():
    from distributed import Client, LocalCluster

    with LocalCluster(n_workers=2, threads_per_worker=1, processes=False, dashboard_address=":0") as cl, \
            Client(cl) as c:
        yield c


def _plan(st: Store, sizes: list[float], max_attempts: int = 2) -> None:
    st.create_campaign("c", MACHINE, run_settings={"max_time_s": 0.5}, max_attempts=max_attempts)
    st.add_points("c", design_grid(MACHINE, sizes, [30.0], [1500.0], [40.0]))


def test_campaign_runs_retries_and_never_records_twice(store, client):
    _plan(store, [10.0, 11.0, 12.0, FLAKY_MM, BROKEN_MM])
    rep = run_campaign(store, "c", client=client, executor=stand_in, heartbeat_s=0.2)
    assert rep.counts == {"planned": 0, "running": 0, "done": 4, "failed": 1}
    assert rep.recorded == 4 and rep.failed_attempts == 3  # flaky once, broken twice (the limit)
    by_size = {r.design.size_mm: r for r in store.runs(campaign="c")}
    assert by_size[FLAKY_MM].status == "done" and by_size[FLAKY_MM].attempts == 2
    assert "planted failure at 13.0 mm, attempt 1" in by_size[FLAKY_MM].error
    broken = by_size[BROKEN_MM]
    assert broken.status == "failed" and broken.error.count("RuntimeError: planted failure") == 2
    # the design stage speeds came from the grid (bottom stage twice as fast)
    assert by_size[10.0].design.stage_speeds_rpm[-1] == 3000.0
    again = run_campaign(store, "c", client=client, executor=stand_in, heartbeat_s=0.2)
    assert again.recorded == 0 and again.counts == rep.counts
    assert set(store.count_stage_rows().values()) == {MACHINE.n_stages}
    assert len(store.count_stage_rows()) == 4


def test_resume_after_a_dead_driver(store, client):
    _plan(store, [10.0, 11.0, 12.0, 15.0])
    dead = new_token()
    held = store.claim("c", 2, "driver that died", dead)
    # a live resume leaves fresh claims alone ...
    rep = run_campaign(store, "c", client=client, executor=stand_in, heartbeat_s=0.2, stale_s=3600)
    assert rep.recorded == 2 and store.counts("c")["running"] == 2
    # ... and takes them over once their heartbeat is stale
    rep = run_campaign(store, "c", client=client, executor=stand_in, heartbeat_s=0.2, stale_s=0.0)
    assert rep.replanned_stale == 2 and rep.recorded == 2
    assert store.counts("c") == {"planned": 0, "running": 0, "done": 4, "failed": 0}
    for c in held:  # the dead driver's results, if they ever arrived, are refused
        assert not store.complete(c.run_id, dead, make_stats(c.design.size_mm))
        assert store.run(c.run_id).attempts == 2


def test_max_runs_stops_early_and_gives_claims_back(store, client):
    _plan(store, [10.0, 11.0, 12.0, 15.0, 16.0])
    rep = run_campaign(store, "c", client=client, executor=stand_in, heartbeat_s=0.2, max_runs=2)
    assert rep.recorded == 2
    c = store.counts("c")
    assert c["done"] == 2 and c["running"] == 0 and c["planned"] == 3


def test_cli_create_add_status_and_bad_input(tmp_path, capsys):
    db = f"sqlite:///{tmp_path / 's.sqlite'}"
    assert cli(["campaign", "create", "k", "--db", db, "--set", "max_time_s=0.8", "--set", "seed=2"]) == 0
    assert cli(["campaign", "add", "k", "--db", db, "--size-mm", "20,30", "--feed-tph", "20,40"]) == 0
    assert "planned 4 runs" in capsys.readouterr().out
    (tmp_path / "p.csv").write_text("size_mm,feed_tph,speed_rpm,gate_deg\n20,20,1500,40\n25,20,1500,40\n")
    assert cli(["campaign", "add", "k", "--db", db, "--points", str(tmp_path / "p.csv")]) == 0
    assert "planned 1 runs (1 already" in capsys.readouterr().out
    assert cli(["campaign", "status", "k", "--db", db]) == 0
    assert "planned=5" in capsys.readouterr().out
    st = Store(db)
    # the campaign defaults (warm start from the stage table, adaptive window from the onset) are stored
    assert st.campaign("k").run_settings == {"max_time_s": 0.8, "seed": 2, "start": "table", "adaptive": True,
                                             "window_from": "onset"}
    assert {r.seed for r in st.runs(campaign="k")} == {2}
    assert cli(["campaign", "create", "bad", "--db", db, "--set", "warp=9"]) == 2
    assert cli(["campaign", "create", "near", "--db", db, "--start-from-nearest-run"]) == 0
    assert st.campaign("near").options.get("start_from_nearest_run") is True
    assert not st.campaign("k").options.get("start_from_nearest_run")
    assert cli(["campaign", "create", "cold", "--db", db, "--set", "start=empty", "--start-from-nearest-run"]) == 2
    assert "--start-from-nearest-run" in capsys.readouterr().err
    assert cli(["campaign", "status", "nope", "--db", db]) == 2
    assert cli(["campaign", "plan", "k", "--db", db, "--planner", "oracle"]) == 2  # not a registered planner
    assert cli(["db", "list", "--db", db, "--size-mm", "abc"]) == 2
    assert "error:" in capsys.readouterr().err
    assert cli(["db", "list", "--db", db, "--size-mm", "20", "--campaign", "k"]) == 0
    assert capsys.readouterr().out.strip().endswith("2 runs")  # 20 mm at 20 and 40 t/h (the CSV row was a duplicate)


def test_campaign_default_is_warm_start_and_adaptive_window(tmp_path, monkeypatch, capsys):
    """A campaign created with defaults runs every point from the stage table's hold-up with the adaptive
    window from the steady-state onset; ``--set start=empty --set adaptive=false --set window_from=detection``
    switches each off; the worker passes them to run_mill."""
    import msmill.dem.mill.run as run_mod
    from msmill.pipeline import campaign as cm

    db = f"sqlite:///{tmp_path / 's.sqlite'}"
    assert cli(["campaign", "create", "warm", "--db", db]) == 0
    assert cli(["campaign", "create", "cold", "--db", db, "--set", "start=empty", "--set", "adaptive=false",
                "--set", "window_from=detection"]) == 0
    assert cli(["campaign", "create", "bad", "--db", db, "--set", "start=hot"]) == 2
    assert "settings.start" in capsys.readouterr().err
    assert cli(["campaign", "create", "bad", "--db", db, "--set", "window_from=start"]) == 2
    assert "settings.window_from" in capsys.readouterr().err
    st = Store(db)
    assert (st.campaign("warm").run_settings == {"start": "table", "adaptive": True, "window_from": "onset"}
            == cm.CAMPAIGN_RUN_DEFAULTS)
    assert st.campaign("cold").run_settings == {"start": "empty", "adaptive": False, "window_from": "detection"}

    seen = {}

    class FakeRun:
        def __init__(self, settings):
            self.stats = type("S", (), {"run": make_stats(20.0)})()
            self.extra = {"outcome": "steady", "git_commit": None,
                          "warm_start": {"kind": "table"} if settings.start == "table" else None}
            self.wall_s = 1.0

    def fake_run_mill(machine, op, size_mm=None, mode="slice", settings=None, ore=None, **kw):
        seen["settings"] = settings
        return FakeRun(settings)

    monkeypatch.setattr(run_mod, "run_mill", fake_run_mill)
    for name, start, adaptive, window_from in (("warm", "table", True, "onset"), ("cold", "empty", False, "detection")):
        info = st.campaign(name)
        st.add_points(name, design_grid(info.machine, [20.0], [30.0], [1500.0], [40.0]))
        [claim] = st.claim(name, 1, "w", new_token())
        out = cm.execute_run(cm._task(info, claim))
        assert seen["settings"].start == start and seen["settings"].adaptive is adaptive
        assert seen["settings"].window_from == window_from
        assert out["outcome"] == "steady"


def test_cli_run_with_progress_and_resume(tmp_path, client, monkeypatch, capsys):
    import msmill.pipeline.campaign as cm

    real = cm.run_campaign
    seen = []

    def on_test_cluster(store, name, **kw):
        assert kw["n_workers"] == 2 and kw["stale_s"] == 30.0
        for k in ("scheduler", "n_workers"):
            kw.pop(k)
        wrapped = kw.pop("progress", None)

        def progress(c, rep):
            seen.append(dict(c))
            if wrapped is not None:
                wrapped(c, rep)

        return real(store, name, client=client, executor=stand_in, progress=progress, **kw)

    monkeypatch.setattr(cm, "run_campaign", on_test_cluster)
    db = f"sqlite:///{tmp_path / 's.sqlite'}"
    assert cli(["campaign", "create", "k", "--db", db]) == 0
    assert cli(["campaign", "add", "k", "--db", db, "--size-mm", "10,11,12"]) == 0
    assert cli(["campaign", "run", "k", "--db", db, "--workers", "2", "--stale-s", "30", "--heartbeat-s", "0.2"]) == 0
    assert "now done 3 failed 0 running 0 planned 0" in capsys.readouterr().out
    assert seen and seen[-1]["done"] == 3
    assert cli(["campaign", "resume", "k", "--db", db, "--workers", "2", "--stale-s", "30", "--no-progress"]) == 0
    assert "recorded 0" in capsys.readouterr().out


def test_run_on_an_existing_scheduler(store):
    from distributed import LocalCluster

    _plan(store, [10.0, 11.0])
    with LocalCluster(n_workers=1, threads_per_worker=2, processes=False, dashboard_address=":0") as cl:
        rep = run_campaign(store, "c", scheduler=cl.scheduler_address, executor=stand_in, heartbeat_s=0.2)
        assert rep.recorded == 2 and len(cl.scheduler.clients) <= 1  # the driver's client was closed


def test_an_invalid_result_is_a_failed_attempt(store, client):
    _plan(store, [10.0, ODD_MM], max_attempts=1)
    rep = run_campaign(store, "c", client=client, executor=stand_in, heartbeat_s=0.2)
    assert rep.counts["done"] == 1 and rep.counts["failed"] == 1 and rep.failed_attempts == 1
    odd = next(r for r in store.runs(campaign="c") if r.design.size_mm == ODD_MM)
    assert "invalid result" in odd.error and "half steady" in odd.error


def test_active_planner_within_campaign_domain(tmp_path) -> None:
    """The registered planner fits the store's runs and plans apart from pending points, in the size range."""
    from msmill.machine import Machine
    from msmill.model.providers import default_table_path
    from msmill.pipeline.campaign import PLANNERS
    from msmill.stageparams import StageParameterTable

    st = Store(f"sqlite:///{tmp_path / 's.sqlite'}")
    machine = Machine.default()
    for run in StageParameterTable.from_json(default_table_path()).runs:
        st.record_run(run, machine, allow_not_steady=True)  # the 20 mm re-run did not settle (docs/mill-dem.md)
    st.create_campaign("al", machine, options={"size_range_mm": [8.0, 20.0]})
    first = PLANNERS["active"](st, "al", 3)
    st.add_points("al", first)
    second = PLANNERS["active"](st, "al", 3)
    pts = [(d.size_mm, d.feed_tph, d.speed_rpm, d.gate_deg) for d in first + second]
    assert all(8.0 <= p[0] <= 20.0 and 10 <= p[1] <= 60 and 1200 <= p[2] <= 1900 and 0 <= p[3] <= 80 for p in pts)
    assert len(set(pts)) == 6  # the second batch believes the first (pending) and goes elsewhere
    assert all(d.stage_speeds_rpm[-1] == 2 * d.speed_rpm for d in first)


def test_active_planner_moves_past_a_failed_point(tmp_path) -> None:
    """A point whose attempts all failed is not proposed again (the store would drop it: the campaign
    planned nothing, round after round, behind a fine-rock point whose workers ran out of memory)."""
    from msmill.machine import Machine
    from msmill.model.providers import default_table_path
    from msmill.pipeline.campaign import PLANNERS
    from msmill.stageparams import StageParameterTable

    st = Store(f"sqlite:///{tmp_path / 's.sqlite'}")
    machine = Machine.default()
    for run in StageParameterTable.from_json(default_table_path()).runs:
        st.record_run(run, machine, allow_not_steady=True)
    st.create_campaign("al", machine, options={"size_range_mm": [8.0, 20.0]}, max_attempts=1)
    first = PLANNERS["active"](st, "al", 1)
    st.add_points("al", first)
    token = new_token()
    (claim,) = st.claim("al", 1, "w", token)
    assert st.fail(claim.run_id, token, "KilledWorker") == "failed"
    again = PLANNERS["active"](st, "al", 1)
    key = (first[0].size_mm, first[0].feed_tph, first[0].speed_rpm, first[0].gate_deg)
    assert (again[0].size_mm, again[0].feed_tph, again[0].speed_rpm, again[0].gate_deg) != key
    assert st.add_points("al", again)[0] == 1


def test_threads_per_run_reach_the_worker_and_its_kernels(store, client, monkeypatch):
    """``run_campaign(threads_per_run=2)`` hands each task 2 threads; the worker sets numba's pool to them
    (a worker that ignored the field would leave a long fine-rock run on one core)."""
    import numba

    import msmill.dem.mill.run as run_mod
    from msmill.errors import MsmillInputError
    from msmill.pipeline import campaign as cm

    def recording(task: dict) -> dict:  # Dask pickles the executor: what it saw comes back in the result
        return stand_in(task) | {"worker": f"threads={task['threads']}"}

    _plan(store, [10.0, 11.0])
    rep = run_campaign(store, "c", client=client, executor=recording, heartbeat_s=0.2, threads_per_run=2)
    assert rep.recorded == 2
    assert [r.worker for r in store.runs(campaign="c")] == ["threads=2", "threads=2"]
    with pytest.raises(MsmillInputError, match="threads_per_run"):
        run_campaign(store, "c", client=client, executor=recording, threads_per_run=0)

    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("numba's pool has one thread on this machine")
    kernels = {}

    class FakeRun:
        stats = type("S", (), {"run": make_stats(20.0)})()
        extra: ClassVar[dict] = {"outcome": "steady", "git_commit": None}
        wall_s = 1.0

    def fake_run_mill(*args, **kw):
        kernels["threads"] = numba.get_num_threads()
        return FakeRun()

    monkeypatch.setattr(run_mod, "run_mill", fake_run_mill)
    before = numba.get_num_threads()
    store.add_points("c", design_grid(MACHINE, [20.0], [30.0], [1500.0], [40.0]))
    [claim] = store.claim("c", 1, "w", new_token())
    try:
        for threads in (2, 1):
            cm.execute_run(cm._task(store.campaign("c"), claim, threads=threads))
            assert kernels["threads"] == threads
    finally:
        numba.set_num_threads(before)


def test_a_campaign_can_start_each_run_from_the_nearest_runs_residence(store, client):
    """With ``start_from_nearest_run`` a table start places the steady residence of the finished run
    nearest in the design cube (none before the first run finishes); without it the table's."""
    import json

    def recording(task: dict) -> dict:
        size = task["design"]["size_mm"]
        st = make_stats(size, seed=task["run_id"]).model_copy(update={"inlet_holdup_kg": 0.1 * size})
        seen = task["run_settings"].get("start_residence_s")
        return stand_in(task) | {"statistics": st.model_dump_json(), "worker": json.dumps(seen),
                                 "note": task["start_residence_from"]}

    store.create_campaign("c", MACHINE, run_settings={"max_time_s": 0.5, "start": "table"},
                          options={"start_from_nearest_run": True})
    store.add_points("c", design_grid(MACHINE, [10.0, 29.0], [30.0], [1500.0], [40.0]))
    assert run_campaign(store, "c", client=client, executor=recording, heartbeat_s=0.2).recorded == 2
    first = {r.design.size_mm: r for r in store.runs(campaign="c")}
    assert {r.worker for r in first.values()} == {"null"}  # nothing had finished yet
    store.add_points("c", design_grid(MACHINE, [12.0, 27.0], [30.0], [1500.0], [40.0]))
    assert run_campaign(store, "c", client=client, executor=recording, heartbeat_s=0.2).recorded == 2
    runs = {r.design.size_mm: r for r in store.runs(campaign="c")}
    for size, nearest in ((12.0, 10.0), (27.0, 29.0)):
        want = store.statistics(first[nearest].id).compartment_residence_s()
        assert json.loads(runs[size].worker) == pytest.approx(want, rel=1e-12)
        assert f"{nearest:.3g} mm" in runs[size].note
    # off by default: the same campaign without the option leaves the table's residence
    store.create_campaign("d", MACHINE, run_settings={"max_time_s": 0.5, "start": "table"})
    store.add_points("d", design_grid(MACHINE, [12.0], [30.0], [1500.0], [40.0]))
    run_campaign(store, "d", client=client, executor=recording, heartbeat_s=0.2)
    assert [r.worker for r in store.runs(campaign="d")] == ["null"]


def test_a_resumed_run_keeps_the_start_its_checkpoint_was_written_with(store, tmp_path, monkeypatch):
    """The nearest finished run may change between attempts: a worker continuing a checkpoint takes the
    residence the checkpoint's inputs hold, not the newer one, so the checkpoint still matches."""
    import pickle

    import msmill.dem.mill.run as run_mod
    from msmill.dem.checkpoint import FORMAT, STATE
    from msmill.pipeline import campaign as cm

    seen = {}

    class FakeRun:
        stats = type("S", (), {"run": make_stats(20.0)})()
        extra: ClassVar[dict] = {"outcome": "steady", "git_commit": None}
        wall_s = 1.0

    monkeypatch.setattr(run_mod, "run_mill", lambda *a, **kw: seen.update(kw) or FakeRun())
    monkeypatch.setattr(run_mod, "check_checkpoint", lambda *a, **kw: None)  # the checkpoint's other inputs
    store.create_campaign("c", MACHINE, run_settings={"start": "table"}, options={"start_from_nearest_run": True})
    store.add_points("c", design_grid(MACHINE, [20.0], [30.0], [1500.0], [40.0]))
    [claim] = store.claim("c", 1, "w", new_token())
    ckpt = tmp_path / "ckpt"
    ckpt.mkdir()
    old = [0.1, 0.2, 0.3, 0.4, 0.5, 0.6]
    with open(ckpt / STATE, "wb") as f:
        pickle.dump({"format": FORMAT, "inputs": {"settings": {"start_residence_s": old}}}, f)
    task = cm._task(store.campaign("c"), claim, start=([1.0] * 6, "the run at 21 mm")) | {"checkpoint_dir": str(ckpt)}
    out = cm.execute_run(task)
    assert seen["settings"].start_residence_s == old
    assert "21 mm" in out["note"]
    cm.execute_run(cm._task(store.campaign("c"), claim, start=([1.0] * 6, "the run at 21 mm")))  # no checkpoint
    assert seen["settings"].start_residence_s == [1.0] * 6
