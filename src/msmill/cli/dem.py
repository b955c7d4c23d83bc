"""``msmill dem``: run the mill DEM at one design point and (re)compute its statistics."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path
from typing import Annotated, Any

import typer

from msmill.errors import MsmillInputError
from msmill.validate import number

EXIT_NOT_STEADY = 3  # the run ended at its time limit without steady state
EXIT_CHOKED = 4  # the mill did not pass the feed rate (product persistently below feed)

app = typer.Typer(help="DEM of the multi-shaft mill: run to steady state, per-stage statistics.",
                  no_args_is_help=True)


#: where ``msmill dem run --out DIR`` keeps its checkpoint while it runs (removed once the outputs are written)
CHECKPOINT_SUBDIR = "checkpoint"
#: options ``--resume`` accepts besides itself (the rest come from the checkpoint)
_RESUME_OPTIONS = {"resume", "checkpoint_every_s", "no_progress", "vtk"}


@app.command("run", epilog="Exit status: 0 steady; 2 bad input; 3 not steady by the time limit; 4 choked "
                           "(statistics are written and marked in 3 and 4).")
def run_cmd(
    ctx: typer.Context,
    machine_toml: Annotated[Path | None, typer.Argument(
        help="Machine description (TOML); 'default' for the shipped one (not with --resume).")] = None,
    size_mm: Annotated[float | None, typer.Option("--size-mm", help="Rock diameter (mm).")] = None,
    out: Annotated[Path | None, typer.Option("--out", help="Output directory.")] = None,
    feed_tph: Annotated[float, typer.Option("--feed-tph", help="Feed rate of the full mill (t/h).")] = 30.0,
    speed_rpm: Annotated[float, typer.Option("--speed-rpm", help="Upper-stage shaft speed (rpm).")] = 1500.0,
    bottom_factor: Annotated[float, typer.Option("--bottom-factor", help="Bottom / upper stage speed.")] = 2.0,
    gate_deg: Annotated[float, typer.Option("--gate-deg", help="Gate angle below horizontal (deg).")] = 40.0,
    slice_: Annotated[bool, typer.Option("--slice", help="Periodic slice one flinger row long (cheap).")] = False,
    max_time_s: Annotated[float | None, typer.Option(
        "--max-time-s", help="Give up waiting for steady state (s); default scales with the residence time.")] = None,
    measure_s: Annotated[float, typer.Option("--measure-s", help="Measurement window after steady state (s).")] = 0.5,
    seed: Annotated[int, typer.Option("--seed", help="Seed of the feed source.")] = 0,
    feed_speed_m_s: Annotated[float, typer.Option(
        "--feed-speed-m-s", help="Downward speed of the fed rock in the chute (m/s); the feed source can place "
        "more rock per second the faster it is (capacity probes above ~250 t/h need more than the default).")] = 2.0,
    vtk: Annotated[bool, typer.Option("--vtk", help="Also write the final particles as VTU.")] = False,
    no_progress: Annotated[bool, typer.Option("--no-progress", help="No progress bar.")] = False,
    adaptive: Annotated[bool, typer.Option(
        "--adaptive", help="Measure until the sampling errors reach the run settings' targets.")] = False,
    max_measure_s: Annotated[float | None, typer.Option(
        "--max-measure-s", help="With --adaptive: longest measurement window (s); default 30 "
        "(coarse rock needs long windows for 500 impacts per stage).")] = None,
    warm_start: Annotated[Path | None, typer.Option(
        "--warm-start", help="Start from the hold-up of this finished run (same gate and slice).")] = None,
    start: Annotated[str, typer.Option(
        "--start", help="empty: start from an empty mill; table: from the default stage table's expected "
        "hold-up (what campaign runs do). --warm-start takes precedence.")] = "empty",
    window_from: Annotated[str, typer.Option(
        "--window-from", help="detection: measure from the time steady state is detected; onset: from its "
        "onset (the two steady windows are not simulated again; what campaign runs do).")] = "detection",
    checkpoint_every_s: Annotated[float, typer.Option(
        "--checkpoint-every-s", help="Wall time between checkpoints (s), kept in OUT/checkpoint while the run "
        "lasts: a run that is stopped continues with --resume OUT, losing at most this much work.")] = 600.0,
    backend: Annotated[str, typer.Option(
        "--backend", help="Step kernels: cpu (numba, the default), cuda (NVIDIA Warp on the GPU; "
        "pip install 'msmill\\[gpu]'), warp-cpu (the Warp kernels on the CPU, for checks).")] = "cpu",
    resume: Annotated[Path | None, typer.Option(
        "--resume", help="Continue the stopped run whose --out was this folder from its checkpoint, with the "
        "settings it was started with (only --checkpoint-every-s, --vtk and --no-progress may be given).")] = None,
) -> None:
    """Run the mill DEM to steady state, record a window, write events, statistics and plots."""
    from msmill.cli.output import atomic_output, check_writable
    from msmill.dem.checkpoint import has_checkpoint, remove_checkpoint
    from msmill.dem.mill.run import resume_mill, run_mill, save_run

    if resume is not None:
        given = sorted(k for k, v in ctx.params.items() if k not in _RESUME_OPTIONS
                       and getattr(ctx.get_parameter_source(k), "name", "") == "COMMANDLINE")
        if given:
            raise MsmillInputError(_option(ctx, given[0]), ctx.params[given[0]],
                                   "nothing with --resume (the run continues with its checkpoint's settings)")
        out = check_writable(resume, "--resume")
        ckpt = out / CHECKPOINT_SUBDIR
        if not has_checkpoint(ckpt):
            raise MsmillInputError("--resume", str(resume), "the --out folder of a stopped 'msmill dem run' "
                                   f"(it has no {CHECKPOINT_SUBDIR}/state.pkl)")
        number(checkpoint_every_s, "--checkpoint-every-s", unit="s", ge=0)
        inputs = _checkpoint_inputs(ckpt)
        result = _with_progress(no_progress, inputs["size_mm"], inputs["settings"],
                                lambda cb: resume_mill(ckpt, progress=cb, checkpoint_every_s=checkpoint_every_s))
        run_settings = {"resumed_from": str(ckpt), **inputs["settings"]}
        inputs_files: list[Path] = []
    else:
        machine, op, settings, warm, out = _fresh_inputs(
            machine_toml, size_mm, out, feed_tph, speed_rpm, bottom_factor, gate_deg, max_time_s, measure_s, seed,
            adaptive, max_measure_s, feed_speed_m_s, start, window_from, checkpoint_every_s, warm_start,
            backend)
        ckpt = out / CHECKPOINT_SUBDIR
        if has_checkpoint(ckpt):
            raise MsmillInputError("--out", str(out), f"a folder without the checkpoint of a stopped run (continue "
                                   f"it with 'msmill dem run --resume {out}', or delete {ckpt})")
        mode = "slice" if slice_ else "full"
        result = _with_progress(no_progress, size_mm, asdict(settings),
                                lambda cb: run_mill(machine, op, size_mm=size_mm, mode=mode, settings=settings,
                                                    progress=cb, start=warm, checkpoint_dir=ckpt))
        run_settings = {"size_mm": size_mm, "mode": mode, "operating_point": op.model_dump(), "seed": seed,
                        "max_time_s": max_time_s, "measure_s": measure_s, "vtk": vtk, "start": start,
                        "window_from": window_from, "adaptive": adaptive, "backend": backend}
        inputs_files = [] if str(machine_toml) == "default" else [machine_toml]
    from msmill.plots.dem import plot_run

    with atomic_output(out, inputs=inputs_files, settings=run_settings) as stage:
        save_run(result, stage, vtk=vtk)
        plot_run(result, stage)
    remove_checkpoint(ckpt)  # the outputs are in place: the run is complete
    st = result.stats.run if result.stats else None
    ss = result.steady_state_time_s
    parts = len(result.extra.get("parts", [])) or 1
    typer.echo(f"steady state: {'not reached' if ss is None else f'{ss:.2f} s'}; window "
               f"{result.window_s[0]:.2f}-{result.window_s[1]:.2f} s; wall {result.wall_s:.1f} s, CPU "
               f"{result.extra.get('cpu_s', float('nan')):.1f} s" + (f" in {parts} parts" if parts > 1 else "")
               + f"; dt {result.extra['dt_s']:.3g} s")
    if st is not None:
        typer.echo(f"tau = {st.characteristic_time_s:.4f} s; mass out {st.mass_out_rate_kg_s:.3f} kg/s "
                   f"({100 * st.mass_out_rate_kg_s / result.scene.feed_kg_s:.0f} % of feed); written to {out}")
    if result.outcome != "steady":
        # statistics are written but marked; ingest refuses them unless explicitly allowed
        msg = result.verdict.message if result.verdict else result.outcome
        typer.echo(f"error: {result.outcome} after {result.window_s[1]:.2f} s (limit "
                   f"{result.extra['time_limit_s']:.2f} s): {msg}; statistics marked '{result.outcome}'", err=True)
        raise typer.Exit(code=EXIT_CHOKED if result.outcome == "choked" else EXIT_NOT_STEADY)


def _option(ctx: typer.Context, name: str) -> str:
    """The command-line spelling of a parameter (``--feed-tph``, or the argument's name)."""
    for p in ctx.command.params:
        if p.name == name:
            return max(p.opts, key=len) if p.opts else name
    return name


def _fresh_inputs(machine_toml: Path | None, size_mm: float | None, out: Path | None, feed_tph: float,
                  speed_rpm: float, bottom_factor: float, gate_deg: float, max_time_s: float | None,
                  measure_s: float, seed: int, adaptive: bool, max_measure_s: float | None, feed_speed_m_s: float,
                  start: str, window_from: str, checkpoint_every_s: float, warm_start: Path | None,
                  backend: str = "cpu") -> tuple:
    """Machine, operating point, settings, warm start and output folder of a new run, every one checked
    (and --out probed for writing) before the (long) simulation starts."""
    from msmill.cli.output import check_writable
    from msmill.dem.backend import check_backend
    from msmill.dem.mill.checks import check_run_inputs
    from msmill.dem.mill.run import RunSettings
    from msmill.machine import Machine, OperatingPoint

    if machine_toml is None:
        raise MsmillInputError("MACHINE_TOML", None, "a machine TOML file or 'default' (or --resume DIR)")
    if size_mm is None:
        raise MsmillInputError("--size-mm", None, "a rock diameter (mm)")
    if out is None:
        raise MsmillInputError("--out", None, "an output folder")
    machine = Machine.default() if str(machine_toml) == "default" else Machine.from_toml(machine_toml)
    try:
        op = OperatingPoint(feed_tph=feed_tph, speed_rpm=speed_rpm, bottom_speed_factor=bottom_factor,
                            gate_deg=gate_deg)
    except MsmillInputError as exc:  # name the options as typed
        names = {"feed_tph": "--feed-tph", "speed_rpm": "--speed-rpm", "bottom_speed_factor": "--bottom-factor",
                 "gate_deg": "--gate-deg"}
        field = "/".join(names.get(f, f) for f in exc.field.split("/"))
        raise MsmillInputError(field, exc.value, exc.allowed) from None
    extra = {} if max_measure_s is None else {"max_measure_s": max_measure_s}
    settings = RunSettings(max_time_s=max_time_s or 0.0, measure_s=measure_s, seed=seed, adaptive=adaptive,
                           feed_speed_m_s=feed_speed_m_s, start=start, window_from=window_from,
                           checkpoint_every_s=checkpoint_every_s, backend=backend, **extra)
    check_backend(backend, "--backend")  # this machine runs it: Warp installed, a GPU for cuda
    check_run_inputs(machine, settings, size_mm)
    out = check_writable(out, "--out")
    warm = None
    if warm_start is not None:
        from msmill.dem.mill.warmstart import WarmStart

        warm = WarmStart.from_dir(warm_start)
    return machine, op, settings, warm, out


def _checkpoint_inputs(ckpt: Path) -> dict:
    from msmill.dem.checkpoint import read_header

    return read_header(ckpt)["inputs"]


def _with_progress(no_progress: bool, size_mm: float | None, settings: dict, go: Callable) -> Any:
    """``go(callback)`` with a progress bar over the run's longest simulated time (or none)."""
    if no_progress:
        return go(None)
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    from msmill.dem.mill.run import RunSettings

    rs = RunSettings(**{k: v for k, v in settings.items() if k in RunSettings.__dataclass_fields__})
    with Progress(TextColumn("{task.description}"), BarColumn(), TextColumn("{task.fields[info]}"),
                  TimeElapsedColumn()) as bar:
        window_s = rs.max_measure_s if rs.adaptive else rs.measure_s  # an adaptive window may end sooner
        task = bar.add_task("DEM", total=rs.time_limit_s(size_mm or 10.0) + window_s, info="")

        def cb(t: float, n: int, phase: str) -> None:
            bar.update(task, completed=t, info=f"t={t:.2f} s  particles={n}  {phase}")

        return go(cb)


@app.command("stats")
def stats_cmd(
    run_dir: Annotated[Path, typer.Argument(help="Directory written by 'msmill dem run'.")],
    out: Annotated[Path | None, typer.Option("--out", help="JSON file (default RUN_DIR/statistics.json).")] = None,
) -> None:
    """Recompute the per-stage statistics of a saved run from its raw events and snapshots."""
    from msmill.cli.output import atomic_output, atomic_write_bytes, check_writable
    from msmill.dem.mill.run import stats_from_dir
    from msmill.plots.dem import plot_stage_impacts

    if not run_dir.is_dir():
        raise MsmillInputError("run_dir", str(run_dir), "an existing directory written by 'msmill dem run'")
    check_writable(run_dir, "run_dir")
    if out is not None:
        if out.is_dir():
            raise MsmillInputError("--out", str(out), "a JSON file path (this is a directory)")
        check_writable(out.parent if str(out.parent) else Path("."), "--out")
    ms = stats_from_dir(run_dir)
    target = out or run_dir / "statistics.json"
    # the run folder is updated in place: its other files and their manifest entries are kept
    with atomic_output(run_dir, field="run_dir", settings={"command": "dem stats"}, update=True) as stage:
        plot_stage_impacts(ms, stage / "stage_impacts.png")
        if out is None:
            ms.run.to_json(stage / "statistics.json")
    if out is not None:
        atomic_write_bytes(out, ms.run.to_json().encode())
    for s in ms.run.stages:
        typer.echo(f"stage {s.stage}: kick {s.kickback:.3f} refeed {s.refeed:.3f} pass {s.pass_through:.3f} "
                   f"p_hit {s.primary_hit_probability:.3f} lambda {s.secondary_lambda:.2f}"
                   + (f" counts {s.secondary_count_selection.chosen} (KL {s.secondary_count_selection.kl:.3f})"
                      if s.secondary_count_selection else ""))
    typer.echo(_outcome_line(run_dir, ms.run))
    typer.echo(f"written {target}")


def _outcome_line(run_dir: Path, st: Any) -> str:
    """The run's outcome and the sampling targets its window missed (targets of its own run settings)."""
    from msmill.dem.mill.run import RunSettings, missed_targets
    from msmill.validate import read_toml

    saved = read_toml(run_dir / "run.toml", "run_dir/run.toml", "run.toml of a DEM run").get("run", {})
    rs = RunSettings(**{k: v for k, v in saved.items() if k in RunSettings.__dataclass_fields__})
    missed = missed_targets(st.sampling_error_reached or {}, rs.targets())
    window = st.measurement_window_s
    head = f"outcome: {st.outcome or 'not recorded'}; window {window:.2f} s"
    if not missed:
        return head + "; every sampling target met"
    return head + "; sampling errors above their targets: " + ", ".join(
        f"{k} {'no samples' if v is None else f'{v:.3g}'} (target {rs.targets()[k]:.3g}, "
        f"{'-' if v is None else f'{v / rs.targets()[k]:.1f}x'})" for k, v in missed.items())


@app.command("envelope")
def envelope_cmd(
    run_dirs: Annotated[list[Path], typer.Argument(help="Directories written by 'msmill dem run'.")],
    out: Annotated[Path, typer.Option("--out", help="Envelope JSON (for 'msmill predict --envelope').")],
) -> None:
    """Collect the outcome (steady / choked / not steady) and throughput of runs into an envelope file."""
    from datetime import UTC, datetime

    from msmill._version import __version__
    from msmill.stageparams import RunStatistics
    from msmill.surrogate.capacity import EnvelopeData, EnvelopePoint

    points = []
    for d in run_dirs:
        if not (d / "statistics.json").is_file():
            raise MsmillInputError("run_dir", str(d), "a directory written by 'msmill dem run' (statistics.json)")
        points.append(EnvelopePoint.from_statistics(RunStatistics.from_json(d / "statistics.json")))
    prov = {"generator": "msmill dem envelope", "msmill_version": __version__, "runs": [str(d) for d in run_dirs],
            "date_utc": datetime.now(UTC).isoformat(timespec="seconds")}
    EnvelopeData(points, prov).to_json(out)
    for d, p in zip(run_dirs, points, strict=True):
        tp = "-" if p.throughput_tph is None else f"{p.throughput_tph:.1f} t/h"
        typer.echo(f"{d}: {p.outcome}; feed {p.feed_tph:g} t/h; throughput {tp}")
    typer.echo(f"written {out}")



@app.command("import")
def import_cmd(
    folder: Annotated[Path, typer.Argument(help="Folder with import.toml, machine.toml, events and positions tables.")],
    out: Annotated[Path | None, typer.Option("--out", help="Where to write statistics.json (default FOLDER).")] = None,
) -> None:
    """Compute per-stage statistics from external DEM tables (Rocky, EDEM, LIGGGHTS; docs/campaign.md)."""
    import shutil

    from msmill.dem.mill.external import import_folder

    ms, _machine = import_folder(folder)
    target = out or folder
    target.mkdir(parents=True, exist_ok=True)
    ms.run.to_json(target / "statistics.json")
    if target.resolve() != folder.resolve():
        for name in ("machine.toml", "import.toml"):
            shutil.copyfile(folder / name, target / name)
    for s in ms.run.stages:
        typer.echo(f"stage {s.stage}: kick {s.kickback:.3f} refeed {s.refeed:.3f} pass {s.pass_through:.3f} "
                   f"p_hit {s.primary_hit_probability:.3f} lambda {s.secondary_lambda:.2f}")
    typer.echo(f"written {target / 'statistics.json'} (ingest with 'msmill db ingest {target}')")
