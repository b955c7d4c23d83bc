"""``msmill report RUN.toml``: one self-contained HTML report of a prediction (msmill.report)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer


def report(
    run_file: Annotated[Path, typer.Argument(help="Run file (TOML); see msmill.model.runfile.")],
    out: Annotated[Path | None, typer.Option("--out", "-o", help="HTML file (default: <run file>.html).")] = None,
    no_load_kw: Annotated[float, typer.Option(help="Stated no-load power (kW); msmill does not model it.")] = 0.0,
) -> None:
    """Write a self-contained HTML report (inputs, PSD, Fig. 14, per-stage breakdown, power, provenance)."""
    from msmill.report import write_report

    dest = out if out is not None else run_file.with_suffix(".html")
    p = write_report(run_file, dest, no_load_kw=no_load_kw)
    typer.echo(f"wrote {p} ({p.stat().st_size / 1024:.0f} kB)")
