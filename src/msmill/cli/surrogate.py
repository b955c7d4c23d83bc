"""``msmill surrogate``: fit, score and plan with the GP surrogate (thin layer over msmill.surrogate).

* ``fit SOURCES... --out FILE``: train from stage-parameter tables and/or
  run-statistics JSON files (``default`` = the packaged table), print the
  leave-one-out accuracy, write the surrogate JSON (and a predicted-vs-DEM plot).
* ``score FILE``: the leave-one-out accuracy of a saved surrogate.
* ``plan FILE|none --batch N``: the next batch of DEM design points.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console
from rich.table import Table

from msmill.cli.console import console
from msmill.errors import MsmillInputError

app = typer.Typer(help="Gaussian-process surrogate of the stage statistics: fit, score, plan.",
                  no_args_is_help=True)


def _console() -> Console:
    return console(140)


def load_runs(sources: list[str]) -> list:
    """RunStatistics from table files (JSON/TOML/CSV), run-statistics JSON files or ``default``."""
    from msmill.model.providers import DEFAULT_TABLE, default_table_path, read_simple_table
    from msmill.stageparams import RunStatistics, StageParameterTable

    runs = []
    for src in sources:
        p = default_table_path() if src in (DEFAULT_TABLE, "table") else Path(src)
        if not p.is_file():
            raise MsmillInputError("sources", src, "existing table or run-statistics files (or 'default')")
        if p.suffix.lower() in (".toml", ".csv"):
            runs += list(read_simple_table(p).runs)
            continue
        try:
            kind = json.loads(p.read_text(encoding="utf-8")).get("kind")
        except (json.JSONDecodeError, AttributeError):
            raise MsmillInputError(str(p), "not a JSON object", "a table or run-statistics JSON") from None
        runs += list(StageParameterTable.from_json(p).runs) if kind == "stage_parameter_table" \
            else [RunStatistics.from_json(p)]
    return runs


def _print_scores(report, con: Console) -> None:
    t = Table(title=f"leave-one-out accuracy per stage ({report.method}, mean over runs)")
    cols = [("stage", "stage"), ("KL primary v", "kl_primary_velocity"),
            ("KL secondary v", "kl_secondary_velocity"), ("KL count", "kl_count"),
            ("streams MAE", "stream_abs_error"), ("hit prob. MAE", "hit_abs_error"),
            ("repr. KL prim.", "representation_kl_primary"), ("repr. KL sec.", "representation_kl_secondary")]
    for head, _ in cols:
        t.add_column(head, justify="right")
    for _, r in report.per_stage.iterrows():
        t.add_row(f"{int(r['stage'])}", *[f"{r[c]:.3g}" for _, c in cols[1:]])
    con.print(t)
    s = report.summary()
    con.print(f"mean KL velocities {s['mean_kl_velocity']:.3g}, counts {s['mean_kl_count']:.3g}, all "
              f"{s['mean_kl']:.3g} (paper: 0.012 after 177 runs); streams MAE {s['stream_mae']:.3g}, "
              f"hit-probability MAE {s['hit_probability_mae']:.3g}; representation floor "
              f"{s['representation_kl']:.3g}; {s['n_runs']} runs")
    d = report.per_point
    for k in range(1, 4):
        if d[d.columns[k + 2]].nunique() <= 1:
            con.print(f"note: every run has {d.columns[k + 2]} = {d.iloc[0, k + 2]:g}: the surrogate has no "
                      f"information on its effect (predictions away from it revert to the mean, with wide bands)")


def _plot(report, path: Path | None) -> None:
    if path is None:
        return
    from msmill.plots.model import png_bytes
    from msmill.plots.surrogate import loo_figure

    path.write_bytes(png_bytes(loo_figure(report)))


@app.command("fit")
def fit_cmd(
    sources: Annotated[list[str], typer.Argument(help="Table / run-statistics files, or 'default'.")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Surrogate JSON to write.")] = Path("surrogate.json"),
    restarts: Annotated[int, typer.Option(help="Optimiser restarts per target.")] = 2,
    seed: Annotated[int, typer.Option(help="Seed of the restarts.")] = 0,
    refit_loo: Annotated[bool, typer.Option("--refit-loo/--closed-form-loo",
                                            help="Refit the GPs for every left-out run.")] = False,
    plot: Annotated[Path | None, typer.Option(help="Write the predicted-vs-DEM plot (PNG).")] = None,
    filling_curves: Annotated[str, typer.Option(
        help="Filling curves of its predictions: 'own' (the runs') or 'table' (the packaged stage table's, "
             "for runs that start from a filled mill).")] = "own",
) -> None:
    """Train the surrogate, print its leave-one-out accuracy and write it as JSON."""
    from msmill.surrogate import persist
    from msmill.surrogate.accuracy import loo_scores
    from msmill.surrogate.stage_model import StageSurrogate

    if restarts < 0:
        raise MsmillInputError("restarts", restarts, "an integer >= 0")
    if filling_curves not in ("own", "table"):
        raise MsmillInputError("filling_curves", filling_curves, "'own' or 'table'")
    runs = load_runs(sources)
    model = StageSurrogate(n_restarts=restarts, random_state=seed,
                           filling_curves=None if filling_curves == "own" else filling_curves).fit(runs)
    report = loo_scores(model, refit=refit_loo)
    con = _console()
    con.print(repr(model))
    _print_scores(report, con)
    prov = {"command": f"msmill surrogate fit {' '.join(sources)} --out {out} --restarts {restarts} --seed {seed}"
                       f" --filling-curves {filling_curves}",
            "store_query": {"sources": list(sources)},
            "metrics": {"method": report.method, **report.summary()}}
    persist.save(model, out, prov)
    _plot(report, plot)
    con.print(f"wrote {out}" + (f" and {plot}" if plot else ""))


@app.command("score")
def score_cmd(
    surrogate: Annotated[Path, typer.Argument(help="Surrogate JSON (msmill surrogate fit), or 'default' for "
                                                   "the shipped one.")],
    refit: Annotated[bool, typer.Option("--refit/--closed-form", help="Refit for every left-out run.")] = False,
    plot: Annotated[Path | None, typer.Option(help="Write the predicted-vs-DEM plot (PNG).")] = None,
) -> None:
    """Print the leave-one-out accuracy of a saved surrogate."""
    from msmill.surrogate import persist
    from msmill.surrogate.accuracy import loo_scores

    if str(surrogate) == "default" and not surrogate.exists():
        from msmill.model.providers import default_surrogate_path

        shipped = default_surrogate_path()
        if shipped is None:
            raise MsmillInputError("surrogate", "default", "a surrogate JSON file (no shipped surrogate installed)")
        surrogate = shipped
    model = persist.load(surrogate)
    con = _console()
    con.print(repr(model))
    report = loo_scores(model, refit=refit)
    _print_scores(report, con)
    _plot(report, plot)


@app.command("plan")
def plan_cmd(
    surrogate: Annotated[str, typer.Argument(help="Surrogate JSON, or 'none' for the initial design.")],
    batch: Annotated[int, typer.Option(help="Number of design points.")] = 8,
    out: Annotated[Path | None, typer.Option("--out", "-o", help="Write the points as CSV.")] = None,
    n_initial: Annotated[int, typer.Option(help="Runs before acquisition replaces Sobol.")] = 10,
    cost_power: Annotated[float, typer.Option(help="Exponent of the expected cost (0 ignores cost).")] = 1.0,
    seed: Annotated[int, typer.Option(help="Sobol scrambling seed.")] = 0,
) -> None:
    """Plan the next batch of DEM runs (space-filling, then cost-aware kriging believer)."""
    import pandas as pd

    from msmill.stageparams import DESIGN_INPUTS
    from msmill.surrogate import persist
    from msmill.surrogate.active import CostModel, group_weights, plan_batch

    model = None if surrogate.lower() == "none" else persist.load(surrogate)
    cost = weights = None
    if model is not None:
        cost = CostModel.from_runs(model.training_.runs)
        weights = group_weights(model.training_.layout.names)
    plan = plan_batch(None if model is None else model.gp_, batch, n_initial=n_initial, cost=cost,
                      cost_power=cost_power, weights=weights, seed=seed)
    frame = pd.DataFrame(plan.points, columns=list(DESIGN_INPUTS))
    frame["score"] = plan.score
    frame["expected_cost_s"] = plan.expected_cost_s
    t = Table(title=f"next batch ({plan.method})")
    for c in frame.columns:
        t.add_column(c, justify="right")
    for _, r in frame.iterrows():
        t.add_row(*[f"{v:.4g}" for v in r])
    con = _console()
    con.print(t)
    if out is not None:
        frame.to_csv(out, index=False)
        con.print(f"wrote {out}")
