"""``msmill breakage``: one impact on one rock, tabulated (thin layer over msmill.breakage)."""

from __future__ import annotations

import math
from typing import Annotated

import numpy as np
import typer
from rich.table import Table

from msmill.cli.console import console
from msmill.validate import limit, number

#: Largest impact speed accepted (m/s): ten times the fastest flinger tip of an impact mill.
MAX_VELOCITY_M_S = 1000.0
#: Largest rock accepted (mm): drop-weight data and the Ab-t10 model end near 100 mm.
MAX_SIZE_MM = 1000.0

#: Breakage sub-models ``table`` can show, with their t10 conventions (``msmill.breakage.fragment_t10_pct``).
TABLE_CONVENTIONS = {"jk_t10": "jk", "ab_t10": "paper", "energy_t10": "energy"}

app = typer.Typer(help="Breakage of a single impact: energy, P_b, t10, t_n and fragment PSD.",
                  no_args_is_help=True)


@app.command("table")
def table_cmd(
    ore_name: Annotated[str, typer.Option("--ore", help="Ore name or ore TOML.")] = "UG2",
    size_mm: Annotated[float, typer.Option("--size-mm", help="Rock size L (mm).")] = 10.0,
    velocity: Annotated[float, typer.Option("--velocity", help="Relative normal impact speed (m/s).")] = 40.0,
    damage: Annotated[float, typer.Option("--damage", help="Accumulated damage before the impact, [0, 1).")] = 0.0,
    grid_min_mm: Annotated[float, typer.Option("--grid-min-mm", help="Finest sieve of the fragment PSD (mm).")] = 0.1,
    grid_max_mm: Annotated[float | None, typer.Option(
        "--grid-max-mm", help="Top of the fragment grid (mm); default: a sqrt(2) grid centred on the rock.")] = None,
    breakage: Annotated[str, typer.Option(
        "--breakage", help="Breakage sub-model whose t10 convention the fragments follow: jk_t10 (the model "
        "default, t10 = A), ab_t10 (the paper's t10 = A P_b) or energy_t10 (t10 = A (1 - exp(-c x)), the "
        "ore's fineness_ratio c).")] = "jk_t10",
) -> None:
    """Ecs, P_b, t10, t_n and the fragment PSD for one impact of a rock of an ore."""
    from msmill import breakage as br
    from msmill.cli.ore import resolve_ore
    from msmill.errors import MsmillInputError
    from msmill.psd import SizeGrid

    if breakage not in TABLE_CONVENTIONS:
        raise MsmillInputError("--breakage", breakage, "one of " + ", ".join(TABLE_CONVENTIONS)
                               + " (the t10-tn sub-models)")
    convention = TABLE_CONVENTIONS[breakage]
    ore = resolve_ore(ore_name)
    number(velocity, "--velocity", unit="m/s", ge=0, le=MAX_VELOCITY_M_S)
    number(size_mm, "--size-mm", unit="mm", gt=0, le=MAX_SIZE_MM)
    number(damage, "--damage", ge=0, lt=1)
    number(grid_min_mm, "--grid-min-mm", unit="mm", gt=0, lt=size_mm)
    if grid_max_mm is not None:
        number(grid_max_mm, "--grid-max-mm", unit="mm", gt=size_mm, le=100 * size_mm)
    top = grid_max_mm or size_mm * 2**0.25
    n_classes = math.ceil(math.log(top / grid_min_mm) / math.log(math.sqrt(2.0)))
    limit(n_classes, "--grid-min-mm/--size-mm", "grid_classes")
    ecs_j = float(br.velocity_to_ecs_j_kg(velocity))
    ecs_kwh = float(br.j_kg_to_kwh_t(ecs_j))
    res = br.damage_after_impact(ecs_kwh, size_mm, ore.b_t_per_kwh, ore.l_ref_mm, ore.gamma,
                                 damage=damage, damage_threshold=ore.damage_threshold)
    pb = float(br.breakage_probability(ecs_kwh, size_mm, ore.b_t_per_kwh, ore.l_ref_mm, damage))
    note = ""
    if convention == "energy":  # the sub-model's own fragment t10 (driven by the whole energy, past P_b = 1)
        from msmill.model.mill import breakage_parameters
        from msmill.model.submodels import EnergyT10Breakage

        brk = EnergyT10Breakage(breakage_parameters(ore))
        t10 = ore.A_pct * float(brk.fragment_index(ecs_kwh, size_mm, damage))
        c = brk.ore.fineness_ratio
        label = f"t10 = A (1 - exp(-c x)), c = {c:g} (energy_t10, broken rock)"
        note = "" if ore.fineness_ratio is not None else brk.ore.notes[-1]
    else:
        t10 = float(br.fragment_t10_pct(pb, ore.A_pct, convention))
        label = "t10 = A P_b (Eq. 12)" if convention == "paper" else "t10 = A (jk_t10, broken rock)"
    tn = ore.tn.tn_pct(t10)

    if grid_max_mm is None:
        # sqrt(2) series downwards from size * 2**0.25: the top class has mid = size exactly
        r = math.sqrt(2.0)
        n = max(1, math.ceil(math.log(size_mm * 2**0.25 / grid_min_mm) / math.log(r) - 1e-9))
        grid = SizeGrid(size_mm * 2**0.25 / r ** np.arange(n, -1, -1))
    else:
        grid = SizeGrid.geometric(grid_min_mm, grid_max_mm)
    parent = int(grid.class_of(size_mm))
    frag = br.fragment_psd(grid, parent, t10, ore.tn)

    con = console(120)
    head = Table(title=f"impact of a {size_mm:g} mm {ore.name} rock at {velocity:g} m/s ({breakage})")
    head.add_column("quantity")
    head.add_column("value")
    head.add_row("E_cs", f"{ecs_j:.4g} J/kg = {ecs_kwh:.4g} kWh/t")
    head.add_row("L_ref", f"{ore.l_ref_mm:g} mm" + (" (DEFAULT, not calibrated)" if ore.l_ref_is_default else ""))
    head.add_row("damage before", f"{damage:g}")
    head.add_row("P_b (Eq. 11)", f"{pb:.4g}")
    head.add_row(label, f"{t10:.4g} %")
    head.add_row("t10 of the population (broken and unbroken)", f"{pb * t10:.4g} %")
    for n, v in zip(br.TN_SIZES, tn, strict=True):
        head.add_row(f"t{n}", f"{v:.4g} %")
    head.add_row("damage of survivors", f"{float(res.damage):.4g} (Tavares, gamma = {ore.gamma:g})")
    head.add_row("fragment P80 / P50", f"{frag.p80_mm:.4g} / {frag.p50_mm:.4g} mm "
                 f"(parent class mid {grid.mids_mm[parent]:.4g} mm)")
    con.print(head)
    ft = Table(title="fragment PSD of a broken rock")
    for col in ("class (mm)", "mass %", "passing % at upper edge"):
        ft.add_column(col)
    for i in range(parent, -1, -1):
        lo = "0" if i == 0 else f"{grid.edges_mm[i]:.4g}"
        ft.add_row(f"{lo}-{grid.edges_mm[i + 1]:.4g}", f"{100 * frag.fractions[i]:.3g}",
                   f"{frag.passing_pct[i]:.4g}")
    con.print(ft)
    if note:
        con.print(f"note: {note}")
    if ore.l_ref_is_default:
        con.print(f"note: L_ref is the msmill default for {ore.name}; calibrate it with `msmill ore calibrate`.")
