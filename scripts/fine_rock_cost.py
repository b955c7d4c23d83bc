"""One campaign-protocol run at a fine rock size, checkpointed, with a small text export of what it cost.

The point of issue 35: 30 t/h, 1500 rpm upper stages (bottom at twice), gates 40 deg, periodic slice,
the campaign's run settings (:data:`msmill.pipeline.campaign.CAMPAIGN_RUN_DEFAULTS`: table start,
adaptive window from the onset), feed seed 0. The run checkpoints into ``WORK/<size>mm/checkpoint``
every ``--checkpoint-every-s``; the same command after a stop continues it from there.

When the run is done it writes ``EXPORT/<size>mm/``: ``statistics.json`` (the run's per-stage
statistics with their provenance), ``cost.json`` (wall and CPU time over the run's parts, rocks in the
slice, time step, onset, settle and window lengths, engine steps and rebuilds, the step kernels' share)
and ``profile.txt`` (cProfile of ``--profile-s`` more simulated seconds of the finished scene: where
the time of a chunk goes). The raw record stays in ``WORK/<size>mm/run`` (not for git).

With ``--budget-s S`` the run stops after ``S`` seconds of wall time if it has not finished (its
checkpoint stays in ``WORK``) and writes ``cost_partial.json`` instead: the trace of wall time, CPU time,
simulated time and rocks after every engine chunk, from which ``benchmarks/fine_rock_cost.py`` takes the
cost per simulated second at the steady hold-up the table start places (a run too long for one session).

Run: ``NUMBA_NUM_THREADS=1 python scripts/fine_rock_cost.py --size-mm 4 [--work /work/fine_rock]``
"""

from __future__ import annotations

import argparse
import cProfile
import io
import json
import pstats
import sys
import time
from dataclasses import asdict
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from msmill._version import __version__
from msmill.dem.mill.run import RunSettings, git_commit, run_mill, save_run
from msmill.machine import Machine, OperatingPoint
from msmill.pipeline.campaign import CAMPAIGN_RUN_DEFAULTS

ROOT = Path(__file__).resolve().parents[1]
POINT = {"feed_tph": 30.0, "speed_rpm": 1500.0, "gate_deg": 40.0}


def cost_summary(run, started_utc: str) -> dict:
    """The run's cost figures (JSON-able)."""
    sim = run.scene.sim
    ts = run.timeseries
    win = (ts["time_s"] >= run.window_s[0]) & (ts["time_s"] <= run.window_s[1])
    parts = run.extra.get("parts", [])
    return {
        "size_mm": run.scene.size_mm, **POINT, "mode": run.scene.mode, "seed": run.settings.seed,
        "wall_s": run.wall_s, "cpu_s": run.extra.get("cpu_s"), "parts": parts,
        "rocks_in_slice_window_mean": float(ts["n_particles"][win].mean()) if win.any() else None,
        "rocks_in_slice_end": int(sim.n_particles), "dt_s": float(sim.dt_s),
        "steady_state_time_s": run.steady_state_time_s, "steady_state_detected_s": run.steady_state_detected_s,
        "window_s": list(run.window_s), "window_length_s": run.window_s[1] - run.window_s[0],
        "settle_s": run.settings.settle_s, "outcome": run.outcome,
        "window_checks": len(run.extra.get("window_checks") or []),
        "engine_steps": int(sim.stats["steps"]), "neighbour_rebuilds": int(sim.stats["rebuilds"]),
        "step_kernels_s": float(sim.stats["loop_time_s"]),
        "step_kernels_share_of_wall": float(sim.stats["loop_time_s"]) / run.wall_s if run.wall_s else None,
        "sampling_error_reached": run.stats.run.sampling_error_reached,
        "started_utc": started_utc,
    }


def profile_chunks(run, sim_s: float, top: int = 25) -> str:
    """cProfile of ``sim_s`` more simulated seconds of the finished scene, in chunks of the run."""
    sim = run.scene.sim
    kw = {"max_relative_speed_m_s": run.scene.max_impact_speed_m_s, "safety": run.settings.safety,
          "snapshot_every_s": run.settings.snapshot_every_s, "progress": False}
    prof = cProfile.Profile()
    t0, c0 = time.perf_counter(), time.process_time()
    prof.enable()
    done = 0.0
    while done < sim_s - 1e-12:
        step = min(run.settings.chunk_s, sim_s - done)
        sim.run(step, **kw)
        done += step
    prof.disable()
    out = io.StringIO()
    out.write(f"# {sim_s:g} s simulated after the run's end, {sim.n_particles} rocks: "
              f"wall {time.perf_counter() - t0:.1f} s, CPU {time.process_time() - c0:.1f} s\n")
    pstats.Stats(prof, stream=out).sort_stats("tottime").print_stats(top)
    return out.getvalue()


class _OutOfBudget(Exception):
    """The wall-time budget of a partial run is spent (its checkpoint stays)."""


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size-mm", type=float, required=True)
    ap.add_argument("--work", type=Path, default=Path("/work/fine_rock"))
    ap.add_argument("--export", type=Path, default=ROOT / "benchmarks" / "data" / "fine_rock_cost")
    ap.add_argument("--checkpoint-every-s", type=float, default=600.0)
    ap.add_argument("--profile-s", type=float, default=0.02)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--budget-s", type=float, default=None, help="stop after this much wall time (s)")
    ap.add_argument("--chunk-s", type=float, default=None, help="engine chunk (s of simulated time; default the "
                    "run settings'): a shorter one traces a partial run more finely")
    a = ap.parse_args(argv)
    tag = f"{a.size_mm:g}mm"
    work = a.work / tag
    work.mkdir(parents=True, exist_ok=True)
    started = datetime.now(UTC).isoformat(timespec="seconds")
    extra = {} if a.chunk_s is None else {"chunk_s": a.chunk_s}
    settings = RunSettings(**CAMPAIGN_RUN_DEFAULTS, seed=a.seed, checkpoint_every_s=a.checkpoint_every_s, **extra)
    out = a.export / tag
    trace: list[dict] = []
    t0 = time.perf_counter()

    def progress(t: float, n: int, phase: str) -> None:
        trace.append({"wall_s": time.perf_counter() - t0, "cpu_s": time.process_time(), "sim_s": t, "rocks": n,
                      "phase": phase})
        print(f"{datetime.now(UTC):%H:%M:%S} t={t:.3f} s rocks={n} {phase}", flush=True)
        if a.budget_s is not None and time.perf_counter() - t0 > a.budget_s:
            raise _OutOfBudget

    try:
        run = run_mill(Machine.default(), OperatingPoint(**POINT), size_mm=a.size_mm, mode="slice",
                       settings=settings, checkpoint_dir=work / "checkpoint", progress=progress)
    except _OutOfBudget:
        out.mkdir(parents=True, exist_ok=True)
        doc = {"size_mm": a.size_mm, **POINT, "complete": False, "trace": trace, "budget_s": a.budget_s,
               "provenance": {"command": " ".join(["python", "scripts/fine_rock_cost.py", *(argv or sys.argv[1:])]),
                              "msmill_version": __version__, "git_commit": git_commit(),
                              "date_utc": datetime.now(UTC).isoformat(timespec="seconds"),
                              "run_settings": asdict(settings), "machine": "default", "started_utc": started}}
        (out / "cost_partial.json").write_text(json.dumps(doc, indent=1) + "\n", encoding="utf-8")
        print(f"{tag}: stopped after {a.budget_s:g} s at t = {trace[-1]['sim_s']:.3f} s; written {out}")
        return 0
    save_run(run, work / "run")
    out.mkdir(parents=True, exist_ok=True)
    run.stats.run.to_json(out / "statistics.json")
    cost = cost_summary(run, started)
    cost["provenance"] = {"command": " ".join(["python", "scripts/fine_rock_cost.py", *(argv or sys.argv[1:])]),
                          "msmill_version": __version__, "git_commit": git_commit(),
                          "date_utc": datetime.now(UTC).isoformat(timespec="seconds"),
                          "run_settings": asdict(settings), "machine": "default"}
    (out / "cost.json").write_text(json.dumps(cost, indent=1, default=float) + "\n", encoding="utf-8")
    (out / "profile.txt").write_text(profile_chunks(run, a.profile_s), encoding="utf-8")
    print(f"{tag}: wall {cost['wall_s']:.0f} s, CPU {cost['cpu_s']:.0f} s, rocks {cost['rocks_in_slice_window_mean']}, "
          f"dt {cost['dt_s']:.3g} s, window {cost['window_length_s']:.2f} s, parts {len(cost['parts'])}; "
          f"written {out}")
    return 0 if np.isfinite(cost["wall_s"]) else 1


if __name__ == "__main__":
    raise SystemExit(main())
