"""``msmill sweep RUN.toml`` and ``msmill optimize RUN.toml`` (no physics here: msmill.model.operating)."""

from __future__ import annotations

import time
import warnings
from pathlib import Path
from typing import Annotated

import numpy as np
import typer

from msmill.errors import MsmillInputError


def _parse_senses(rest: str, field: str) -> list[str]:
    """``s1,s2,...`` -> names (a range ``a:b`` is refused: the sense is categorical; the names are checked by
    ``msmill.model.operating.mills_by_sense``)."""
    from msmill.machine import rotation_senses
    from msmill.model.operating import SENSE

    if ":" in rest:
        raise MsmillInputError(f"{field} {SENSE}", rest, "rotation senses separated by commas (no range), of "
                               + ", ".join(rotation_senses()))
    return [v.strip() for v in rest.split(",")]


def _parse_range(text: str, field: str, with_count: bool) -> tuple[str, list]:
    """``name=lo:hi[:n]`` or ``name=v1,v2,...`` -> (name, values); ``rotation_sense=s1,s2`` -> (name, senses)."""
    from msmill.model.operating import SENSE, VARIABLES

    name, sep, rest = text.partition("=")
    name = name.strip()
    if not sep or name not in (*VARIABLES, SENSE):
        raise MsmillInputError(field, text, "NAME=LOW:HIGH" + (":N or NAME=V1,V2,..." if with_count else "")
                               + f" with NAME one of {', '.join(VARIABLES)}, or {SENSE}=S1,S2,...")
    if name == SENSE:
        return name, _parse_senses(rest, field)
    try:
        if ":" in rest:
            parts = [float(p) for p in rest.split(":")]
            if with_count:
                if len(parts) not in (2, 3):
                    raise ValueError
                n = int(parts[2]) if len(parts) == 3 else 7
                if n < 1:
                    raise ValueError
                return name, list(np.linspace(parts[0], parts[1], n))
            if len(parts) != 2 or parts[0] > parts[1]:
                raise ValueError
            return name, parts
        if not with_count:
            raise ValueError
        return name, [float(p) for p in rest.split(",")]
    except ValueError:
        raise MsmillInputError(field, text, "NAME=LOW:HIGH" + (":N or NAME=V1,V2,..." if with_count else "")
                               + " with numbers (LOW <= HIGH)") from None


def _unique(pairs, field: str = "--var") -> dict[str, list[float]]:
    """``{name: values}``, refusing a variable given twice (the second would silently replace the first)."""
    out: dict[str, list[float]] = {}
    for name, values in pairs:
        if name in out:
            raise MsmillInputError(field, name, "each variable once")
        out[name] = values
    return out


def _grid_size(counts: list[int], field: str) -> None:
    """Refuse grids above the stated limit (:data:`msmill.validate.LIMITS` ``sweep_points``)."""
    from msmill.validate import limit

    limit(int(np.prod(counts)) if counts else 0, field, "sweep_points")


ENVELOPE_HELP = "DEM envelope (JSON) whose capacity constrains the points, instead of the shipped one."
CHECK_HELP = ("Points above the envelope's predicted capacity are infeasible (flagged in the table, excluded by the "
              "optimiser); above a lower bound (no DEM run choked) they are flagged only.")


def _build(run_file: Path, names: list[str], envelope: Path | None = None, capacity_check: bool = True,
           senses: list[str] | None = None, field: str = "--var"):
    """``(run file, mills, feed, op)``: ``mills`` is ``{sense: Mill}`` for ``senses``, else ``{None: Mill}``."""
    from msmill.cli.predict import apply_envelope
    from msmill.model.operating import SENSE, mills_by_sense
    from msmill.model.runfile import RunFile

    rf = RunFile.from_toml(run_file)
    if senses is None:
        mill, feed, op = rf.build()
        mills = {None: mill}
    else:  # the run file's own sense need not resolve: only the senses asked for are built
        mills = mills_by_sense(rf, senses, f"{field} {SENSE}")
        feed, op = rf.feed_psd(), rf.operating_point()
    for m in mills.values():
        apply_envelope(m, envelope, capacity_check)
        if "feed_scale" in names:
            m.grid = None  # the model grid follows each scaled feed's top size
    return rf, mills, feed, op


def sweep(
    run_file: Annotated[Path, typer.Argument(help="Run file (TOML) giving the ore, feed and other settings.")],
    var: Annotated[list[str], typer.Option("--var", help="NAME=LOW:HIGH[:N] or NAME=V1,V2 (one or two); "
                                           "rotation_sense=S1,S2: one mill per sense.")],
    out: Annotated[Path | None, typer.Option("--out", "-o", help="Output folder (default: <run dir>/sweep_out).")] = None,
    passing_size_mm: Annotated[float | None, typer.Option(help="Also report % passing at this size (mm).")] = None,
    no_load_kw: Annotated[float, typer.Option(help="Stated no-load power (kW) in the specific energy.")] = 0.0,
    envelope: Annotated[Path | None, typer.Option("--envelope", help=ENVELOPE_HELP)] = None,
    capacity_check: Annotated[bool, typer.Option("--capacity-check/--no-capacity-check", help=CHECK_HELP)] = True,
) -> None:
    """P80, throughput, specific energy and hold-up over one or two operating variables."""
    from msmill.cli.validate import _console, write_files
    from msmill.model.operating import SENSE, stage_parameter_lines, sweep_senses
    from msmill.model.operating import sweep as run_sweep
    from msmill.plots.model import png_bytes
    from msmill.plots.validation import sweep_plot

    t0 = time.perf_counter()
    axes = _unique(_parse_range(v, "--var", True) for v in var)
    _grid_size([len(v) for v in axes.values()], "--var")
    senses = axes.pop(SENSE, None)
    rf, mills, feed, op = _build(run_file, list(axes), envelope, capacity_check, senses)
    opts = dict(passing_size_mm=passing_size_mm, no_load_kw=no_load_kw)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # off-point warnings: see inside_design_space
        table = (run_sweep(mills[None], feed, op, axes, **opts) if senses is None
                 else sweep_senses(mills, feed, op, axes, **opts))
    x, hue = _plot_axes(list(axes), senses is not None)
    files = {"sweep.csv": table.to_csv(index=False).encode()}
    for y in ("p80_mm", "specific_energy_kwh_t", "holdup_t"):
        files[f"sweep_{y}.png"] = png_bytes(sweep_plot(table, x, y, hue))
    dest = out if out is not None else rf.path("sweep_out")
    write_files(dest, files)
    con = _console()
    shown = table.drop(columns="stage_parameters", errors="ignore")
    con.print(shown.to_string(index=False, float_format=lambda v: f"{v:.4g}"))
    _capacity_lines(con, mills, table)
    for line in stage_parameter_lines(mills) if senses is not None else []:
        con.print(line)
    con.print(f"wrote {', '.join(files)} to {dest} ({time.perf_counter() - t0:.1f} s)")


def _plot_axes(names: list[str], by_sense: bool) -> tuple[str, str | None]:
    """The sweep plots' x variable and hue: with the rotation sense swept, the sense is the hue
    (or the x axis when it is the only variable)."""
    from msmill.model.operating import SENSE

    if by_sense:
        return (names[0], SENSE) if names else (SENSE, None)
    return names[0], names[1] if len(names) == 2 else None


def _capacity_lines(con, mills: dict, table) -> None:
    """The capacity line of each mill (``{None: mill}``, or ``{sense: mill}`` over the sense's rows)."""
    from msmill.model.operating import SENSE

    for sense, mill in mills.items():
        rows = table if sense is None else table[table[SENSE] == sense]
        _capacity_line(con, mill, rows, "" if sense is None else f"{sense}: ")


def _capacity_line(con, mill, table, prefix: str = "") -> None:
    if mill.capacity is None:
        con.print(f"{prefix}capacity: no DEM envelope (no constraint)")
        return
    n = int(table["above_capacity"].sum())
    cap = mill.capacity
    if cap.lower_bound:
        from msmill.surrogate.capacity import demonstrated_rule

        con.print(f"{prefix}capacity (DEM envelope, a lower bound: {demonstrated_rule()}): {n} of {len(table)} points "
                  "above it (above_capacity; still feasible: the capacity there is unknown, not exceeded)")
        return
    con.print(f"{prefix}capacity (DEM envelope, {cap.n_choked} choked of {cap.n_steady + cap.n_choked} runs): {n} of "
              f"{len(table)} points above it (above_capacity, feasible = false)")


def optimize(
    run_file: Annotated[Path, typer.Argument(help="Run file (TOML) giving the ore, feed and other settings.")],
    bound: Annotated[list[str], typer.Option("--bound", help="NAME=LOW:HIGH, a variable to optimise (repeatable); "
                                             "rotation_sense=S1,S2: optimise each sense, report the best.")],
    goal: Annotated[str, typer.Option(help="max_feed or min_energy.")] = "max_feed",
    target_p80_mm: Annotated[float | None, typer.Option(help="Target: P80 at most this (mm).")] = None,
    target_passing: Annotated[str | None, typer.Option(help="Target: SIZE_MM:PCT, passing at least PCT %.")] = None,
    n_grid: Annotated[int, typer.Option(help="Grid points per variable.")] = 7,
    no_load_kw: Annotated[float, typer.Option(help="Stated no-load power (kW) in the specific energy.")] = 0.0,
    l_ref_se_mm: Annotated[float | None, typer.Option(help="L_ref standard error (from msmill calibrate): "
                                                      "re-optimise at L_ref +- s.e.")] = None,
    out: Annotated[Path | None, typer.Option("--out", "-o", help="Output folder (default: <run dir>/optimize_out).")] = None,
    envelope: Annotated[Path | None, typer.Option("--envelope", help=ENVELOPE_HELP)] = None,
    capacity_check: Annotated[bool, typer.Option("--capacity-check/--no-capacity-check", help=CHECK_HELP)] = True,
) -> None:
    """Settings within the bounds reaching a target P80 (or passing) at the highest feed or lowest energy."""
    from msmill.cli.validate import _console, write_files
    from msmill.model.operating import SENSE, optimize_senses, stage_parameter_lines
    from msmill.model.operating import optimize as run_optimize
    from msmill.plots.model import png_bytes
    from msmill.plots.validation import pareto_plot

    t0 = time.perf_counter()
    bounds = _unique((_parse_range(b, "--bound", False) for b in bound), "--bound")
    senses = bounds.pop(SENSE, None)
    bounds = {k: (v[0], v[1]) for k, v in bounds.items()}
    opts = dict(goal=goal, **_targets(target_p80_mm, target_passing, n_grid, len(bounds)), no_load_kw=no_load_kw)
    rf, mills, feed, op = _build(run_file, list(bounds), envelope, capacity_check, senses, "--bound")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        if senses is None:
            res, by_sense, mill = run_optimize(mills[None], feed, op, bounds, **opts), None, mills[None]
        else:
            by_sense = optimize_senses(mills, feed, op, bounds, **opts)
            res = by_sense.best or next(iter(by_sense.by_sense.values()))  # no sense met it: the first's closest
            mill = mills[by_sense.best_sense or senses[0]]
        sens = None
        if l_ref_se_mm is not None and res.settings is not None:
            sens = _sensitivity(mill, l_ref_se_mm, feed, op, bounds, opts)
    candidates = res.candidates if by_sense is None else by_sense.candidates()
    front = res.front if by_sense is None else by_sense.front()
    files = {"candidates.csv": candidates.to_csv(index=False).encode(),
             "pareto_front.csv": front.to_csv(index=False).encode(),
             "pareto.png": png_bytes(pareto_plot(candidates[candidates["feasible"]], front, res.row, target_p80_mm))}
    if by_sense is not None:
        files["senses.csv"] = by_sense.summary().to_csv(index=False).encode()
    if sens is not None:
        files["optimum_sensitivity.csv"] = sens.to_csv(index=False).encode()
    dest = out if out is not None else rf.path("optimize_out")
    write_files(dest, files)
    con = _console()
    _capacity_lines(con, mills, candidates)
    if by_sense is not None:
        for line in _sense_lines(by_sense) + stage_parameter_lines(mills):
            con.print(line)
    if by_sense is not None and by_sense.best is None:
        con.print(f"no rotation sense ({', '.join(senses)}) reaches {res.target} within the bounds "
                  "(each one's closest above)")
    else:
        _print_optimum(con, res, "" if by_sense is None else f" of every rotation sense: {by_sense.best_sense}")
    if sens is not None:
        con.print("optimum at L_ref -+ s.e.:")
        con.print(sens.to_string(index=False, float_format=lambda v: f"{v:.4g}"))
    elif res.settings is not None:
        con.print("uncertainty: give --l-ref-se-mm (from msmill calibrate) to re-optimise at L_ref +- s.e.")
    con.print(f"wrote {', '.join(files)} to {dest} ({time.perf_counter() - t0:.1f} s)")


def _targets(target_p80_mm: float | None, target_passing: str | None, n_grid: int, n_bounds: int) -> dict:
    """The optimiser's checked ``target_p80_mm``, ``target_passing`` and ``n_grid``."""
    from msmill.validate import integer, limit, number

    integer(n_grid, "--n-grid", ge=1)
    limit(n_grid, "--n-grid", "n_grid")
    _grid_size([n_grid] * n_bounds, "--n-grid")
    if target_p80_mm is not None:
        number(target_p80_mm, "--target-p80-mm", unit="mm", gt=0)
    tp = None
    if target_passing is not None:
        try:
            a, b = (float(x) for x in target_passing.split(":"))
        except ValueError:
            raise MsmillInputError("--target-passing", target_passing, "SIZE_MM:PCT, e.g. 2:60") from None
        number(a, "--target-passing (size)", unit="mm", gt=0)
        number(b, "--target-passing (percent)", unit="%", gt=0, le=100)
        tp = (a, b)
    return dict(target_p80_mm=target_p80_mm, target_passing=tp, n_grid=n_grid)


def _sensitivity(mill, l_ref_se_mm: float, feed, op, bounds: dict, opts: dict):
    """The optimum at L_ref -+ s.e. of ``mill`` (``msmill.model.operating.optimum_sensitivity``)."""
    import dataclasses

    from msmill.model.mill import Mill
    from msmill.model.operating import optimum_sensitivity

    def make(L: float) -> Mill:
        return Mill(dataclasses.replace(mill.ore, l_ref_mm=L), mill.provider, grid=mill.grid,
                    breakage=mill.breakage.name, damage=mill.damage.name, envelope=mill.capacity)

    return optimum_sensitivity(make, mill.ore.l_ref_mm, l_ref_se_mm, feed, op, bounds, **opts)


def _outputs(r: dict) -> str:
    """``P80 ... mm, ... t/h, ... kWh/t, ... kW`` of a result row."""
    return (f"P80 {r['p80_mm']:.4g} mm, {r['throughput_tph']:.4g} t/h, {r['specific_energy_kwh_t']:.3g} kWh/t, "
            f"{r['power_kw']:.3g} kW")


def _sense_lines(by_sense) -> list[str]:
    """One line per rotation sense: its optimum (or its closest miss) and whether it met the target."""
    lines = []
    for sense, res in by_sense.by_sense.items():
        r = res.row if res.row is not None else res.closest
        at = ", ".join(f"{k} = {r[k]:.4g}" for k in res.bounds) if r is not None else ""
        met = (f"meets {res.target}; best" if res.row is not None else f"misses {res.target}; the closest")
        best = " (best)" if sense == by_sense.best_sense else ""
        lines.append(f"rotation sense {sense}: {met}" + (f": {at}" if at else "")
                     + (f" -> {_outputs(r)}" if r is not None else "") + best)
    return lines


def _print_optimum(con, res, which: str = "") -> None:
    """The optimum of ``res`` (or what the bounds reach), its band and the bounds it sits on."""
    if res.settings is None:
        c = res.closest
        reach = ""
        if c is not None:
            got = (f"P80 {c['p80_mm']:.4g} mm" if res.target.startswith("P80") else
                   next(f"passing {k[8:-6]} mm {c[k]:.4g} %" for k in c if k.startswith("passing_")))
            reach = (f"; the closest: {got} at " + ", ".join(f"{k} = {c[k]:.4g}" for k in res.bounds)
                     + ("" if c["feasible"] else " (infeasible)"))
        con.print(f"no setting within the bounds reaches {res.target} ({len(res.candidates)} evaluated){reach}")
        return
    r = res.row
    con.print(f"best{which} ({res.goal}, {res.target}): "
              + ", ".join(f"{k} = {v:.4g}" for k, v in res.settings.items())
              + f" -> {_outputs(r)}"
              + ("" if r["inside_design_space"] else " (outside the design space)")
              + _capacity_text(r))
    if "p80_low_mm" in r:
        con.print(f"P80 band {r['p80_low_mm']:.4g}-{r['p80_high_mm']:.4g} mm")
    on = res.at_bounds()
    if on:
        con.print("the optimum sits on a bound: " + ", ".join(
            f"{k} at its {side} bound {res.bounds[k][0 if side == 'low' else 1]:g}" for k, side in on.items())
            + " (a wider range may do better)")


def _capacity_text(row: dict) -> str:
    """``; capacity ...`` of a result row (a lower bound when no DEM run choked), or ''."""
    cap = row.get("capacity_tph", np.nan)
    if not np.isfinite(cap):
        return ""
    if row.get("capacity_is_lower_bound"):
        return f"; capacity >= {cap:.4g} t/h (no DEM run choked)"
    return f"; capacity {cap:.4g} t/h, P(steady) {row['p_steady']:.2f}"
