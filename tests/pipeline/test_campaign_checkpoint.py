"""A campaign run whose worker is killed part-way through resumes from its checkpoint when re-run (issue 35)."""

from __future__ import annotations

import json
import os
import signal
import threading
import time
import warnings
from pathlib import Path

import pytest

from msmill.dem.checkpoint import has_checkpoint, read_header
from msmill.errors import OutOfDomainWarning
from msmill.machine import Machine
from msmill.pipeline.campaign import checkpoint_base, design_grid, execute_run, run_campaign
from msmill.pipeline.store import Store

MACHINE = Machine.default().model_copy(update={"n_stages": 2})
SETTINGS = dict(max_time_s=0.55, chunk_s=0.05, steady_window_s=0.1, rel_tol=0.5, trend_tol=5.0, balance_tol=5.0,
                snapshot_every_s=0.005, adaptive=True, min_measure_s=0.1, max_measure_s=0.25, check_every_s=0.05,
                checkpoint_every_s=0.0)


def _kill_after_checkpoints(run_dir: Path, pids: dict, log: dict) -> None:
    """SIGKILL the worker once the run has checkpointed a few chunks in."""
    deadline = time.monotonic() + 240
    while time.monotonic() < deadline:
        if has_checkpoint(run_dir):
            try:
                t = read_header(run_dir)["sim_time_s"]
            except Exception:  # a header read while the file is replaced
                t = 0.0
            if t >= 0.25:
                time.sleep(0.1)  # inside the next chunk
                for pid in pids.values():
                    os.kill(pid, signal.SIGKILL)
                log["killed_at_sim_s"] = t
                return
        time.sleep(0.02)


def test_a_killed_worker_is_rerun_from_its_checkpoint(tmp_path):
    from distributed import Client, LocalCluster

    store = Store(f"sqlite:///{tmp_path / 'store.sqlite'}")
    store.create_campaign("ck", MACHINE, run_settings=SETTINGS,
                          options={"checkpoint_dir": str(tmp_path / "checkpoints")})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", OutOfDomainWarning)
        store.add_points("ck", design_grid(MACHINE, [20.0], [60.0], [700.0], [40.0], bottom_speed_factor=1.0))
    base = checkpoint_base(store, store.campaign("ck"))
    assert base == tmp_path / "checkpoints"
    log: dict = {}
    one = {"NUMBA_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "PYTHONWARNINGS": "ignore"}
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=":0", env=one,
                      silence_logs=50) as cl, Client(cl) as client:
        pids = client.run(os.getpid)
        killer = threading.Thread(target=_kill_after_checkpoints, args=(base / "run000001", pids, log), daemon=True)
        killer.start()
        rep = run_campaign(store, "ck", client=client, heartbeat_s=0.5)
        killer.join(timeout=5)
    assert "killed_at_sim_s" in log, "the worker was not killed: the test did not test a resume"
    assert rep.recorded == 1 and store.counts("ck")["done"] == 1
    rec = store.runs(campaign="ck")[0]
    assert rec.attempts == 1  # Dask re-ran the task; the store saw one attempt
    assert rec.note and rec.note.startswith("resumed from its checkpoint 1 time(s)")
    prov = store.statistics(rec.id).provenance
    assert len(prov["parts"]) == 2 and prov["parts"][1]["resumed"]
    assert prov["parts"][1]["sim_from_s"] == pytest.approx(log["killed_at_sim_s"], abs=0.051)
    # the record's times are the sums over the parts, with the final statistics (after the provenance was made)
    for key in ("wall_s", "cpu_s"):
        before_stats = sum(p[key] for p in prov["parts"])
        assert prov["parts"][0][key] > 0 and before_stats <= getattr(rec, key) < before_stats + 5.0
    assert not (base / "run000001").exists()  # recorded: the checkpoint is removed
    # the resumed run's statistics are those of the same run made without interruption
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", OutOfDomainWarning)
        MACHINE.to_toml(tmp_path / "m.toml")
        plain = execute_run({"machine_toml": str(tmp_path / "m.toml"), "design": rec.design.model_dump(),
                             "mode": "slice", "run_settings": {**SETTINGS, "seed": rec.seed}, "options": {},
                             "run_id": 0, "attempt": 1, "checkpoint_dir": None})
    got, want = store.statistics(rec.id), json.loads(plain["statistics"])
    assert [json.loads(s.model_dump_json()) for s in got.stages] == want["stages"]


def test_a_checkpoint_of_other_settings_is_replaced_with_a_note(tmp_path):
    MACHINE.to_toml(tmp_path / "m.toml")
    design = design_grid(MACHINE, [20.0], [60.0], [700.0], [40.0], bottom_speed_factor=1.0)[0].model_dump()
    task = {"machine_toml": str(tmp_path / "m.toml"), "design": design, "mode": "slice",
            "run_settings": {**SETTINGS, "seed": 3}, "options": {}, "run_id": 7, "attempt": 1,
            "checkpoint_dir": str(tmp_path / "run000007")}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", OutOfDomainWarning)
        first = execute_run(task)  # leaves its final checkpoint (the driver would remove it)
        assert first["note"] is None and has_checkpoint(tmp_path / "run000007")
        again = execute_run({**task, "run_settings": {**task["run_settings"], "seed": 4}})
    assert again["note"].startswith("started afresh: checkpoint:") and "seed: 4 here, 3 in the checkpoint" in \
        again["note"]
