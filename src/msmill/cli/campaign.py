"""``msmill campaign``: plan and run batches of DEM runs on Dask, resumable after crashes."""

from __future__ import annotations

import csv
from pathlib import Path
from typing import Annotated

import typer

from msmill.cli.db import DbOpt, open_store
from msmill.errors import MsmillInputError

app = typer.Typer(help="Campaigns of DEM runs in the store, executed on Dask (local or a cluster).",
                  no_args_is_help=True)

NameArg = Annotated[str, typer.Argument(help="Campaign name.")]
SchedOpt = Annotated[str | None, typer.Option("--scheduler", help="Address of a running Dask scheduler.")]
WorkersOpt = Annotated[int | None, typer.Option("--workers", help="Local worker processes (default: cores).")]
StaleOpt = Annotated[float, typer.Option("--stale-s", help="Heartbeat age after which a running run is re-planned (s).")]
MaxRunsOpt = Annotated[int | None, typer.Option("--max-runs", help="Stop after recording this many runs.")]
HeartOpt = Annotated[float, typer.Option("--heartbeat-s", help="Heartbeat interval of held runs (s).")]
ThreadsOpt = Annotated[int, typer.Option("--threads-per-run", help="Numba threads of each run's step kernels; "
                                         "local workers default to the cores over this.")]
QuietOpt = Annotated[bool, typer.Option("--no-progress", help="No progress bar.")]


def _floats(name: str, text: str) -> list[float]:
    try:
        return [float(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise MsmillInputError(name, text, "comma-separated numbers") from None


def _settings(items: list[str]) -> dict[str, object]:
    import tomllib

    out: dict[str, object] = {}
    for it in items:
        key, sep, val = it.partition("=")
        if not sep:
            raise MsmillInputError("--set", it, "KEY=VALUE with a RunSettings field")
        try:
            out[key.strip()] = tomllib.loads(f"v = {val.strip()}")["v"]
        except tomllib.TOMLDecodeError:
            out[key.strip()] = val.strip()
    return out


@app.command("create")
def create_cmd(
    name: NameArg,
    machine_toml: Annotated[str, typer.Option("--machine", help="Machine TOML or 'default'.")] = "default",
    full: Annotated[bool, typer.Option("--full", help="Full mill instead of a periodic slice.")] = False,
    set_: Annotated[list[str] | None, typer.Option(
        "--set", help="RunSettings field, KEY=VALUE (repeatable); campaigns default to start=table (warm start "
                      "from the stage table's hold-up) and adaptive=true.")] = None,
    max_attempts: Annotated[int, typer.Option("--max-attempts", help="Attempts per run before it fails.")] = 3,
    ore: Annotated[str | None, typer.Option("--ore", help="Ore (rock material) name.")] = None,
    raw_dir: Annotated[Path | None, typer.Option("--raw-dir", help="Workers save raw run folders here.")] = None,
    checkpoint_dir: Annotated[str | None, typer.Option(
        "--checkpoint-dir", help="Workers checkpoint their runs here (one folder per run; on a cluster, a file "
        "system every worker shares), so a re-claimed run continues; 'none': no checkpoints. Default: a folder "
        "per store and campaign under ~/.local/share/msmill/checkpoints. Interval: --set checkpoint_every_s=S.")]
    = None,
    size_range_mm: Annotated[tuple[float, float] | None, typer.Option(
        "--size-range-mm", help="Rock sizes the active-learning planner may choose (mm), LOW HIGH; "
                                "default the paper's 2-30 mm.")] = None,
    max_run_hours: Annotated[float | None, typer.Option(
        "--max-run-hours", help="The planner chooses no point whose expected wall time (the cost model learnt "
                                "from the runs) exceeds this (h); default no cap.")] = None,
    start_from_nearest_run: Annotated[bool, typer.Option(
        "--start-from-nearest-run", help="A table start places the steady residence per compartment of the "
        "finished run nearest in the design cube instead of the stage table's (docs/mill-dem.md); fine rock "
        "then starts near its steady hold-up.")] = False,
    db: DbOpt = None,
) -> None:
    """Create a campaign: machine, slice/full and the DEM run settings."""
    from msmill.dem.mill.checks import check_run_inputs
    from msmill.dem.mill.run import RunSettings
    from msmill.machine import Machine
    from msmill.pipeline.campaign import run_settings_dict
    from msmill.pipeline.store.queue import check_campaign_name

    check_campaign_name(name)
    machine = Machine.default() if machine_toml == "default" else Machine.from_toml(Path(machine_toml))
    settings = run_settings_dict(_settings(set_ or []))
    check_run_inputs(machine, RunSettings(**settings))  # bad settings fail here, not when the runs execute
    if ore is not None:
        from msmill.ore import list_ores

        if ore not in list_ores():
            raise MsmillInputError("--ore", ore, "one of " + ", ".join(list_ores()))
    opts = {"ore": ore, "raw_dir": str(raw_dir.resolve()) if raw_dir else None,
            "checkpoint_dir": None if checkpoint_dir is None else
            "none" if checkpoint_dir.strip().lower() == "none" else str(Path(checkpoint_dir).resolve())}
    if start_from_nearest_run:
        if settings.get("start") != "table":
            raise MsmillInputError("--start-from-nearest-run", True, "a campaign whose runs start from the table "
                                   "(--set start=table, the default)")
        opts["start_from_nearest_run"] = True
    if opts["checkpoint_dir"] is not None and not checkpoint_dir.strip():
        raise MsmillInputError("--checkpoint-dir", checkpoint_dir, "a folder path or 'none'")
    if size_range_mm is not None:
        lo, hi = size_range_mm
        if not 0 < lo < hi:
            raise MsmillInputError("--size-range-mm", f"{lo} {hi}", "two sizes 0 < LOW < HIGH (mm)")
        opts["size_range_mm"] = [lo, hi]
    if max_run_hours is not None:
        if not max_run_hours > 0:
            raise MsmillInputError("--max-run-hours", max_run_hours, "a positive number of hours")
        opts["max_run_hours"] = float(max_run_hours)
    info = open_store(db).create_campaign(name, machine, mode="full" if full else "slice",
                                          run_settings=settings,
                                          max_attempts=max_attempts, options={k: v for k, v in opts.items() if v})
    typer.echo(f"campaign {info.name}: machine {info.machine_hash[:12]}, {info.mode}, settings {info.run_settings}")


@app.command("add")
def add_cmd(
    name: NameArg,
    size_mm: Annotated[str | None, typer.Option(help="Rock sizes (mm), comma-separated.")] = None,
    feed_tph: Annotated[str, typer.Option(help="Feed rates (t/h), comma-separated.")] = "30",
    speed_rpm: Annotated[str, typer.Option(help="Upper-stage speeds (rpm), comma-separated.")] = "1500",
    gate_deg: Annotated[str, typer.Option(help="Gate angles (deg), comma-separated.")] = "40",
    bottom_factor: Annotated[float, typer.Option(help="Bottom / upper stage speed.")] = 2.0,
    points: Annotated[Path | None, typer.Option("--points", help="CSV: size_mm,feed_tph,speed_rpm,gate_deg.")] = None,
    db: DbOpt = None,
) -> None:
    """Plan runs: the grid of the given values and/or the rows of a CSV file (duplicates skipped)."""
    from msmill.pipeline.campaign import design_grid

    st = open_store(db)
    machine = st.campaign(name).machine
    designs = []
    if size_mm is not None:
        designs += design_grid(machine, _floats("--size-mm", size_mm), _floats("--feed-tph", feed_tph),
                               _floats("--speed-rpm", speed_rpm), _floats("--gate-deg", gate_deg), bottom_factor)
    if points is not None:
        with points.open(newline="", encoding="utf-8") as f:
            for row in csv.DictReader(f):
                try:
                    designs += design_grid(machine, [float(row["size_mm"])], [float(row["feed_tph"])],
                                           [float(row["speed_rpm"])], [float(row["gate_deg"])], bottom_factor)
                except (KeyError, ValueError):
                    raise MsmillInputError(str(points), row, "columns size_mm,feed_tph,speed_rpm,gate_deg") from None
    if not designs:
        raise MsmillInputError("points", "none", "--size-mm values or a --points CSV")
    added, existing = st.add_points(name, designs)
    typer.echo(f"planned {added} runs ({existing} already in the campaign)")


@app.command("plan")
def plan_cmd(
    name: NameArg,
    n: Annotated[int, typer.Option("--n", help="Number of new design points.")] = 4,
    planner: Annotated[str, typer.Option(help="Planner name (registered in msmill.pipeline.campaign.PLANNERS).")]
    = "active",
    cost_power: Annotated[float, typer.Option(
        "--cost-power", help="Exponent of the expected DEM cost in the acquisition (0: ignore cost; 1: "
                             "variance per second of DEM).")] = 1.0,
    seed: Annotated[int, typer.Option("--seed", help="Seed of the candidate design.")] = 0,
    db: DbOpt = None,
) -> None:
    """Let a planner (the surrogate's active learning) choose the next design points."""
    from msmill.pipeline import campaign as cm

    if planner not in cm.PLANNERS:
        raise MsmillInputError("--planner", planner, ", ".join(sorted(cm.PLANNERS)) or "no planner installed yet")
    st = open_store(db)
    if not 0 <= cost_power <= 4:
        raise MsmillInputError("--cost-power", cost_power, "a number 0-4")
    kwargs = {"cost_power": cost_power, "seed": seed} if planner == "active" else {}
    added, existing = st.add_points(name, cm.PLANNERS[planner](st, name, n, **kwargs))
    typer.echo(f"planned {added} runs ({existing} already in the campaign)")


def _execute(name: str, db: str | None, scheduler: str | None, workers: int | None, stale_s: float,
             heartbeat_s: float, max_runs: int | None, retry_failed: bool, no_progress: bool,
             threads_per_run: int = 1) -> None:
    from msmill.pipeline.campaign import run_campaign

    if threads_per_run < 1:
        raise MsmillInputError("--threads-per-run", threads_per_run, "an integer >= 1")
    st = open_store(db)
    st.campaign(name)  # fails early on an unknown name
    kw = {"scheduler": scheduler, "n_workers": workers, "stale_s": stale_s, "heartbeat_s": heartbeat_s,
          "max_runs": max_runs, "retry_failed": retry_failed, "threads_per_run": threads_per_run}
    if no_progress:
        rep = run_campaign(st, name, **kw)
    else:
        from rich.progress import (
            BarColumn,
            Progress,
            TextColumn,
            TimeElapsedColumn,
            TimeRemainingColumn,
        )

        with Progress(TextColumn("{task.description}"), BarColumn(), TextColumn("{task.fields[info]}"),
                      TimeElapsedColumn(), TextColumn("left"), TimeRemainingColumn()) as bar:
            c0 = st.counts(name)
            task = bar.add_task(name, total=sum(c0.values()), completed=c0["done"] + c0["failed"], info="")

            def cb(c: dict[str, int], _rep: object) -> None:
                bar.update(task, total=sum(c.values()), completed=c["done"] + c["failed"],
                           info=f"done {c['done']} running {c['running']} failed {c['failed']} "
                                f"planned {c['planned']}")

            rep = run_campaign(st, name, progress=cb, **kw)
    c = rep.counts
    typer.echo(f"{name}: recorded {rep.recorded}, failed attempts {rep.failed_attempts}, re-planned stale "
               f"{rep.replanned_stale}, {rep.elapsed_s:.0f} s; now done {c['done']} failed {c['failed']} "
               f"running {c['running']} planned {c['planned']}")


@app.command("run")
def run_cmd(name: NameArg, db: DbOpt = None, scheduler: SchedOpt = None, workers: WorkersOpt = None,
            stale_s: StaleOpt = 120.0, heartbeat_s: HeartOpt = 10.0, max_runs: MaxRunsOpt = None,
            no_progress: QuietOpt = False, threads_per_run: ThreadsOpt = 1) -> None:
    """Execute the campaign's planned runs on Dask until none is left."""
    _execute(name, db, scheduler, workers, stale_s, heartbeat_s, max_runs, False, no_progress, threads_per_run)


@app.command("resume")
def resume_cmd(
    name: NameArg, db: DbOpt = None, scheduler: SchedOpt = None, workers: WorkersOpt = None,
    stale_s: StaleOpt = 120.0, heartbeat_s: HeartOpt = 10.0, max_runs: MaxRunsOpt = None,
    retry_failed: Annotated[bool, typer.Option("--retry-failed", help="Also retry runs that failed.")] = False,
    no_progress: QuietOpt = False, threads_per_run: ThreadsOpt = 1,
) -> None:
    """Continue after a crash: re-plan runs with a stale heartbeat, then run what is planned."""
    _execute(name, db, scheduler, workers, stale_s, heartbeat_s, max_runs, retry_failed, no_progress,
             threads_per_run)


@app.command("status")
def status_cmd(name: NameArg, db: DbOpt = None) -> None:
    """Runs of a campaign per status, and the last error of each failed run."""
    st = open_store(db, create=False)
    info = st.campaign(name)
    c = st.counts(name)
    typer.echo(f"{name}: machine {info.machine_hash[:12]}, {info.mode}, max attempts {info.max_attempts}")
    typer.echo(" ".join(f"{k}={v}" for k, v in c.items()) + f" total={sum(c.values())}")
    for r in st.runs(campaign=name):
        if r.status in ("failed", "running") or (r.error and r.status == "planned"):
            last = (r.error or "").strip().splitlines()[-1:] or [""]
            typer.echo(f"run {r.id} {r.status} attempts {r.attempts} worker {r.worker or '-'}: {last[0][:160]}")
        elif r.note:
            typer.echo(f"run {r.id} {r.status}: {r.note[:160]}")


@app.command("report")
def report_cmd(
    export: Annotated[Path | None, typer.Option(
        "--export", help="Campaign export folder (default: the packaged msmill/data/campaigns/default).")] = None,
    surrogate: Annotated[Path | None, typer.Option("--surrogate", help="Surrogate JSON (default: the shipped one).")]
    = None,
    envelope: Annotated[Path | None, typer.Option("--envelope", help="Envelope JSON (default: the shipped one).")]
    = None,
    out: Annotated[Path | None, typer.Option(
        "--out", help="Markdown file (default: docs/campaign-results.md of the checkout); figures go to img/ "
                      "beside it.")] = None,
    no_learning_curve: Annotated[bool, typer.Option(
        "--no-learning-curve", help="Skip the learning curve (ten surrogate fits: minutes; the rest takes "
                                    "seconds).")] = False,
) -> None:
    """Write the campaign's results page (docs/campaign-results.md) and its figures from the export."""
    from msmill.cli.campaign_report import write_campaign_report

    write_campaign_report(export, surrogate, envelope, out, echo=typer.echo, with_learning_curve=not no_learning_curve)
