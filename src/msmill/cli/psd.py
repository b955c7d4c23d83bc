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
    path: Annotated[Path, typer.Argument(help="Cumulative passing CSV: size_mm, passing_pct (or the product CSV of 'msmill predict').")],
    percentile: Annotated[list[float] | None, typer.Option(
        "--percentile", "-p", help="Extra percentiles (repeatable), e.g. -p 10 -p 90.")] = None,
) -> None:
    """P50, P80 (and any Pxx), Rosin-Rammler and Gates-Gaudin-Schuhmann fits of a PSD."""
    from msmill.errors import MsmillInputError
    from msmill.psd import PSD
    from msmill.validate import number, read_csv

    pcts = sorted({50.0, 80.0, *(number(q, "--percentile", unit="%", gt=0, le=100) for q in (percentile or []))})
    frame = read_csv(path, "path", "PSD CSV file")
    psd = PSD.from_frame(frame)
    given = frame["size_mm" if "size_mm" in frame.columns else "upper_mm"].astype(float)  # or predict's table
    lo_mm, hi_mm = float(given.min()), float(given.max())
    con = console(120)
    table = Table(title=f"{path.name}: {len(given)} sieves, {lo_mm:.4g}-{hi_mm:.4g} mm")
    table.add_column("statistic")
    table.add_column("value")
    sizes = psd.percentile(pcts)
    outside = []
    for q, s in zip(pcts, [sizes] if isinstance(sizes, float) else sizes, strict=True):
        flag = ""
        if s < lo_mm * (1 - 1e-9) or s > hi_mm * (1 + 1e-9):
            flag = " (extrapolated: outside the sieves given)"
            outside.append(f"P{q:g}")
        table.add_row(f"P{q:g}", f"{s:.4g} mm{flag}")
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
    if outside:
        verb = "lies" if len(outside) == 1 else "lie"
        con.print(f"note: {', '.join(outside)} {verb} outside the sieves given ({lo_mm:.4g}-{hi_mm:.4g} mm): "
                  "extrapolated (log-linear) beyond the data, not measured", soft_wrap=True)
