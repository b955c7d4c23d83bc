"""``msmill predict run.toml``: predict the product of a mill from a run file (no physics here).

Validates the whole run file and runs the model before anything is written;
then writes the product PSD table (CSV), the time series and per-stage tables,
and the plots, and prints a summary table.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated, Any

import typer


def predict(
    run_file: Annotated[Path, typer.Argument(help="Run file (TOML); see msmill.model.runfile.")],
    out: Annotated[Path | None, typer.Option("--out", "-o", help="Output folder (default: the run file's \\[output] dir).")] = None,
    plots: Annotated[bool | None, typer.Option("--plots/--no-plots", help="Write PNG plots.")] = None,
    solver: Annotated[str | None, typer.Option(help="Override the run file's \\[model] solver.")] = None,
    envelope: Annotated[Path | None, typer.Option(
        "--envelope", help="DEM envelope (JSON: scripts/build_envelope.py or 'msmill dem envelope') to check the "
        "feed rate against, instead of the shipped one.")] = None,
    capacity_check: Annotated[bool, typer.Option(
        "--capacity-check/--no-capacity-check", help="Warn when the feed rate exceeds the envelope's capacity.")
    ] = True,
    ore_file: Annotated[Path | None, typer.Option(
        "--ore-file", help="Your own ore TOML (msmill ore show --help) instead of the run file's \\[ore].")] = None,
) -> None:
    """Predict the product PSD, hold-up and impact energy of a mill run file."""
    from msmill.cli.output import atomic_output, check_writable
    from msmill.model.runfile import RunFile

    rf = RunFile.from_toml(run_file)
    if solver is not None:
        rf = RunFile.model_validate({**rf.model_dump(), "base_dir": rf.base_dir, "name": rf.name,
                                     "model": {**rf.model.model_dump(), "solver": solver}})
    if ore_file is not None:
        from msmill.ore import Ore

        Ore.from_toml(ore_file)  # a bad file is a one-line error naming it, before any work
        rf = RunFile.model_validate({**rf.model_dump(), "base_dir": rf.base_dir, "name": rf.name,
                                     "ore": {"file": str(ore_file.resolve())}})
    folder = check_writable(out if out is not None else rf.path(rf.output.dir),
                            "--out" if out is not None else f"{rf.name}.output.dir")
    mill, feed, op = rf.build()
    apply_envelope(mill, envelope, capacity_check)
    result = mill.run(feed, op)

    # render everything in memory first, then commit the set atomically with a manifest
    csv_name = Path(rf.output.csv)
    stem = csv_name.stem
    files: dict[str, bytes] = {
        csv_name.name: result.psd_table.to_csv(index=False).encode(),
        f"{stem}_timeseries.csv": result.timeseries.to_csv(index=False).encode(),
        f"{stem}_stages.csv": result.stages.to_csv(index=False).encode(),
    }
    if plots if plots is not None else rf.output.plots:
        from msmill.plots.model import png_bytes, prediction_figures

        for key, fig in prediction_figures(result, title=rf.title).items():
            files[f"{stem}_{key}.png"] = png_bytes(fig)
    settings = {"run_file": rf.model_dump(mode="json"), "solver": result.solver}
    with atomic_output(folder, field="--out", inputs=[run_file], settings=settings) as stage:
        for name, data in files.items():
            (stage / name).write_bytes(data)
    _print_summary(rf, mill, result, folder, list(files))


def apply_envelope(mill, envelope: Path | None, capacity_check: bool) -> None:
    """The mill checks its feed against ``envelope`` (default: the shipped one), or not at all."""
    if not capacity_check:
        mill.use_envelope(None)
    elif envelope is not None:
        mill.use_envelope(envelope)


def _capacity_rows(result: Any) -> list[tuple[str, str]]:
    """Summary rows of the envelope check: the capacity (or its lower bound) and P(steady)."""
    from msmill.model.result import display_number

    if result.capacity_is_lower_bound:
        known = not math.isnan(result.probability_steady)  # NaN above the bound: no evidence either way
        return [("capacity at F80, speed, gate (t/h; DEM envelope lower bound, no run choked)",
                 f">= {display_number(result.capacity_tph)}"),
                ("probability of steady flow at this feed",
                 "1 (within the lower bound)" if known else "unknown (above the lower bound)")]
    return [("capacity at F80, speed, gate (t/h; DEM envelope)", f"{result.capacity_tph:.3g}"),
            ("probability of steady flow at this feed", f"{result.probability_steady:.2f}")]


def _impact_kw(result) -> float:
    from msmill.model.power import power_estimate

    return power_estimate(result).impact_kw


def _print_summary(rf, mill, result, folder: Path, names: list[str]) -> None:
    from rich.table import Table

    from msmill.cli.console import console

    con = console(120)
    t = Table(title=rf.title or rf.name, show_header=True)
    t.add_column("quantity")
    t.add_column("value", justify="right")
    rows = [
        ("feed rate (t/h)", f"{result.feed_tph:g}"),
        ("F80 (mm)", f"{result.f80_mm:.3g}"),
        ("P80 (mm)", f"{result.p80_mm:.3g}"),
        *([(f"P80 5-95 % band (mm, {result.band_samples} GP samples)",
            f"{result.p80_band_mm[0]:.3g} - {result.p80_band_mm[1]:.3g}")] if result.p80_band_mm else []),
        ("P50 (mm)", f"{result.p50_mm:.3g}"),
        ("reduction ratio F80/P80", f"{result.reduction_ratio:.3g}"),
        *[(f"passing {s:g} mm (%)", f"{v:.3g}") for s, v in result.passing_pct.items()],
        ("time to steady state (s)", f"{result.time_to_steady_state_s:.3g}"),
        ("mass held in mill (kg)", f"{1000 * result.stages['holdup_t'].sum():.3g}"),
        ("primary impacts per rock (mass-weighted)", f"{result.primary_impacts_per_t:.3g}"),
        ("secondary impacts per rock (mass-weighted)", f"{result.secondary_impacts_per_t:.3g}"),
        ("impact energy (kWh/t)", f"{result.specific_impact_energy_kwh_t:.3g}"),
        ("impact power (kW; no-load not included, docs/validation.md)", f"{_impact_kw(result):.3g}"),
        ("mass-balance error", f"{result.mass_balance_error:.1e}"),
        *(_capacity_rows(result) if result.capacity_tph is not None else []),
        ("feed / product mass with extrapolated stage statistics (%)",
         f"{result.extrapolated_feed_pct:.3g} / {result.extrapolated_product_pct:.3g}"),
        *([("feed / product mass with stage statistics from thin data (%)",
            f"{result.thin_data_feed_pct:.3g} / {result.thin_data_product_pct:.3g}")]
          if result.thin_data_product_pct == result.thin_data_product_pct else []),  # not NaN
        *([(f"P80 (mm) / passing 75 um (%) with statistics held below {result.held_below_mm:.3g} mm",
            f"{result.held_below_p80_mm:.3g} / {result.held_below_passing_75um_pct:.3g} "
            f"(here {result.p80_mm:.3g} / {float(result.product_psd.passing_at(0.075)):.3g})")]
          if result.held_below_mm == result.held_below_mm else []),  # not NaN
    ]
    for r in rows:
        t.add_row(*r)
    con.print(t)
    from msmill.model.result import display_number, stage_display

    table = stage_display(result.stages)
    s = Table(title="per stage", show_header=True)
    for col in table.columns:
        s.add_column(col, justify="right")
    for row in table.itertuples(index=False):
        s.add_row(str(row[0]), *(display_number(v) for v in row[1:]))
    con.print(s)
    con.print(f"solver: {result.solver}; sub-models: "
              + ", ".join(f"{k}={v}" for k, v in result.submodels.items()))
    for note in result.notes:
        con.print(f"note: {note}", soft_wrap=True)
    con.print(f"wrote {', '.join(names)} to {folder}")
