"""Rotation-sense study (issue 37): the default machine's DEM with each rotation sense of the rotor pairs.

Configurations (machine files ``src/msmill/data/machines/<name>.toml``, copies of ``default.toml``
differing only in ``name``, ``description`` and ``central_sweep``): ``down_down`` (today's: every
pair counter-rotating, sweeping down through the centre), ``up_up`` (every pair sweeping up),
``down_up`` (stage 1 down, stages 2-5 up), ``up_down`` (stage 1 up, stages 2-5 down) and
``co_rotating`` (``("down", "up")`` in every stage). Each at 10, 20, 30 mm x 1250, 1850 rpm
(bottom stage at twice) x feed seeds 0, 1, 2; 30 t/h, gates 40 deg, periodic slice, the campaign's run
settings (:data:`msmill.pipeline.campaign.CAMPAIGN_RUN_DEFAULTS`: table start, adaptive window from
the onset).

Order: seed by seed (all configurations at seed 0 first), within a seed 30, 20 then 10 mm (the
cheapest first), so whatever has finished at any time is a usable dataset. Resumable: a run whose
export exists is skipped. Each run writes a small text export (no raw events) to
``OUT/<config>/<size>mm_<rpm>rpm_seed<k>/``: ``statistics.json`` (the run's
:class:`msmill.stageparams.RunStatistics`, trimmed by :func:`trim_statistics`) and
``provenance.json`` (command, msmill version, git commit, date, inputs, wall time, outcome)::

    NUMBA_NUM_THREADS=1 python scripts/rotation_sense_study.py --out benchmarks/data/rotation_sense \
        [--configs down_down up_up] [--seeds 0] [--commit-every 3]

``--headroom-m H`` runs the machine files with the roof ``H`` above the stage-1 axes instead (a pilot;
exports to ``OUT/<config>_headroom<H>m/``, so give it another ``--out``). The analysis is
:mod:`msmill.dem.mill.observations` (``python benchmarks/paper_observations.py``).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import subprocess
import sys
import time
from dataclasses import asdict
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import msmill
from msmill._version import __version__
from msmill.dem.mill.observations import CONFIGS, run_dir_name
from msmill.dem.mill.run import RunSettings, git_commit, run_mill
from msmill.errors import MsmillInputError
from msmill.machine import Machine, OperatingPoint
from msmill.pipeline.campaign import CAMPAIGN_RUN_DEFAULTS

MACHINE_DIR = Path(msmill.__file__).parent / "data" / "machines"
SIZES_MM = (30.0, 20.0, 10.0)
SPEEDS_RPM = (1250.0, 1850.0)
SEEDS = (0, 1, 2)
FEED_TPH = 30.0
GATE_DEG = 40.0
#: fields of a stage's statistics the study does not read, dropped from the export
STAGE_DROP = ("secondary_count_histogram", "secondary_count_selection", "region_weights", "region_streams")


def plan(configs: list[str], sizes_mm: list[float], speeds_rpm: list[float], seeds: list[int]
         ) -> list[tuple[str, float, float, int]]:
    """Runs ``(config, size_mm, speed_rpm, seed)`` in the study's order: seed, size, speed, configuration."""
    return [(c, size, rpm, seed) for seed in seeds for size in sizes_mm for rpm in speeds_rpm for c in configs]


def trim_statistics(stats: dict[str, Any]) -> dict[str, Any]:
    """The run's statistics without the parts the study does not read (histograms, region streams, count
    selection, filling transport); the stage streams, their sampling errors, hit probabilities, velocity
    mixtures, hold-ups, window, outcome and provenance stay."""
    out = {k: v for k, v in stats.items() if k != "filling_transport"}
    out["stages"] = [{k: v for k, v in s.items() if k not in STAGE_DROP} for s in stats["stages"]]
    return out


def _commit(repo: Path, paths: list[Path], message: str) -> None:
    """``git add`` + ``git commit --only`` of ``paths`` (three tries: another git command may hold the index)."""
    for _ in range(3):
        paths = [p.resolve() for p in paths]
        add = subprocess.run(["git", "-C", str(repo), "add", "--", *map(str, paths)], capture_output=True, text=True)
        ci = subprocess.run(["git", "-C", str(repo), "commit", "-q", "-m", message, "--", *map(str, paths)],
                            capture_output=True, text=True)
        if add.returncode == 0 and ci.returncode == 0:
            print(f"committed: {message}", flush=True)
            return
        time.sleep(5)
    print(f"commit failed ({ci.stderr.strip() or ci.stdout.strip()}); the exports stay uncommitted", flush=True)


def study_machine(config: str, headroom_m: float | None = None) -> Machine:
    """The configuration's machine file, optionally with another roof height above the stage-1 axes (m)."""
    machine = Machine.from_toml(MACHINE_DIR / f"{config}.toml")
    if headroom_m is None:
        return machine
    return Machine.from_dict({**machine.model_dump(), "headroom_m": headroom_m,
                              "name": f"{config}_headroom{headroom_m:g}m"}, source="--headroom-m")


def run_one(config: str, size_mm: float, speed_rpm: float, seed: int, out: Path,
            headroom_m: float | None = None) -> dict[str, Any]:
    """One run, exported to ``out`` (written to a temporary folder first, renamed when complete)."""
    path = MACHINE_DIR / f"{config}.toml"
    machine = study_machine(config, headroom_m)
    op = OperatingPoint(feed_tph=FEED_TPH, speed_rpm=speed_rpm, gate_deg=GATE_DEG)
    settings = RunSettings(seed=seed, **CAMPAIGN_RUN_DEFAULTS)
    run = run_mill(machine, op, size_mm=size_mm, mode="slice", settings=settings)
    stats = json.loads(run.stats.run.model_dump_json())
    prov = {
        "command": " ".join([Path(sys.argv[0]).name, *sys.argv[1:]]),
        "generator": "scripts/rotation_sense_study.py",
        "msmill_version": __version__,
        "git_commit": run.extra.get("git_commit") or git_commit(),
        "date_utc": datetime.now(UTC).isoformat(timespec="seconds"),
        "config": config,
        "machine_file": f"src/msmill/data/machines/{config}.toml",
        "machine_sha256": hashlib.sha256(path.read_bytes()).hexdigest(),
        "central_sweep": [list(p) for p in (machine.central_sweep or [])],
        "headroom_m": machine.headroom_m,
        "headroom_override_m": headroom_m,
        "inputs": {"size_mm": size_mm, "feed_tph": FEED_TPH, "speed_rpm": speed_rpm, "gate_deg": GATE_DEG,
                   "stage_speeds_rpm": op.stage_speeds(machine.n_stages), "mode": "slice", "seed": seed},
        "run_settings": asdict(settings),
        "numba_num_threads": os.environ.get("NUMBA_NUM_THREADS"),
        "wall_s": run.wall_s,
        "outcome": run.outcome,
        "steady_state_time_s": run.steady_state_time_s,
        "steady_state_detected_s": run.steady_state_detected_s,
        "window_s": list(run.window_s),
        "dt_s": run.extra.get("dt_s"),
        "raw_events": "not kept",
    }
    tmp = out.with_name(out.name + ".partial")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    (tmp / "statistics.json").write_text(json.dumps(trim_statistics(stats), indent=1) + "\n", encoding="utf-8")
    (tmp / "provenance.json").write_text(json.dumps(prov, indent=1) + "\n", encoding="utf-8")
    shutil.rmtree(out, ignore_errors=True)
    tmp.rename(out)
    return prov


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("benchmarks/data/rotation_sense"))
    ap.add_argument("--configs", nargs="+", default=list(CONFIGS))
    ap.add_argument("--sizes-mm", type=float, nargs="+", default=list(SIZES_MM))
    ap.add_argument("--speeds-rpm", type=float, nargs="+", default=list(SPEEDS_RPM))
    ap.add_argument("--seeds", type=int, nargs="+", default=list(SEEDS))
    ap.add_argument("--max-runs", type=int, default=0, help="stop after this many new runs (0: no limit)")
    ap.add_argument("--commit-every", type=int, default=0,
                    help="git-commit the exports after every N new runs (0: never); the repository of --out")
    ap.add_argument("--dry-run", action="store_true", help="print the plan and what is done, run nothing")
    ap.add_argument("--headroom-m", type=float, default=None,
                    help="pilot: the machine files with this roof height above the stage-1 axes (m); exports go "
                         "to OUT/<config>_headroom<h>m/ (use another --out than the study's)")
    args = ap.parse_args(argv)
    for c in args.configs:
        if c not in CONFIGS:
            raise MsmillInputError("--configs", c, ", ".join(CONFIGS))
        if not (MACHINE_DIR / f"{c}.toml").is_file():
            raise MsmillInputError("--configs", c, f"a machine file {MACHINE_DIR}/<name>.toml")
    if args.headroom_m is not None:
        study_machine(args.configs[0], args.headroom_m)  # a bad roof height fails here, in one line
    runs = plan(args.configs, args.sizes_mm, args.speeds_rpm, args.seeds)
    tag = "" if args.headroom_m is None else f"_headroom{args.headroom_m:g}m"
    done = [r for r in runs if (args.out / (r[0] + tag) / run_dir_name(*r[1:]) / "provenance.json").is_file()]
    print(f"{len(runs)} runs planned, {len(done)} exported already", flush=True)
    new: list[Path] = []
    n_new = 0
    for config, size, rpm, seed in runs:
        out = args.out / (config + tag) / run_dir_name(size, rpm, seed)
        if (out / "provenance.json").is_file():
            continue
        if args.dry_run:
            print(f"todo {config} {out.name}")
            continue
        t0 = time.perf_counter()
        try:
            prov = run_one(config, size, rpm, seed, out, args.headroom_m)
        except Exception as exc:  # one failed run must not end the study; it is retried on resume
            print(f"FAILED {config} {out.name}: {type(exc).__name__}: {exc}", flush=True)
            continue
        n_new += 1
        new.append(out)
        print(f"done {config} {out.name}: {prov['outcome']}, window {prov['window_s'][0]:.2f}-"
              f"{prov['window_s'][1]:.2f} s, wall {time.perf_counter() - t0:.0f} s "
              f"({datetime.now(UTC):%H:%M:%S} UTC)", flush=True)
        if args.commit_every and len(new) >= args.commit_every:
            _commit(args.out.resolve().parent, new, f"rotation_sense: {len(new)} more study exports (last "
                    f"{config} {out.name})")
            new = []
        if args.max_runs and n_new >= args.max_runs:
            break
    if args.commit_every and new:
        _commit(args.out.resolve().parent, new, f"rotation_sense: {len(new)} more study exports")


if __name__ == "__main__":
    main()
