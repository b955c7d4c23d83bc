"""``msmill circuit CIRCUIT.toml``: a closed circuit's steady state and its band (no physics here).

Validates the circuit file and solves the circuit (and its 5-95 % band from the
surrogate's posterior samples) before anything is written; then writes the
stream summary and one sieve table per stream (CSV) and prints the summary.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import typer


def circuit(
    circuit_file: Annotated[Path, typer.Argument(help="Circuit file (TOML); see docs/circuit.md.")],
    out: Annotated[Path | None, typer.Option("--out", "-o", help="Output folder (default: <file stem>_output "
                                                                 "beside the circuit file).")] = None,
    band_samples: Annotated[int | None, typer.Option(
        "--band-samples", help="Posterior samples behind the 5-95 % band (default: the file's \\[band] samples, "
        "64; 0: no band).")] = None,
    method: Annotated[str | None, typer.Option(help="Override the file's \\[solver] method (wegstein, direct).")
                      ] = None,
) -> None:
    """Solve a closed circuit: circulating load, product P80 (with 5-95 % bands), t/h per stream, energy."""
    from msmill.cli.output import atomic_output, check_writable
    from msmill.errors import MsmillInputError
    from msmill.model.circuit import METHODS, CircuitFile
    from msmill.model.mill import MAX_BAND_SAMPLES

    cf = CircuitFile.from_toml(circuit_file)
    if method is not None:
        if method not in METHODS:
            raise MsmillInputError("--method", method, " or ".join(METHODS))
        cf.solver = cf.solver.model_copy(update={"method": method})
    if band_samples is not None and not (band_samples == 0 or 2 <= band_samples <= MAX_BAND_SAMPLES):
        raise MsmillInputError("--band-samples", band_samples, f"0 (no band) or 2-{MAX_BAND_SAMPLES}")
    folder = check_writable(out if out is not None else circuit_file.resolve().parent
                            / f"{circuit_file.stem}_output", "--out")
    result = cf.solve()
    band = cf.band(result, band_samples)
    mills = result.mill_summaries()
    files: dict[str, bytes] = {"streams.csv": result.streams_frame().to_csv(index=False).encode()}
    for name in result.circuit.streams:
        files[f"stream_{name}.csv"] = result.stream_table(name).to_csv(index=False).encode()
    if band is not None:
        files["band_samples.csv"] = band.samples_frame().to_csv(index=False).encode()
    settings = {"circuit_file": str(circuit_file), "method": cf.solver.method,
                "band_samples": 0 if band is None else band.n_samples}
    with atomic_output(folder, field="--out", inputs=[circuit_file], settings=settings) as stage:
        for name, data in files.items():
            (stage / name).write_bytes(data)
    _print_summary(cf, result, band, mills, folder, list(files))


def _print_summary(cf: Any, result: Any, band: Any, mills: dict, folder: Path, names: list[str]) -> None:
    from rich.table import Table

    from msmill.cli.console import console

    con = console(120)
    t = Table(title=result.circuit.title or cf.name, show_header=True)
    t.add_column("quantity")
    t.add_column("value", justify="right")
    k = f"{band.n_samples} GP samples" if band is not None else ""
    kw = sum(m["impact_kw"] for m in mills.values())
    rows = [
        ("fresh feed (t/h)", f"{result.circuit.fresh_tph:.4g}"),
        ("product (t/h)", f"{result.product_tph:.4g}"),
        (f"circulating load (%; {' + '.join(result.recycle_streams)} / fresh feed)",
         f"{result.circulating_load_pct:.4g}"),
        *([(f"circulating load 5-95 % band (%, {k})",
            f"{band.circulating_load_band_pct[0]:.4g} - {band.circulating_load_band_pct[1]:.4g}")] if band else []),
        ("product P80 (mm)", f"{result.product_p80_mm:.3g}"),
        *([(f"product P80 5-95 % band (mm, {k})",
            f"{band.product_p80_band_mm[0]:.3g} - {band.product_p80_band_mm[1]:.3g}")] if band else []),
        ("product passing 75 um (%)", f"{float(result.product_psd.passing_at(0.075)):.3g}"),
    ]
    for n, m in mills.items():
        rows.append((f"{n}: feed, fresh plus recycle (t/h)", f"{m['feed_tph']:.4g}"))
        if band is not None:
            lo, hi = band.mill_feed_band_tph[n]
            rows.append((f"{n}: feed 5-95 % band (t/h, {k})", f"{lo:.4g} - {hi:.4g}"))
        chk = m["capacity"]
        if chk is not None:
            cap = f">= {chk.capacity_tph:.3g}" if chk.lower_bound else f"{chk.capacity_tph:.3g}"
            rows.append((f"{n}: capacity at its feed's F80, speed, gate (t/h; DEM envelope)",
                         cap + ("  (feed ABOVE it)" if chk.above else "")))
            rows.append((f"{n}: probability of steady flow at its feed", f"{chk.probability_steady:.2f}"))
            if band is not None:
                hi = band.mill_feed_band_tph[n][1]
                rows.append((f"{n}: band's 95 % feed / capacity", f"{hi / chk.capacity_tph:.2f}"
                             + (" (capacity is a lower bound)" if chk.lower_bound else "")))
        rows.append((f"{n}: impact energy (kWh/t of its feed)", f"{m['impact_energy_kwh_t_feed']:.3g}"))
    rows += [
        ("impact energy per tonne of product (kWh/t; no-load not included)",
         f"{kw / result.product_tph:.3g}"),
        ("solver", f"{result.method}: {result.iterations} passes; "
                   + ", ".join(f"{n}'s operators built {m['operator_rebuilds']} times" for n, m in mills.items())),
        ("relative mass-balance error (last pass / products)",
         f"{result.residual:.1e} / {result.mass_balance_error:.1e}"),
    ]
    for r in rows:
        t.add_row(*r)
    con.print(t)
    s = Table(title="streams", show_header=True)
    for col in ("stream", "from", "to", "t/h", "P80 (mm)"):
        s.add_column(col, justify="right" if col in ("t/h", "P80 (mm)") else "left")
    for _, r in result.streams_frame().iterrows():
        s.add_row(r["stream"] + (" (recycle)" if r["recycle"] else ""), r["from"], r["to"], f"{r['tph']:.4g}",
                  f"{r['p80_mm']:.3g}")
    con.print(s)
    for n, m in mills.items():
        for note in m["result"].notes:
            con.print(f"note: {n}: {note}", soft_wrap=True)
    if band is not None:
        con.print(f"note: band: {band.n_samples} posterior samples of the stage parameters (seed {band.seed}) "
                  "solved together at the band's resolution; their 5-95 % spread about their median is added "
                  "to the prediction (docs/circuit.md)", soft_wrap=True)
    con.print(f"wrote {', '.join(names)} to {folder}")
