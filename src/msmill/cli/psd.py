"""``msmill psd``: statistics of a particle size distribution (thin layer over msmill.psd)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from rich.table import Table

from msmill.cli.console import console

app = typer.Typer(help="Particle size distributions: percentiles and distribution fits.",
                  no_args_is_help=True)


@app.command("stats")
def stats_cmd(
    path: Annotated[Path, typer.Argument(help="Cumulative passing CSV: size_mm, passing_pct.")],
    percentile: Annotated[list[float] | None, typer.Option(
        "--percentile", "-p", help="Extra percentiles (repeatable), e.g. -p 10 -p 90.")] = None,
) -> None:
    """P50, P80 (and any Pxx), Rosin-Rammler and Gates-Gaudin-Schuhmann fits of a PSD."""
    from msmill.errors import MsmillInputError
    from msmill.psd import PSD

    psd = PSD.read_csv(path)
    con = console(120)
    pcts = sorted({50.0, 80.0, *(percentile or [])})
    table = Table(title=f"{path.name}: {len(psd.sizes_mm)} sieves, {psd.sizes_mm[0]:.4g}-{psd.sizes_mm[-1]:.4g} mm")
    table.add_column("statistic")
    table.add_column("value")
    sizes = psd.percentile(pcts)
    for q, s in zip(pcts, [sizes] if isinstance(sizes, float) else sizes, strict=True):
        table.add_row(f"P{q:g}", f"{s:.4g} mm")
    for name, method in (("Rosin-Rammler", psd.fit_rosin_rammler),
                         ("Gates-Gaudin-Schuhmann", psd.fit_gates_gaudin_schuhmann)):
        try:
            fit = method()
        except MsmillInputError as exc:
            table.add_row(name, f"not fitted ({exc.allowed})")
            continue
        params = ", ".join(f"{k} = {v:.4g}" for k, v in fit.params.items())
        table.add_row(name, f"{params}; R^2 = {fit.r_squared:.4f}, RMSE = {fit.rmse_pct:.3g} %")
    con.print(table)
