"""``msmill validate DIR`` and ``msmill calibrate DIR``: surveys against the model (no physics here).

Both read a folder of experiment files (``msmill.model.experiments``), call the
model layer (``msmill.model.validation``, ``msmill.model.fitting``), render
every output in memory and then write the files (temp file, then rename).
"""

from __future__ import annotations

import time
import warnings
from pathlib import Path
from typing import Annotated

import typer

from msmill.errors import MsmillInputError

#: Most posterior samples of the stage parameters ``msmill calibrate`` refits with (each is a whole fit).
MAX_STAGE_SAMPLES = 64


def write_files(folder: Path, files: dict[str, bytes]) -> None:
    """Write ``files`` into ``folder`` as one atomic set with a manifest (``msmill.cli.output``)."""
    from msmill.cli.output import atomic_output

    with atomic_output(folder) as stage:
        for name, data in files.items():
            (stage / name).write_bytes(data)


def _console():
    from msmill.cli.console import console

    return console(140)


def validate(
    folder: Annotated[Path, typer.Argument(help="Folder of experiment TOML files (docs/validation.md).")],
    out: Annotated[Path | None, typer.Option("--out", "-o", help="Output folder (default DIR/validation).")] = None,
    stage_parameters: Annotated[str, typer.Option(help="Stage-parameter table ('default' = packaged).")] = "default",
    breakage: Annotated[str | None, typer.Option(help="Breakage sub-model (default: the model default, jk_t10).")] = None,
    damage: Annotated[str | None, typer.Option(help="Damage sub-model (default tavares).")] = None,
    ore_file: Annotated[list[Path] | None, typer.Option("--ore-file", help="Calibrated ore TOML (repeatable).")] = None,
    plots: Annotated[bool, typer.Option("--plots/--no-plots", help="Write PNG plots.")] = True,
) -> None:
    """Predict every survey and report its K-S statistic per experiment and per ore (paper Figs. 11-13)."""
    from rich.table import Table

    from msmill.cli.output import check_writable
    from msmill.errors import OutOfDomainWarning
    from msmill.model.experiments import read_experiments
    from msmill.model.validation import validate as run_validation

    check_writable(out if out is not None else folder / "validation", "--out")  # before any work
    t0 = time.perf_counter()
    ores = _ore_files(ore_file)
    es = read_experiments(folder, ores=ores, skip=ore_file or ())
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", OutOfDomainWarning)  # reported per survey in the table
        v = run_validation(es, stage_parameters, ores=ores, breakage=breakage, damage=damage)
    files = {"ks_by_experiment.csv": v.table.to_csv(index=False).encode(),
             "ks_by_ore.csv": v.summary.to_csv(index=False).encode()}
    if plots:
        files.update(_validation_plots(v, es))
    dest = out if out is not None else folder / "validation"
    write_files(dest, files)
    con = _console()
    t = Table(title=f"K-S by ore ({len(v.table)} surveys, {folder})")
    for col in ("ore", "n", "K-S mean", "median", "min", "max", "best", "worst", "outside domain"):
        t.add_column(col)
    for _, r in v.summary.iterrows():
        t.add_row(r["ore"], str(r["n"]), f"{r['ks_mean']:.3f}", f"{r['ks_median']:.3f}", f"{r['ks_min']:.3f}",
                  f"{r['ks_max']:.3f}", r["best_id"], r["worst_id"], str(r["n_outside_design_space"]))
    con.print(t)
    for _, r in v.table[v.table["outside_design_space"]].iterrows():
        con.print(f"outside the design space: {r['id']}: {r['domain_notes'].split(' | ')[0]}")
    _power_line(con, v.table)
    con.print(f"wrote {', '.join(files)} to {dest} ({time.perf_counter() - t0:.1f} s)")


def _ore_files(paths: list[Path] | None) -> dict:
    """``{name: Ore}`` of the user's ore files (``--ore-file``; one-line errors naming the file)."""
    from msmill.ore import Ore

    out: dict = {}
    for p in paths or []:
        o = Ore.from_toml(p)
        if o.name in out:
            raise MsmillInputError("--ore-file", str(p), f"ore files with different names ({o.name!r} given twice)")
        out[o.name] = o
    return out


def _power_line(con, table) -> None:
    from msmill.model.power import fit_no_load

    m = table.dropna(subset=["measured_power_kw"])
    if len(m) >= 3:
        try:
            icpt, slope, rmse = fit_no_load(m["impact_kw"], m["measured_power_kw"])
        except MsmillInputError:
            return
        con.print(f"measured power vs predicted impact power ({len(m)} surveys): no-load {icpt:.3g} kW, "
                  f"slope {slope:.3g}, rms {rmse:.2g} kW (measured = no-load + slope x impact power)")


def _validation_plots(v, es) -> dict[str, bytes]:
    from msmill.plots.model import png_bytes
    from msmill.plots.validation import ks_swarm, overlay

    files = {"ks_swarm.png": png_bytes(ks_swarm(v.table))}
    feeds = {e.id: e.feed_psd for e in es.surveys}
    for _, r in v.summary.iterrows():
        for which in ("best", "worst"):
            i = r[f"{which}_id"]
            ks = float(v.table.loc[v.table["id"] == i, "ks"].iloc[0])
            fig = overlay(v.measured[i], v.predicted[i], f"{r['ore']}, {which} prediction: {i} (K-S {ks:.3f})",
                          feed=feeds[i])
            files[f"overlay_{r['ore']}_{which}.png"] = png_bytes(fig)
    return files


def calibrate(
    folder: Annotated[Path, typer.Argument(help="Folder of experiment TOML files (docs/validation.md).")],
    out: Annotated[Path | None, typer.Option("--out", "-o", help="Output folder (default DIR/calibration).")] = None,
    fit: Annotated[list[str] | None, typer.Option("--fit", help="Parameter to fit (repeatable): l_ref_mm "
                                                  "(default), A_pct, b_t_per_kwh, gamma.")] = None,
    objective: Annotated[str, typer.Option(help="ssq (weighted squares of % passing) or ks (mean K-S).")] = "ssq",
    stage_parameters: Annotated[str, typer.Option(help="Stage-parameter table ('default' = packaged).")] = "default",
    impact_tests: Annotated[bool, typer.Option("--impact-tests/--no-impact-tests",
                                               help="Also fit the single-impact tests.")] = True,
    bound: Annotated[list[str] | None, typer.Option("--bound", help="NAME=LOW:HIGH bounds of a fitted "
                                                    "parameter (repeatable; defaults in docs/validation.md).")] = None,
    breakage: Annotated[str | None, typer.Option(help="Breakage sub-model of the survey fits (default: the model default, jk_t10).")] = None,
    damage: Annotated[str | None, typer.Option(help="Damage sub-model of the survey fits (default tavares).")] = None,
    ore_file: Annotated[list[Path] | None, typer.Option(
        "--ore-file", help="Your own ore TOML (msmill ore show --help; repeatable): experiments name it by its "
        "name, it overrides a built-in ore of that name.")] = None,
    hold_out: Annotated[str, typer.Option(help="Single-impact tests held out one 'test' or one 'speed' at a "
                                          "time (the held-out K-S).")] = "test",
    stage_samples: Annotated[int, typer.Option(help="Posterior samples of the stage parameters refitted with "
                                               "(their spread enters the s.e.; a surrogate's only; 0: none).")] = 8,
) -> None:
    """Fit L_ref (optionally A, b, gamma) per ore to the surveys; fit and compare breakage sub-models on lab tests."""
    import tomli_w

    from msmill.cli.output import check_writable
    from msmill.errors import OutOfDomainWarning
    from msmill.model.experiments import read_experiments
    from msmill.model.fitting import HOLD_OUT, calibrate_surveys, calibrated_ore
    from msmill.model.validation import SurveyModel
    from msmill.ore import get_ore

    check_writable(out if out is not None else folder / "calibration", "--out")  # before any work
    if hold_out not in HOLD_OUT:
        raise MsmillInputError("--hold-out", hold_out, "one of " + ", ".join(HOLD_OUT))
    if stage_samples != 0 and not 2 <= stage_samples <= MAX_STAGE_SAMPLES:
        raise MsmillInputError("--stage-samples", stage_samples, f"0 (none) or 2-{MAX_STAGE_SAMPLES}")
    t0 = time.perf_counter()
    ores = _ore_files(ore_file)
    es = read_experiments(folder, ores=ores, skip=ore_file or ())
    con = _console()
    files: dict[str, bytes] = {}
    fitted_rows: list[dict] = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", OutOfDomainWarning)
        for ore_name in es.ores("survey"):
            surveys = [e for e in es.surveys if e.ore == ore_name]
            t1 = time.perf_counter()
            ore = ores.get(ore_name) or get_ore(ore_name)
            model = SurveyModel(ore, surveys, stage_parameters, breakage=breakage, damage=damage)
            cal = calibrate_surveys(model, fit or ("l_ref_mm",), objective, bounds=_bounds(bound),
                                    stage_samples=stage_samples)
            new = calibrated_ore(ore, cal)
            files[f"{ore_name}_calibrated.toml"] = tomli_w.dumps(new.to_dict()).encode()
            files[f"{ore_name}_calibration.csv"] = cal.table.to_csv(index=False).encode()
            if cal.stage_samples:
                files[f"{ore_name}_stage_samples.csv"] = cal.stage_params.to_csv(index_label="sample").encode()
            fitted_rows += [{"ore": ore_name, "parameter": k, "value": cal.params[k], "se": cal.std_errors[k],
                             "se_jackknife": cal.jackknife_std_errors[k], "se_stage": cal.stage_std_errors[k],
                             "se_jacobian": cal.jacobian_std_errors[k], "stage_samples": cal.stage_samples,
                             "dof": cal.dof[k], **dict(zip(("ci95_low", "ci95_high"), cal.interval(k), strict=True))}
                            for k in cal.fitted]
            _print_calibration(con, cal, time.perf_counter() - t1)
        if fitted_rows:
            import pandas as pd

            files["survey_fits.csv"] = pd.DataFrame(fitted_rows).to_csv(index=False).encode()
        if impact_tests and es.impact_tests:
            files.update(_impact_outputs(con, es, ores, hold_out))
    if not files:
        raise MsmillInputError("experiments", str(folder), "at least one survey or single-impact test")
    dest = out if out is not None else folder / "calibration"
    write_files(dest, files)
    con.print(f"wrote {', '.join(files)} to {dest} ({time.perf_counter() - t0:.1f} s)")


def _bounds(texts: list[str] | None) -> dict[str, tuple[float, float]]:
    from msmill.model.fitting import SURVEY_FITTABLE

    out = {}
    for t in texts or []:
        name, _, rng = t.partition("=")
        try:
            lo, hi = (float(x) for x in rng.split(":"))
        except ValueError:
            raise MsmillInputError("--bound", t, "NAME=LOW:HIGH with numbers") from None
        if name not in SURVEY_FITTABLE or not 0 < lo < hi:
            raise MsmillInputError("--bound", t, f"NAME one of {', '.join(SURVEY_FITTABLE)}, 0 < LOW < HIGH")
        out[name] = (lo, hi)
    return out


def _print_calibration(con, cal, seconds: float) -> None:
    from rich.table import Table

    t = Table(title=f"{cal.ore}: {len(cal.table)} surveys, {cal.n_points} operating points, "
                    f"objective {cal.objective} ({seconds:.1f} s)")
    for col in ("parameter", "value", "s.e.", "95 % interval (t)", "of it: surveys (jackknife)",
                f"stage parameters ({cal.stage_samples} posterior samples)", "s.e. (Jacobian)"):
        t.add_column(col)
    for k in cal.fitted:
        stage = f"{cal.stage_std_errors[k]:.2g}" if cal.stage_samples else "not drawn"
        lo, hi = cal.interval(k)
        t.add_row(k, f"{cal.params[k]:.4g}", f"{cal.std_errors[k]:.2g}", f"{lo:.4g}-{hi:.4g} ({cal.dof[k]:.0f} dof)",
                  f"{cal.jackknife_std_errors[k]:.2g}", stage, f"{cal.jacobian_std_errors[k]:.2g}")
    con.print(t)
    if not cal.stage_samples:
        con.print("  s.e. without the stage parameters' uncertainty (a table has no posterior samples, "
                  "or --stage-samples 0): it is the surveys' scatter only")
    tb = cal.table
    con.print(f"  mean K-S: {tb['ks_before'].mean():.3f} with the start parameters, {tb['ks_fit'].mean():.3f} "
              f"fitted, {tb['ks_cv'].mean():.3f} leave-one-survey-out"
              + (f"; spline interpolation K-S {cal.interpolation_ks:.1e}" if cal.fitted == ("l_ref_mm",) else ""))


def _impact_outputs(con, es, ores: dict, hold_out: str) -> dict[str, bytes]:
    """Every breakage sub-model fitted to each ore's single-impact tests: table, CSVs."""
    import pandas as pd
    from rich.table import Table

    from msmill.model.fitting import FITTABLE, impact_report

    files: dict[str, bytes] = {}
    tables = []
    for ore_name in es.ores("single_impact"):
        tests = [t for t in es.impact_tests if t.ore == ore_name]
        t1 = time.perf_counter()
        summary, held = impact_report(tests, ores.get(ore_name, ore_name), hold_out=hold_out)
        files[f"{ore_name}_impact_heldout.csv"] = held.to_csv(index=False).encode()
        tables.append(summary.assign(ore=ore_name))
        how = "leave-one-test-out" if hold_out == "test" else "leave-one-speed-out"
        t = Table(title=f"{ore_name}: {len(tests)} single-impact tests at "
                        f"{len({float(x.impact_speed_m_s) for x in tests})} speeds, every breakage sub-model "
                        f"({time.perf_counter() - t1:.1f} s)")
        for col in ("sub-model", "K-S fitted", f"K-S {how}", "parameters +- s.e.", "on a bound", "identified"):
            t.add_column(col)
        for _, r in summary.iterrows():
            pars = ", ".join(f"{k} {r[k]:.4g} +- {r['se_bootstrap_' + k]:.2g}" for k in FITTABLE[r["submodel"]])
            spread = max(r[f"spread_{k}"] for k in FITTABLE[r["submodel"]])
            why = "a parameter on a bound" if r["on_bound"] else f"multi-start spread {spread:.2g}"
            t.add_row(r["submodel"], f"{r['ks_fit_mean']:.3f}", f"{r['ks_held_out_mean']:.3f}", pars,
                      r["on_bound"] or "none", "yes" if r["identified"] else f"NO ({why})")
        con.print(t)
        sig = ", ".join(f"{r['submodel']} {r['noise_sigma']:.3f}" for _, r in summary.iterrows())
        con.print("  s.e.: parametric bootstrap (the fit's products re-sieved with each retained mass scattered "
                  f"by the scatter the tests show about the fit, sigma: {sig}); jackknife and Jacobian "
                  "errors in impact_fits.csv; bounds scale with the tests' sizes and energies (lo_/hi_ columns)")
        for _, r in summary[summary["on_bound"] != ""].iterrows():
            con.print(f"  {r['submodel']}: {r['on_bound']} on its bound: the value is the bound's, not the data's")
        best = summary.loc[summary["ks_held_out_mean"].idxmin()]
        con.print(f"  {ore_name}: {best['submodel']} fits better (held-out K-S {best['ks_held_out_mean']:.3f})")
    files["impact_fits.csv"] = pd.concat(tables, ignore_index=True).to_csv(index=False).encode()
    return files
