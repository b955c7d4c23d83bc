"""``msmill db``: the SQL training store (ingest, export, list, show, migrate)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from msmill.errors import MsmillInputError

app = typer.Typer(help="SQL store of DEM runs and their statistics (SQLite by default, any SQLAlchemy URL).",
                  no_args_is_help=True)

DbOpt = Annotated[str | None, typer.Option(
    "--db", envvar="MSMILL_DB", show_envvar=True,
    help="SQLAlchemy URL or SQLite file (default ~/.local/share/msmill/store.sqlite).")]
RangeOpt = Annotated[str | None, typer.Option(help="Value or range LOW:HIGH (either side may be empty).")]


def open_store(db: str | None, create: bool = True):  # returns a Store (imported lazily)
    """The store at ``--db`` / ``MSMILL_DB`` / the default file, migrated.

    ``create=False`` (read commands): a SQLite file that does not exist is an error, not a new store.
    """
    from msmill.pipeline.store import Store

    return Store(db, create=create)


def parse_range(name: str, text: str | None) -> tuple[float | None, float | None] | None:
    """``"20:40"`` -> (20, 40); ``"30"`` -> (30, 30) within 1e-9; ``":40"`` -> (None, 40)."""
    if text is None:
        return None
    lo, sep, hi = text.partition(":")
    try:
        if not sep:
            v = float(lo)
            return v - 1e-9 * max(1.0, abs(v)), v + 1e-9 * max(1.0, abs(v))
        low, high = (float(lo) if lo.strip() else None), (float(hi) if hi.strip() else None)
    except ValueError:
        raise MsmillInputError(f"--{name.replace('_', '-')}", text, "a number or LOW:HIGH") from None
    if low is not None and high is not None and low > high:
        raise MsmillInputError(f"--{name.replace('_', '-')}", text, "LOW:HIGH with LOW <= HIGH")
    return low, high


def design_filters(**ranges: str | None) -> dict[str, tuple[float | None, float | None]]:
    """Filters for :meth:`Store.runs` from range options."""
    out = {}
    for k, v in ranges.items():
        r = parse_range(k, v)
        if r is not None:
            out[k] = r
    return out


@app.command("info")
def info_cmd(db: DbOpt = None) -> None:
    """Show the store's URL, schema revision and number of runs per status."""
    st = open_store(db, create=False)
    runs = st.runs()
    by = {}
    for r in runs:
        by[r.status] = by.get(r.status, 0) + 1
    typer.echo(f"store: {st.url}\nschema revision: {st.revision()} (head {st.head()})")
    typer.echo(f"runs: {len(runs)} " + " ".join(f"{k}={v}" for k, v in sorted(by.items())))
    typer.echo(f"campaigns: {', '.join(c.name for c in st.campaigns()) or '-'}")


@app.command("upgrade")
def upgrade_cmd(db: DbOpt = None) -> None:
    """Migrate the store to the newest schema (opening a store does this too)."""
    from msmill.pipeline.store import Store

    st = Store(db, upgrade=False)
    before = st.revision()
    after = st.upgrade()
    typer.echo(f"{st.url}: {before or 'empty'} -> {after}")


@app.command("ingest")
def ingest_cmd(
    paths: Annotated[list[Path], typer.Argument(help="Run folders, folders of them, or exported run-*.json.")],
    db: DbOpt = None,
    allow_not_steady: Annotated[bool, typer.Option("--allow-not-steady",
                                                   help="Also take runs that did not reach steady state.")] = False,
) -> None:
    """Ingest saved 'msmill dem run' / 'msmill dem import' folders and exported documents (idempotent)."""
    from msmill.pipeline.store.transfer import ingest_paths

    res = ingest_paths(open_store(db), list(paths), allow_not_steady=allow_not_steady)
    for r in res:
        tail = f" run {r.run_id}" if r.run_id is not None else ""
        typer.echo(f"{r.status}{tail}: {r.path}" + (f" ({r.reason})" if r.reason else ""))
    n = {s: sum(r.status == s for r in res) for s in ("added", "exists", "skipped")}
    typer.echo(f"added={n['added']} exists={n['exists']} skipped={n['skipped']}")


@app.command("export")
def export_cmd(
    out: Annotated[Path, typer.Argument(help="Folder for the run-*.json documents.")],
    db: DbOpt = None,
    campaign: Annotated[str | None, typer.Option(help="Only this campaign's runs.")] = None,
) -> None:
    """Write every done run as one JSON document (readable back by 'msmill db ingest')."""
    from msmill.pipeline.store.transfer import export_runs

    paths = export_runs(open_store(db, create=False), out, campaign=campaign)
    typer.echo(f"exported {len(paths)} runs to {out}")


@app.command("list")
def list_cmd(
    db: DbOpt = None,
    campaign: Annotated[str | None, typer.Option(help="Only this campaign.")] = None,
    status: Annotated[str | None, typer.Option(help="planned, running, done or failed.")] = None,
    machine: Annotated[str | None, typer.Option(help="Machine hash (prefix).")] = None,
    size_mm: RangeOpt = None, feed_tph: RangeOpt = None, speed_rpm: RangeOpt = None, gate_deg: RangeOpt = None,
) -> None:
    """List runs, filtered by campaign, status, machine and design variables."""
    from rich.table import Table

    from msmill.cli.console import console

    runs = open_store(db, create=False).runs(campaign=campaign, status=status, machine_hash=machine, filters=design_filters(
        size_mm=size_mm, feed_tph=feed_tph, speed_rpm=speed_rpm, gate_deg=gate_deg))
    t = Table("id", "status", "outcome", "size_mm", "feed_tph", "speed_rpm", "gate_deg", "mode", "source",
              "campaign", "attempts", "wall_s", "machine")
    for r in runs:
        d = r.design
        t.add_row(str(r.id), r.status, r.outcome or "-", f"{d.size_mm:g}", f"{d.feed_tph:g}", f"{d.speed_rpm:g}",
                  f"{d.gate_deg:g}", r.mode, r.source, r.campaign or "-", str(r.attempts),
                  f"{r.wall_s:.1f}" if r.wall_s is not None else "-", r.machine_hash[:10])
    console(200).print(t)
    typer.echo(f"{len(runs)} runs")


@app.command("show")
def show_cmd(run_id: Annotated[int, typer.Argument(help="Run id (see 'msmill db list').")], db: DbOpt = None) -> None:
    """Show one run: its facts, per-stage statistics and raw files."""
    st = open_store(db, create=False)
    r = st.run(run_id)
    d = r.design
    typer.echo(f"run {r.id}: {r.status} ({r.outcome or '-'}), {r.mode}, source {r.source}, attempts {r.attempts}")
    typer.echo(f"design: size {d.size_mm:g} mm, feed {d.feed_tph:g} t/h, speed {d.speed_rpm:g} rpm, "
               f"gate {d.gate_deg:g} deg, stage speeds {d.stage_speeds_rpm}")
    typer.echo(f"machine {r.machine_hash[:16]}; engine {r.engine}; msmill {r.package_version}; "
               f"commit {r.git_commit}; seed {r.seed}; wall {r.wall_s} s; CPU {r.cpu_s} s")
    if r.note:
        typer.echo(f"note: {r.note}")
    if r.source_path:
        typer.echo(f"source: {r.source_path}")
    if r.error:
        typer.echo("errors:\n" + r.error.rstrip())
    if r.status == "done":
        s = st.statistics(run_id)
        typer.echo(f"tau {s.characteristic_time_s:.4g} s; steady state at {s.steady_state_time_s}; "
                   f"mass out {s.mass_out_rate_kg_s} kg/s")
        for g in s.stages:
            typer.echo(f"stage {g.stage}: kick {g.kickback:.3f} refeed {g.refeed:.3f} pass {g.pass_through:.3f} "
                       f"p_hit {g.primary_hit_probability:.3f} v1 {g.primary_velocity.mean():.1f} m/s "
                       f"lambda {g.secondary_lambda:.2f} v2 {g.secondary_velocity.mean():.1f} m/s")
    for f in st.raw_files(run_id):
        typer.echo(f"raw {f['kind']}: {f['path']} sha256 {f['sha256'][:16]} ({f['size_bytes']} B)")
