"""Checkpoint and resume (issue 35): a run killed anywhere and resumed equals the uninterrupted run, bitwise.

A short two-stage slice run (about 6 s of CPU) checkpoints after every engine chunk in a child process,
which is killed with SIGKILL in the middle of a chunk, or in the middle of writing a checkpoint; the
run is resumed here and compared with the same run made without interruption in this process.
"""

from __future__ import annotations

import json
import pickle
import signal
import subprocess
import sys
import time
import warnings
from pathlib import Path

import pandas as pd
import pytest

from msmill.cli.main import run as cli
from msmill.dem import checkpoint as ckpt_mod
from msmill.dem.checkpoint import has_checkpoint, read_header
from msmill.dem.mill.run import RunSettings, resume_mill, run_mill
from msmill.errors import MsmillInputError, OutOfDomainWarning
from msmill.machine import Machine, OperatingPoint

MACHINE = Machine.default().model_copy(update={"n_stages": 2})
OP = dict(feed_tph=60, speed_rpm=700, bottom_speed_factor=1.0, gate_deg=40)
SETTINGS = dict(max_time_s=0.55, chunk_s=0.05, steady_window_s=0.1, rel_tol=0.5, trend_tol=5.0, balance_tol=5.0,
                snapshot_every_s=0.005, adaptive=True, min_measure_s=0.1, max_measure_s=0.25, check_every_s=0.05,
                checkpoint_every_s=0.0)

# the child: the same run with a checkpoint after every chunk; with argv[2] = N it is killed (SIGKILL, by
# itself) half-way through writing its N-th state file
CHILD = """
import os, signal, sys, warnings, json
from msmill.dem import checkpoint
from msmill.dem.mill.run import RunSettings, run_mill
from msmill.machine import Machine, OperatingPoint
warnings.simplefilter("ignore")
cfg = json.loads(sys.argv[1])
kill_at = int(sys.argv[2])
if kill_at:
    real, n = checkpoint._write_atomic, [0]
    def torn(path, write):
        if path.name == checkpoint.STATE:
            n[0] += 1
            if n[0] == kill_at:
                import io
                buf = io.BytesIO()
                write(buf)
                with open(path.with_name(path.name + ".tmp"), "wb") as f:
                    f.write(buf.getvalue()[: len(buf.getvalue()) // 2])
                    f.flush()
                os.kill(os.getpid(), signal.SIGKILL)
        real(path, write)
    checkpoint._write_atomic = torn
m = Machine.default().model_copy(update={"n_stages": 2})
run_mill(m, OperatingPoint(**cfg["op"]), size_mm=20.0, mode="slice", settings=RunSettings(**cfg["settings"]),
         checkpoint_dir=cfg["dir"])
"""


def _run(**kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", OutOfDomainWarning)
        return run_mill(MACHINE, OperatingPoint(**OP), size_mm=20.0, mode="slice",
                        settings=RunSettings(**{**SETTINGS, **kw.pop("settings", {})}), **kw)


def _fingerprint(run) -> dict:
    """What must be bitwise equal: every raw table, the window and the statistics (not their provenance,
    which holds dates and wall times)."""
    def digest(df: pd.DataFrame) -> str:
        return pd.util.hash_pandas_object(df, index=False).sum().item().to_bytes(8, "little", signed=False).hex()

    stats = json.loads(run.stats.run.to_json())
    stats.pop("provenance")
    return {"events": digest(run.events), "removed": digest(run.removed), "timeseries": digest(run.timeseries),
            "snapshots": digest(run.snapshots), "window_s": run.window_s, "stats": stats,
            "checks": run.extra.get("window_checks")}


@pytest.fixture(scope="module")
def reference():
    run = _run()
    return _fingerprint(run), run


def _child(d: Path, kill_at_write: int = 0) -> subprocess.Popen:
    cfg = {"op": OP, "settings": SETTINGS, "dir": str(d)}
    return subprocess.Popen([sys.executable, "-c", CHILD, json.dumps(cfg), str(kill_at_write)])


def test_killed_in_the_middle_of_a_chunk_resumes_to_the_same_run(reference, tmp_path):
    d = tmp_path / "ck"
    child = _child(d)
    try:
        deadline = time.monotonic() + 120
        while not has_checkpoint(d) and time.monotonic() < deadline:
            time.sleep(0.02)
        first = read_header(d)["sim_time_s"]
        while read_header(d)["sim_time_s"] < first + 0.2 and child.poll() is None:  # a few chunks on
            time.sleep(0.02)
        time.sleep(0.13)  # a chunk is ~0.3 s of wall time: this lands inside one
    finally:
        child.send_signal(signal.SIGKILL)
        child.wait()
    assert child.returncode == -signal.SIGKILL
    head = read_header(d)
    assert head["phase"] != "done" and 0.2 < head["sim_time_s"] < reference[0]["window_s"][1]
    run = resume_mill(d)
    assert _fingerprint(run) == reference[0]
    parts = run.extra["parts"]
    assert len(parts) == 2 and parts[1]["resumed"] and parts[1]["sim_from_s"] == head["sim_time_s"]
    assert run.wall_s == pytest.approx(sum(p["wall_s"] for p in parts))
    assert run.extra["cpu_s"] == pytest.approx(sum(p["cpu_s"] for p in parts))
    assert run.stats.run.provenance["cpu_s"] == pytest.approx(run.extra["cpu_s"], rel=0.2)


def test_killed_while_writing_a_checkpoint_resumes_from_the_one_before(reference, tmp_path):
    d = tmp_path / "ck"
    child = _child(d, kill_at_write=4)
    child.wait(timeout=300)
    assert child.returncode == -signal.SIGKILL
    assert (d / "state.pkl.tmp").stat().st_size > 0  # the torn write is there, and is not read
    head = read_header(d)
    assert head["phase"] != "done"
    run = resume_mill(d)
    assert _fingerprint(run) == reference[0]
    assert not (d / "state.pkl.tmp").exists()  # the next write replaced it


def test_a_checkpoint_of_other_settings_or_code_is_refused_in_one_line(reference, tmp_path, monkeypatch):
    d = tmp_path / "ck"
    _run(checkpoint_dir=d)  # leaves its final checkpoint
    with pytest.raises(MsmillInputError, match=r"seed: 0 here, 1 in the checkpoint|seed: 1 here, 0") as err:
        _run(settings={"seed": 1}, checkpoint_dir=d)
    assert "\n" not in str(err.value)
    # the same inputs continue from it (here: it is finished, so only the statistics are computed)
    assert _fingerprint(_run(checkpoint_dir=d)) == reference[0]
    monkeypatch.setattr("msmill.dem.mill.run.code_digest", lambda: "0" * 16)
    with pytest.raises(MsmillInputError, match="a checkpoint of this code") as err:
        resume_mill(d)
    assert "\n" not in str(err.value)


def test_append_only_lists_are_written_once_and_torn_segments_ignored(tmp_path):
    d = tmp_path / "w"
    items: list = [1, 2]
    state = {"items": items, "other": [9]}
    w = ckpt_mod.CheckpointWriter(d)
    w.write({"kind": "t"}, state, {"items": items})
    items += [3, 4, 5]
    w.write({"kind": "t"}, state, {"items": items})
    segs = sorted(p.name for p in (d / "seg").iterdir())
    assert segs == ["items.000000000-000000002.pkl", "items.000000002-000000005.pkl"]
    (d / "seg" / "items.000000005-000000009.pkl").write_bytes(b"torn")  # a write cut off before its state
    head, back = ckpt_mod.read_checkpoint(d)
    assert back == state and head["segments"]["items"][-1] == ("items.000000002-000000005.pkl", 3)
    w2 = ckpt_mod.CheckpointWriter(d, head["segments"])
    back["items"].append(6)
    w2.write({"kind": "t"}, back, {"items": back["items"]})
    assert not (d / "seg" / "items.000000005-000000009.pkl").exists()
    assert ckpt_mod.read_checkpoint(d)[1]["items"] == [1, 2, 3, 4, 5, 6]
    with pytest.raises(RuntimeError, match="shrank"):
        w2.write({"kind": "t"}, {}, {"items": [1]})
    (d / "state.pkl").write_bytes(pickle.dumps({"format": 99}))
    with pytest.raises(MsmillInputError, match="format"):
        read_header(d)


def test_cli_resume_refuses_other_options_and_folders_without_a_checkpoint(tmp_path, capsys):
    d = tmp_path / "out"
    (d / "checkpoint").mkdir(parents=True)
    assert cli(["dem", "run", "--resume", str(d)]) == 2
    assert "has no checkpoint/state.pkl" in capsys.readouterr().err
    assert cli(["dem", "run", "--resume", str(d), "--feed-tph", "40"]) == 2
    err = capsys.readouterr().err
    assert "--feed-tph" in err and "nothing with --resume" in err and err.count("\n") == 1
    assert cli(["dem", "run", "--size-mm", "20", "--out", str(d)]) == 2  # no machine
    assert "MACHINE_TOML" in capsys.readouterr().err


def test_cli_refuses_to_overwrite_a_stopped_runs_checkpoint(reference, tmp_path, capsys):
    d = tmp_path / "out"
    _run(checkpoint_dir=d / "checkpoint")
    MACHINE.to_toml(tmp_path / "m.toml")
    assert cli(["dem", "run", str(tmp_path / "m.toml"), "--size-mm", "20", "--out", str(d), "--slice"]) == 2
    assert "--resume" in capsys.readouterr().err
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", OutOfDomainWarning)
        code = cli(["dem", "run", "--resume", str(d), "--no-progress"])
    assert code == 0, capsys.readouterr().err
    assert (d / "statistics.json").is_file() and not (d / "checkpoint").exists()
    saved = json.loads((d / "statistics.json").read_text())
    assert saved["stages"] == reference[0]["stats"]["stages"]
    capsys.readouterr()
    assert cli(["dem", "stats", str(d)]) == 0  # says the outcome and what the window missed, in one line
    line = [x for x in capsys.readouterr().out.splitlines() if x.startswith("outcome:")]
    assert len(line) == 1 and line[0].startswith(f"outcome: {saved['outcome']}; window 0.25 s")
    assert "every sampling target met" in line[0] or "above their targets" in line[0]
