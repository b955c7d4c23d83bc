"""Benchmark: a real DEM campaign that loses a worker and then its driver, and is resumed.

Campaign: the default 5-stage mill, periodic slice, 30 mm rock, 30 t/h, gates
at 30 and 45 deg, upper-stage speeds 1200-1800 rpm (8 design points by
default); short runs (``max_time_s`` 1.0, 0.1 s steady-state windows, 0.2 s
measurement window), each a few seconds to a few tens of seconds of CPU.

1. Driver in this process on a ``LocalCluster`` of 2 single-threaded worker
   processes; while a run is computing, its worker process is killed
   (SIGKILL). The driver stops after recording ``--phase1-runs`` results.
2. ``msmill campaign run`` as a child process (its own LocalCluster); once it
   has recorded one more run and holds others, the whole process group
   (driver and its workers) is killed with SIGKILL.
3. After the heartbeats went stale, ``msmill campaign resume --stale-s 5``.

Then the store is checked. Last line:
``planned=<n> done=<n> duplicates=<d> lost=<l> resumed_after_driver_kill=<yes|no>``
(duplicates: design points with more than one done run, runs whose stage
rows are not exactly one per stage, repeated content hashes; lost: planned
points without a done run).

Run: ``nice -n 5 python benchmarks/campaign_faults.py [--points 8] [--db URL] [--keep DIR]``
"""

from __future__ import annotations

import argparse
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from pathlib import Path

from msmill.machine import Machine
from msmill.pipeline.campaign import design_grid, run_campaign
from msmill.pipeline.store import Store

NAME = "faults"
SETTINGS = {"max_time_s": 1.0, "chunk_s": 0.05, "steady_window_s": 0.1, "measure_s": 0.2,
            "snapshot_every_s": 0.01, "seed": 0}


def plan(store: Store, n_points: int) -> int:
    machine = Machine.default()
    speeds = [1200.0, 1400.0, 1600.0, 1800.0, 1300.0, 1500.0, 1700.0, 1900.0]
    designs = design_grid(machine, [30.0], [30.0], speeds[: (n_points + 1) // 2], [30.0, 45.0])[:n_points]
    store.create_campaign(NAME, machine, mode="slice", run_settings=SETTINGS, max_attempts=3)
    return store.add_points(NAME, designs)[0]


def kill_a_busy_worker(client, pids: dict[str, int], log: dict) -> None:
    """SIGKILL the worker process of the first task that has been computing for >= 2 s."""
    seen: dict[str, float] = {}
    while not log.get("stop"):
        for addr, keys in client.processing().items():
            for k in keys:
                seen.setdefault(k, time.monotonic())
                if time.monotonic() - seen[k] >= 2.0 and addr in pids:
                    os.kill(pids[addr], signal.SIGKILL)  # a worker process this benchmark started
                    log.update(killed_worker=addr, killed_task=k, at=time.monotonic())
                    return
        time.sleep(0.2)


def phase1(store: Store, n_runs: int) -> dict:
    from distributed import Client, LocalCluster

    log: dict = {}
    one = {"NUMBA_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0", env=one,
                      silence_logs=50) as cl, Client(cl) as client:
        pids = client.run(os.getpid)
        killer = threading.Thread(target=kill_a_busy_worker, args=(client, pids, log), daemon=True)
        killer.start()
        rep = run_campaign(store, NAME, client=client, heartbeat_s=2.0, max_runs=n_runs)
        log["stop"] = True
    log["report"] = rep
    return log


def cli(db: str, *args: str) -> list[str]:
    return [sys.executable, "-m", "msmill", "campaign", *args, NAME, "--db", db, "--workers", "2",
            "--heartbeat-s", "2", "--no-progress"]


def phase2(store: Store, db: str, logdir: Path) -> dict:
    """Start a driver process and SIGKILL its process group once it recorded a run and holds another."""
    done0 = store.counts(NAME)["done"]
    with open(logdir / "driver.log", "w") as out:
        p = subprocess.Popen(cli(db, "run"), stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
        t0 = time.monotonic()
        while p.poll() is None and time.monotonic() - t0 < 1200:
            c = store.counts(NAME)
            if c["done"] > done0 and c["running"] > 0:
                os.killpg(p.pid, signal.SIGKILL)  # the driver and the workers it started
                break
            time.sleep(0.5)
        rc = p.wait()
    time.sleep(1.0)
    return {"returncode": rc, "killed": rc == -signal.SIGKILL, "counts_after_kill": store.counts(NAME),
            "seconds": time.monotonic() - t0}


def phase3(store: Store, db: str, logdir: Path) -> dict:
    time.sleep(6.0)  # let the dead driver's heartbeats go stale (> --stale-s 5)
    t0 = time.monotonic()
    with open(logdir / "resume.log", "w") as out:
        rc = subprocess.run([*cli(db, "resume"), "--stale-s", "5"], stdout=out, stderr=subprocess.STDOUT,
                            timeout=1800).returncode
    return {"returncode": rc, "seconds": time.monotonic() - t0}


def audit(store: Store, n_stages: int) -> dict:
    runs = store.runs(campaign=NAME)
    points = {r.design_point_id for r in runs}
    done = [r for r in runs if r.status == "done"]
    per_point = Counter(r.design_point_id for r in done)
    rows = store.count_stage_rows()
    hashes = Counter(r.content_hash for r in done if r.content_hash)
    dup = (sum(n - 1 for n in per_point.values()) + sum(1 for r in done if rows.get(r.id) != n_stages)
           + sum(n - 1 for n in hashes.values()) + sum(1 for r in runs if r.status != "done" and r.id in rows))
    return {"planned": len(points), "done": len(done), "duplicates": dup, "lost": len(points - set(per_point)),
            "attempts": Counter(r.attempts for r in runs), "outcomes": Counter(r.outcome for r in done),
            "wall_s": [round(r.wall_s or 0, 1) for r in done]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=8, help="design points (>= 6)")
    ap.add_argument("--phase1-runs", type=int, default=3, help="results recorded before phase 1 stops")
    ap.add_argument("--db", default=None, help="store URL (default: a SQLite file in a temporary folder)")
    ap.add_argument("--keep", default=None, help="keep the store and logs in this folder")
    args = ap.parse_args()
    work = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="msmill-faults-"))
    work.mkdir(parents=True, exist_ok=True)
    db = args.db or f"sqlite:///{work / 'store.sqlite'}"
    store = Store(db)
    t0 = time.monotonic()
    n = plan(store, args.points)
    print(f"store={store.url} planned {n} runs")
    p1 = phase1(store, args.phase1_runs)
    print(f"phase 1: killed worker {p1.get('killed_worker')} during {p1.get('killed_task')}; recorded "
          f"{p1['report'].recorded}, failed attempts {p1['report'].failed_attempts}; {store.counts(NAME)}")
    p2 = phase2(store, db, work)
    print(f"phase 2: driver process killed={p2['killed']} (rc {p2['returncode']}) after {p2['seconds']:.0f} s; "
          f"{p2['counts_after_kill']}")
    p3 = phase3(store, db, work)
    print(f"phase 3: resume rc {p3['returncode']} in {p3['seconds']:.0f} s; {store.counts(NAME)}")
    a = audit(store, Machine.default().n_stages)
    print(f"attempts per run {dict(a['attempts'])}; outcomes {dict(a['outcomes'])}; run wall_s {a['wall_s']}; "
          f"total {time.monotonic() - t0:.0f} s")
    resumed = p2["killed"] and p3["returncode"] == 0 and a["done"] == a["planned"]
    store.close()
    if not args.keep:
        shutil.rmtree(work, ignore_errors=True)
    print(f"planned={a['planned']} done={a['done']} duplicates={a['duplicates']} lost={a['lost']} "
          f"resumed_after_driver_kill={'yes' if resumed else 'no'}")


if __name__ == "__main__":
    main()
