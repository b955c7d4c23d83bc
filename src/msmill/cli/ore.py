"""``msmill ore``: list, show and calibrate ore parameter sets (thin layer over msmill.ore)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer
from rich.table import Table

from msmill.cli.console import console
from msmill.errors import MsmillInputError
from msmill.validate import number

if TYPE_CHECKING:
    from rich.console import Console

    from msmill.ore import Ore

app = typer.Typer(help="Ore parameter sets: list, show, calibrate L_ref from drop-weight data.",
                  no_args_is_help=True)


def _console() -> Console:
    return console(140)


def resolve_ore(name_or_path: str) -> Ore:
    """An ore by registry name, or loaded from a ``.toml`` path."""
    from msmill.ore import Ore, get_ore

    p = Path(name_or_path)
    if name_or_path.lower().endswith(".toml"):
        return Ore.from_toml(p)
    return get_ore(name_or_path)


def _l_ref_text(ore: Ore) -> str:
    return f"{ore.l_ref_mm:.4g} mm" + (" (DEFAULT, not calibrated)" if ore.l_ref_is_default else "")


@app.command("list")
def list_cmd() -> None:
    """List the registered ores."""
    from msmill.ore import get_ore, list_ores

    table = Table(title="ores")
    for col in ("name", "A (%)", "b (t/kWh)", "A*b", "L_ref", "density (kg/m3)"):
        table.add_column(col)
    for name in list_ores():
        o = get_ore(name)
        table.add_row(o.name, f"{o.A_pct:g}", f"{o.b_t_per_kwh:g}", f"{o.ab:.1f}", _l_ref_text(o),
                      f"{o.density_kg_m3:g}")
    _console().print(table)


@app.command("show")
def show_cmd(
    name: Annotated[str, typer.Argument(help="Ore name (case-insensitive) or path of an ore TOML file.")],
) -> None:
    """Show every parameter of an ore with its source."""
    ore = resolve_ore(name)
    con = _console()
    table = Table(title=f"ore {ore.name}", show_lines=True)
    table.add_column("parameter")
    table.add_column("value")
    table.add_column("source", overflow="fold", max_width=90)
    s = ore.sources
    table.add_row("A", f"{ore.A_pct:g} %", s.get("breakage", ""))
    table.add_row("b", f"{ore.b_t_per_kwh:g} t/kWh", s.get("breakage", ""))
    table.add_row("L_ref", _l_ref_text(ore), s.get("l_ref", ""))
    table.add_row("density", f"{ore.density_kg_m3:g} kg/m3", s.get("physical", ""))
    table.add_row("Young's modulus", f"{ore.youngs_modulus_pa:.3g} Pa", s.get("elastic", ""))
    table.add_row("Poisson's ratio", f"{ore.poisson_ratio:g}", s.get("elastic", ""))
    tn = ", ".join(f"t{n}: k={k:.4g} s={sv:.4g}" for n, (k, sv) in ore.tn.as_dict().items())
    table.add_row("t_n = k t10^s", tn, ore.tn.source)
    table.add_row("Tavares gamma", f"{ore.gamma:g}", s.get("damage", ""))
    table.add_row("damage threshold", f"{ore.damage_threshold:g}", s.get("damage", ""))
    con.print(table)
    if ore.l_ref_is_default:
        con.print(f"note: L_ref is the msmill default ({ore.l_ref_mm:g} mm), not calibrated for "
                  f"{ore.name}; run `msmill ore calibrate <drop-weight.csv> --ore {ore.name}`.")


@app.command("calibrate")
def calibrate_cmd(
    data: Annotated[Path, typer.Argument(help="Drop-weight CSV: size_mm, ecs_kwh_t, t10_pct.")],
    ore_name: Annotated[str, typer.Option("--ore", help="Ore (name or TOML) for held/start values.")] = "UG2",
    fit_ab: Annotated[bool, typer.Option(
        "--fit-ab", help="Fit A and b with L_ref held (b and L_ref are not separately identifiable).")] = False,
    fit_a: Annotated[bool, typer.Option("--fit-a", help="Fit A together with L_ref.")] = False,
    l_ref_mm: Annotated[float | None, typer.Option(
        "--l-ref-mm", help="L_ref held with --fit-ab (default: the ore's).")] = None,
    out: Annotated[Path | None, typer.Option("--out", help="Write the calibrated ore as TOML.")] = None,
    residuals: Annotated[bool, typer.Option("--residuals/--no-residuals", help="Print the residual table.")] = True,
    breakage: Annotated[str | None, typer.Option(
        "--breakage", help="Breakage sub-model whose parameters are fitted (default: the model's default, "
        "jk_t10); the drop-weight test is simulated through it.")] = None,
) -> None:
    """Fit L_ref (optionally A, or A and b) of Eq. 11-12 to drop-weight data."""
    from msmill.calibration import calibrate
    from msmill.cli.output import atomic_write_bytes, check_writable
    from msmill.model import submodels as sm

    if fit_ab and fit_a:
        raise MsmillInputError("--fit-a/--fit-ab", "both", "one of --fit-a or --fit-ab")
    if out is not None:
        if out.is_dir():
            raise MsmillInputError("--out", str(out), "a TOML file path (this is a directory)")
        check_writable(out.parent if str(out.parent) else Path("."), "--out")
    if l_ref_mm is not None:
        number(l_ref_mm, "--l-ref-mm", unit="mm", gt=0)
    ore = resolve_ore(ore_name)
    name = breakage or sm.DEFAULTS["breakage"]
    with_t10 = [k for k, f in sm.SUBMODELS["breakage"].items() if hasattr(f, "t10_convention")]
    if name not in with_t10:
        raise MsmillInputError("--breakage", name, sm.did_you_mean(name, with_t10))
    fit = ("A_pct", "b_t_per_kwh") if fit_ab else (("A_pct", "l_ref_mm") if fit_a else ("l_ref_mm",))
    lab = sm.lab_test(name, sm.BreakageParameters.from_ore(ore).tn)
    res = calibrate(data, ore, fit=fit, l_ref_mm=l_ref_mm, lab_test=lab)
    con = _console()
    table = Table(title=f"calibration of {ore.name} on {data.name} (n = {res.n_points})")
    for col in ("parameter", "value", "std. error", "status"):
        table.add_column(col)
    units = {"A_pct": "%", "b_t_per_kwh": "t/kWh", "l_ref_mm": "mm"}
    for k, v in res.params.items():
        if k in res.fitted:
            table.add_row(k, f"{v:.4g} {units[k]}", f"{res.std_errors[k]:.2g}", "fitted")
        else:
            table.add_row(k, f"{v:.4g} {units[k]}", "-", "held")
    con.print(table)
    con.print(f"R^2 = {res.r_squared:.4f}   RMSE = {res.rmse_pct:.3g} % t10   "
              f"converged: {res.success}   breakage sub-model: {name}")
    if fit_ab:
        con.print("note: b and L_ref enter Eq. 11 only as b/L_ref; b is fitted for the held L_ref.")
    if math.isfinite(res.r_squared) and res.r_squared < 0:
        con.print(f"warning: R^2 = {res.r_squared:.3g} < 0: the fitted model describes t10 worse than its "
                  "mean; check the data's units (size_mm, ecs_kwh_t, t10_pct)")
    if not res.success:
        con.print(f"warning: the fit did not converge cleanly ({res.message}); do not use these values")
    if residuals:
        _print_residuals(con, res.residuals)
    if out is not None:
        import tomli_w

        new = res.to_ore(ore)
        atomic_write_bytes(out, tomli_w.dumps(new.to_dict()).encode("utf-8"))
        con.print(f"wrote {out}")


#: Residual rows printed by ``ore calibrate`` (the largest by magnitude; all are in
#: ``CalibrationResult.residuals``).
MAX_RESIDUAL_ROWS = 30


def _print_residuals(con: Console, table) -> None:
    """The largest residuals as a table (all of them if there are few)."""
    n = len(table)
    shown = table
    title = "residuals"
    if n > MAX_RESIDUAL_ROWS:
        order = table["residual_pct"].abs().to_numpy().argsort()[::-1][:MAX_RESIDUAL_ROWS]
        shown = table.iloc[sorted(order)]
        title = f"residuals: the {MAX_RESIDUAL_ROWS} largest of {n} rows (in file order)"
    rt = Table(title=title)
    for col in shown.columns:
        rt.add_column(col)
    for row in shown.itertuples(index=False):
        rt.add_row(*(f"{x:.4g}" for x in row))
    con.print(rt)
