"""The training campaign's results page (``msmill campaign report``): ``docs/campaign-results.md`` and its figures.

Runs on whatever the export holds (re-run it after every batch):

* totals: runs, DEM wall hours, sizes;
* learning curve: closed-form leave-one-out mean KL of the velocity
  distributions against the number of runs (runs in the order they were
  computed), with the paper's 0.012 after 177 runs and the quantile
  representation's floor;
* the design points (pair plot) and the DEM cost per run against size and feed rate;
* the surrogate's trends of the streams and the hit probability against speed,
  size, feed rate and gate angle, stage by stage, and three of the paper's
  qualitative claims tested against the DEM runs and the surrogate (with the
  surrogate's posterior spread; no tuning);
* the product P80 at 10/30/60 t/h and gates 0/40/80 deg (``msmill predict``'s model);
* the slice-to-full correction, when the export holds paired full-mill runs;
* the capacity (operating envelope, ``msmill.surrogate.capacity``) of the shipped envelope: a map over gate angle and
  speed, the probability of steady flow against feed, the choked runs held out one at a time, and the
  capacity's sensitivity to the model's priors.

The numbers come from :mod:`msmill.pipeline.results`, the figures from :mod:`msmill.plots.campaign`;
this module writes the text (an edge: it runs :class:`msmill.model.Mill` for the P80 table).
"""

from __future__ import annotations

import datetime as dt
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from msmill.errors import MsmillInputError
from msmill.pipeline.results import (
    CAPACITY_AT,
    CampaignRuns,
    choked_loo,
    domain_centre,
    hours_by_size_band,
    kl_by_sample_size,
    learning_curve,
    load_campaign,
    passed_shares,
    point_key,
    prior_sensitivity,
    range_change,
    rocks_per_s,
    run_settings_by_point,
    run_table,
    spearman,
    sweep,
    warn_counts,
)
from msmill.plots.campaign import plot_capacity, plot_cost, plot_design, plot_learning, plot_trends

__all__ = ["CampaignReport", "checkout_root", "render", "write_campaign_report"]

#: the command named on the page
COMMAND = "msmill campaign report"


def checkout_root() -> Path:
    """The source checkout msmill runs from (the folder with ``pyproject.toml``), else the working directory."""
    for p in Path(__file__).resolve().parents:
        if (p / "pyproject.toml").is_file():
            return p
    return Path.cwd()


def _rel(p: Path | str) -> str:
    """A path relative to the checkout when inside it, else as given."""
    root = checkout_root()
    q = Path(p).resolve()
    return str(q.relative_to(root)) if q.is_relative_to(root) else str(p)


def markdown_table(df: Any) -> list[str]:
    """A DataFrame as Markdown table lines (no extra dependency)."""
    head = "| " + " | ".join(map(str, df.columns)) + " |"
    return [head, "|" + "---|" * len(df.columns), *("| " + " | ".join(f"{v:g}" if isinstance(v, float) else str(v)
                                                           for v in row) + " |" for row in df.itertuples(index=False))]


def _dem_verdict(rho: list[tuple[float, float]], sign: int) -> str:
    """Stages where the DEM runs' rank correlation (p < 0.05) has the claimed ``sign``, and those against it."""
    agree = [i + 1 for i, (r, p) in enumerate(rho) if p < 0.05 and sign * r > 0]
    disagree = [i + 1 for i, (r, p) in enumerate(rho) if p < 0.05 and sign * r < 0]
    parts = [f"DEM (p < 0.05): agrees on stages {agree or 'none'}"]
    if disagree:
        parts.append(f"**disagrees on stages {disagree}**")
    return ", ".join(parts)


def _verdict(delta: np.ndarray, sd: np.ndarray, sign: int) -> str:
    """How many stages' surrogate change has the claimed ``sign`` by more than 2 posterior sd."""
    z = sign * delta / np.maximum(sd, 1e-12)
    agree, disagree = int(np.sum(z > 2)), int(np.sum(z < -2))
    n = delta.size
    if agree == n:
        return "agrees (every stage, > 2 sd)"
    if disagree:
        return f"disagrees on {disagree} of {n} stages (> 2 sd the other way); agrees on {agree}"
    return f"agrees on {agree} of {n} stages (> 2 sd); the rest within the surrogate's uncertainty"


def claims(provider: Any, runs: Any, at: dict[str, float]) -> list[str]:
    """Markdown lines testing three of the paper's qualitative claims."""
    n_st = provider.surrogate.n_stages
    kick = runs[[f"s{s}.kickback" for s in range(1, n_st + 1)]].to_numpy()
    lowest = np.argmin(kick, axis=1) + 1
    mean_at, _ = sweep(provider, "gate_deg", np.array([at["gate_deg"]]), at)
    k_sur = mean_at["kickback"][:, 0]
    out = ["| claim (paper) | DEM runs | surrogate (change over the trained range, +- posterior sd, per stage) "
           "| verdict |", "|---|---|---|---|"]
    share, n_top = float(np.mean(lowest == 1)), int(np.sum(lowest == 1))
    if np.all(lowest == 1) and np.argmin(k_sur) == 0:
        verdict = "agrees (every run and the surrogate)"
    elif share >= 0.9 and np.argmin(k_sur) == 0:
        verdict = (f"agrees in {n_top} of {lowest.size} runs ({share:.0%}) and in the surrogate; the other runs "
                   "have another stage lowest")
    else:
        verdict = (f"**disagrees**: stage 1 lowest in {share:.0%} of the runs, surrogate's lowest: "
                   f"stage {np.argmin(k_sur) + 1}")
    out.append(f"| the top stage has the least kickback | stage with the lowest kickback per run: "
               f"{', '.join(f'{s}: {int(np.sum(lowest == s))}' for s in range(1, n_st + 1))} | kickback at the "
               f"centre: {' / '.join(f'{v:.3f}' for v in k_sur)} | {verdict} |")
    for var, q, sign, text in (("speed_rpm", "pass_through", +1, "pass-through rises with speed"),
                               ("size_mm", "refeed", -1, "refeed falls with particle size")):
        rho = [spearman(runs[var], runs[f"s{s}.{q}"]) for s in range(1, n_st + 1)]
        delta, sd = range_change(provider, var, at, q)
        out.append(f"| {text} | Spearman rho({var}, {q}) per stage (p): "
                   f"{' / '.join(f'{r:+.2f} ({p:.2g})' for r, p in rho)} | "
                   f"{' / '.join(f'{d:+.3f}+-{s:.3f}' for d, s in zip(delta, sd, strict=True))} | "
                   f"{_dem_verdict(rho, sign)}; surrogate: {_verdict(delta, sd, sign)} |")
    return out


def p80_table(provider: Any) -> list[str]:
    """Product P80 (and band) of the UG2 example at 10/30/60 t/h and gates 0/40/80 deg."""
    from msmill.machine import OperatingPoint
    from msmill.model import Mill
    from msmill.model.runfile import RunFile

    path = checkout_root() / "examples/ug2.toml"
    if not path.is_file():
        return [f"`{path}` not found: the P80 table needs a source checkout of msmill."]
    rf = RunFile.from_toml(path)
    feed, op, md = rf.feed_psd(), rf.operating_point(), rf.model
    m = Mill(rf.ore_obj(), provider, rf.machine_obj(), transport=md.transport, impacts=md.impacts,
             breakage=md.breakage, damage=md.damage, solver=md.solver, grid=rf.model_grid(feed), band_samples=16)
    rows = ["| feed (t/h) | gate (deg) | P80 (mm) | 5-95 % band (mm) | note |", "|---|---|---|---|---|"]
    for f, g in ((10, 40), (30, 40), (60, 40), (30, 0), (30, 80)):
        with warnings.catch_warnings(record=True) as w:
            warnings.simplefilter("always")
            res = m.run(feed, OperatingPoint(feed_tph=f, speed_rpm=op.speed_rpm, gate_deg=g), timeseries=False)
        note = "outside the trained feed/gate range" if any(
            ("feed_tph" in str(x.message) or "gate_deg" in str(x.message)) for x in w) else ""
        if res.capacity_tph is not None and f > res.capacity_tph:
            note += f"{'; ' if note else ''}above the DEM capacity {res.capacity_tph:.0f} t/h (P(steady) " \
                    f"{res.probability_steady:.2f})"
        lo, hi = res.p80_band_mm
        rows.append(f"| {f} | {g} | {res.p80_mm:.2f} | {lo:.2f}-{hi:.2f} | {note} |")
    return rows


def sense_table() -> list[str]:
    """The UG2 example's prediction with each rotation sense that has a shipped surrogate (issue 37 item 4)."""
    from msmill.machine import rotation_senses
    from msmill.model.providers import sense_surrogate_path
    from msmill.model.runfile import RunFile

    path = checkout_root() / "examples/ug2.toml"
    if not path.is_file():
        return [f"`{path}` not found: the table needs a source checkout of msmill."]
    rows = ["| rotation sense | surrogate (runs) | P80 (mm) | 5-95 % band (mm) | passing 75 um (%) | residence (s) | "
            "time to steady state (s) | impact energy (kWh/t) | product on extrapolated statistics (%) |",
            "|---|---|---|---|---|---|---|---|---|"]
    base = RunFile.from_toml(path)
    for sense in rotation_senses():
        if sense_surrogate_path(sense) is None:
            rows.append(f"| {sense} | none shipped | | | | | | | |")
            continue
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            mill, feed, op = base.with_rotation_sense(sense).build()
            res = mill.run(feed, op)
        lo, hi = res.p80_band_mm
        residence_s = 3600.0 * float(res.stages["holdup_t"].sum()) / res.feed_tph
        runs = getattr(mill.provider, "surrogate", None)
        n = len(runs.training_.runs) if runs is not None and runs.training_ is not None else "?"
        rows.append(f"| {sense} | {n} | {res.p80_mm:.2f} | {lo:.2f}-{hi:.2f} | {float(res.product_psd.passing_at(0.075)):.2f} | "
                    f"{residence_s:.3f} | {res.time_to_steady_state_s:.2f} | {res.specific_impact_energy_kwh_t:.3f} | "
                    f"{res.extrapolated_product_pct:.1f} |")
    return [*rows, "", "`examples/ug2.toml` as shipped (30 t/h, 1500/3000 rpm, gates 40 deg, 64 posterior samples in "
                       "the band) with `[machine] rotation_sense` set to each sense; residence = mass held in the mill "
                       "over the feed rate. A sense without a shipped surrogate has no prediction "
                       "(`msmill predict` says so in one line)."]


def pair_table(slices: list, fulls: list) -> list[str]:
    """Slice against full-mill values of the paired runs, stage by stage."""
    from msmill.surrogate.fidelity import match_pairs

    pairs = match_pairs([r.statistics for r in slices], [r.statistics for r in fulls])
    if not pairs:
        return []
    out = ["| design point | stage | kickback slice / full | refeed | pass-through | hit probability | "
           "lambda slice / full (ratio) |", "|---|---|---|---|---|---|---|"]
    for sl, fu in pairs:
        d = sl.design
        for a, b in zip(sl.stages, fu.stages, strict=True):
            out.append(f"| {d.size_mm:g} mm, {d.feed_tph:g} t/h, {d.speed_rpm:g} rpm, {d.gate_deg:g} deg | "
                       f"{a.stage} | {a.kickback:.3f} / {b.kickback:.3f} | {a.refeed:.3f} / {b.refeed:.3f} | "
                       f"{a.pass_through:.3f} / {b.pass_through:.3f} | {a.primary_hit_probability:.3f} / "
                       f"{b.primary_hit_probability:.3f} | {a.secondary_lambda:.3f} / {b.secondary_lambda:.3f} "
                       f"({b.secondary_lambda / a.secondary_lambda:.2f}) |")
    return [*out, ""]


def _made_with(settings: dict) -> str:
    """The steady-state windows and time limit a run was made with, in words."""
    w, t = settings.get("steady_window_s"), settings.get("max_time_s")
    auto = "residence-scaled limit" if "residence_factor" in settings else f"fixed limit {t:g} s" if t else "?"
    return f"{w:g} s windows, {auto}" if w else "?"


def choked_table(model: Any, pts: list, settings: dict | None = None) -> list[str]:
    """Each choked run: the capacity and P(steady) at its feed, fitted with and without it (leave one out)."""
    settings = settings or {}
    rows = ["| size (mm) | speed (rpm) | gate (deg) | feed (t/h) | passed (t/h) | run made with | "
            "capacity, all runs (t/h) | P(steady) at its feed, all runs | capacity, without this run (t/h) | "
            "P(steady), without it |",
            "|---|---|---|---|---|---|---|---|---|---|"]
    for r in choked_loo(model, pts):
        p = r.point
        lc, lp = ((f"{r.loo_capacity_tph:.1f}", f"{r.loo_probability_steady:.2f}") if r.loo_capacity_tph is not None
                  else ("- (no other choked run)", "-"))
        made = _made_with(settings.get(point_key(p.size_mm, p.feed_tph, p.speed_rpm, p.gate_deg), {}))
        rows.append(f"| {p.size_mm:.1f} | {p.speed_rpm:.0f} | {p.gate_deg:.1f} | {p.feed_tph:.1f} | "
                    f"{p.throughput_tph:.1f} | {made} | {r.capacity_tph:.1f} | {r.probability_steady:.2f} | {lc} | "
                    f"{lp} |")
    return rows


def _older_settings_caveat(pts: list, settings: dict) -> list[str]:
    """A caveat line when choked runs were made with other steady-state windows than today's criterion."""
    from msmill.steadystate import SteadyStateCriterion

    today = SteadyStateCriterion().window_s
    old = [p for p in pts if p.outcome == "choked" and (settings.get(point_key(p.size_mm, p.feed_tph, p.speed_rpm,
                                                                         p.gate_deg), {}).get("steady_window_s")
                                                         not in (None, today))]
    if not old:
        return []
    return [f"- {len(old)} of the choked runs were made with other run settings than today's (steady-state "
            f"windows of {today:g} s and a time limit scaled with the residence time): their outcome was "
            "recomputed from a time series that stopped when the old criterion was met, possibly before today's "
            "criterion can see steady state, and a filling mill's product rate looks like a choke's. Re-run such "
            "points with today's settings before trusting them.", ""]


def passed_share(pts: list) -> str:
    """The throughput passed in the measurement window as a share of the feed, steady against choked runs."""
    st, ch = passed_shares(pts)
    if not st.size:
        return ""
    q10, q50, q90 = np.percentile(st, [10, 50, 90])
    return (f"- The product rate the runs passed in their measurement window, as a share of their feed: steady runs "
            f"median {q50:.2f} (10-90 %: {q10:.2f}-{q90:.2f}, lowest {st.min():.2f}; {int((st < 0.9).sum())} of "
            f"{st.size} below 0.9), choked runs " + ", ".join(f"{x:.2f}" for x in ch) + ". The choked runs' "
            f"shares lie inside the steady runs' spread (at 30 mm and 10 t/h a slice receives about {rocks_per_s():.0f} "
            "rocks a second, so a 1 s window's product rate is noisy): "
            "the choke verdict (product below (1 - balance_tol) F in both of the last two windows and not "
            "catching up, docs/mill-dem.md) sits close to that noise, so a verdict near the boundary can go either "
            "way.")


def prior_table(pts: list) -> list[str]:
    """Capacity at :data:`CAPACITY_AT` under the prior variants."""
    head = "| priors | sigma | " + " | ".join(f"{s:g} mm, {v:g} rpm, {g:g} deg" for s, v, g in CAPACITY_AT) + " |"
    rows = [head, "|" + "---|" * (2 + len(CAPACITY_AT))]
    for name, sigma, caps in prior_sensitivity(pts):
        rows.append(f"| {name} | {sigma:.2f} | " + " | ".join(f"{c:.0f}" for c in caps) + " |")
    return rows


#: grid of the lower-bound table (no choked run): sizes (mm), upper-stage speeds (rpm), gate angles (deg)
DEMONSTRATED_AT = ((6.0, 10.0, 14.0, 20.0, 28.0), (1200.0, 1550.0, 1900.0), (0.0, 20.0, 40.0, 60.0, 80.0))


def demonstrated_section(env: Any, model: Any, missing: list, env_rel: str) -> list[str]:
    """Capacity section when no run choked: the largest feed a steady run passed near each point (lower bounds)."""
    from msmill.surrogate.capacity import demonstrated_rule

    n = env.counts()
    sizes, speeds, gates = DEMONSTRATED_AT
    head = "| rock (mm) | upper speed (rpm) | " + " | ".join(f"gate {g:g} deg" for g in gates) + " |"
    rows = [head, "|" + "---|" * (2 + len(gates))]
    for s_mm in sizes:
        for v in speeds:
            cells = [model.capacity_tph(s_mm, v, g) for g in gates]
            rows.append(f"| {s_mm:g} | {v:g} | " + " | ".join("-" if not np.isfinite(c) else f">= {c:.0f}"
                                                            for c in cells) + " |")
    top = max((p for p in env.points if p.outcome == "steady"), key=lambda p: p.feed_tph)
    return [
        f"From the shipped envelope `{env_rel}` (`scripts/build_envelope.py`, {env.provenance.get('date_utc', '')}"
        f", commit {str(env.provenance.get('git_commit', ''))[:7]}): **{n['steady']} steady runs and no choked "
        f"run**; {n['not_steady']} not-steady runs carry no capacity information and are not used."
        + (f" **{len(missing)} run documents of the export are not in the envelope: rebuild it.**" if missing else ""),
        "",
        "No DEM run of the default machine has choked: the slice passed every feed the chute's feed stream could "
        f"deliver, up to {top.feed_tph:.0f} t/h ({top.size_mm:.3g} mm rock, {top.speed_rpm:.0f} rpm, gate "
        f"{top.gate_deg:.1f} deg; `docs/mill-dem.md` 3.1), more than 40 times the design space's largest feed. "
        "So the data bound the capacity from below only, and the shipped envelope (method `demonstrated`, "
        "`msmill.surrogate.capacity`) says exactly that, under one stated assumption: the capacity at a size, speed "
        f"and gate is **at least** {demonstrated_rule()} (`docs/mill-dem.md` 3.1): continuous, never falling as "
        "the gates open.",
        "",
        *rows,
        "",
        "`msmill predict` reports the lower bound (`capacity ... >= X`) and warns, in one line, when the feed rate "
        "is above it: the feed is beyond what the DEM has shown the mill to pass there, and the capacity above it is "
        "unknown (not exceeded). `msmill sweep` and `msmill optimize` flag such points (`above_capacity`) and keep "
        "them feasible. Where only low-feed runs are near (fine rock, the small entries above), the bound lies "
        "inside the design space's 10-60 t/h, so there the tools flag feeds that no DEM run near them has passed, "
        "until a DEM run at a higher feed there lifts the bound (`msmill campaign add`). "
        "The censored capacity model and the classifier stay in `msmill.surrogate.capacity` for data with chokes "
        "(`scripts/build_envelope.py --method censored` refuses to fit without one).",
        "",
    ]


def _envelope_line(env: Any, env_rel: str, missing: list, counts: str) -> str:
    """First line of the capacity section: the envelope file, its provenance and run counts."""
    return (f"From the shipped envelope `{env_rel}` (`scripts/build_envelope.py`, {env.provenance.get('date_utc', '')}"
            f", commit {str(env.provenance.get('git_commit', ''))[:7]}): {counts}; {env.counts()['not_steady']} "
            "not-steady runs carry no capacity information and are not used."
            + (f" **{len(missing)} run documents of the export are not in the envelope: rebuild it.**"
               if missing else ""))


def capacity_section(env_path: Path | None, all_runs: list, img: Path) -> list[str]:
    """The page's capacity section (and its figure, ``img/campaign-capacity.png``) from the envelope file."""
    from msmill.surrogate.capacity import EnvelopeData, load_capacity

    if env_path is None:
        return ["No envelope ships (`scripts/build_envelope.py` builds it from the export).", ""]
    env = EnvelopeData.from_json(env_path)
    model = load_capacity(env_path)
    used = {r["content_hash"] for r in env.provenance.get("runs", [])}
    missing = [r for r in all_runs if r.content_hash not in used]
    if model.lower_bound:
        return demonstrated_section(env, model, missing, _rel(env_path))
    lo, hi = model.domain["size_mm"]
    mid = float(np.sqrt(lo * hi))
    plot_capacity(model, env.points, mid, img / "campaign-capacity.png")
    n = env.counts()
    return [_envelope_line(env, _rel(env_path), missing, f"**{n['steady']} steady and {n['choked']} choked** runs"),
            "", "![capacity](img/campaign-capacity.png)", "", _censored_model_line(model, mid), "",
            *_censored_support(model, env.points, n, run_settings_by_point(all_runs)),
            "`msmill predict` warns (one line: capacity, requested feed, by how much, probability of steady flow) "
            "when the feed rate is above the capacity at the feed's F80, speed and gate; `msmill sweep` flags such "
            "points (`above_capacity`) and `msmill optimize` excludes them (`--envelope FILE` to use another "
            "envelope, `--no-capacity-check` to switch it off).", ""]


def _censored_model_line(model: Any, mid: float) -> str:
    """The censored capacity law, its fitted coefficients (+- 1 sd) and the figure's panels."""
    c = model.params["coefficients"]
    sd = np.sqrt(np.diag(model.params["covariance"]))
    return ("Model (`msmill.surrogate.capacity`, censored): log capacity = b0 + b1 log2(size/15 mm) + b2 (speed - "
            "1550 rpm)/350 rpm + b3 (gate - 40 deg)/40 deg, with a run-to-run scatter sigma; a steady run at feed F "
            "says capacity >= F, a choked run says throughput <= capacity < F. Fitted (MAP, +- 1 posterior sd): "
            + ", ".join(f"{k} {v:.2f} +- {e:.2f}" for (k, v), e in zip(c.items(), sd, strict=True))
            + f"; sigma {model.params['sigma']:.2f} (a factor {np.exp(model.params['sigma']):.2f} either way). The "
            f"left panel is the median capacity at {mid:.3g} mm (the geometric middle of the runs' sizes); the others "
            "are the probability that the mill passes a feed, with the capacity as the solid P = 1/2 line.")


def _censored_support(model: Any, pts: list, n: dict[str, int], settings: dict) -> list[str]:
    """'What the data support': choked runs, in-sample warnings, held-out chokes, scatter, priors, classifier."""
    fs, ns, fc, nc = warn_counts(model, pts)
    return [
        "What the data support:",
        "",
        f"- **{n['choked']} choked runs** among {n['steady'] + n['choked']}. The capacity is measured only near "
        "them (narrow gates); everywhere else the steady runs give only lower bounds, so the law's slopes and the "
        "scatter come largely from those bounds and the priors. Where the median capacity is above the largest "
        f"feed any run had ({model.domain['feed_tph'][1]:.0f} t/h, hatched) it is an extrapolation of the "
        "log-linear law, not a measurement.",
        f"- In sample, the capacity lies below the feed of {fc} of {nc} choked runs and of {fs} of {ns} steady "
        "runs (those would have warned)"
        + (": `msmill predict` at the choked runs' own settings does not warn, it reports a probability of "
           "steady flow below 1 there (table)" if fc < nc else "")
        + ". Each choked run held out in turn (a fit without it, as a new run would meet the model):",
        "",
        *choked_table(model, pts, settings),
        "",
        *_older_settings_caveat(pts, settings),
        passed_share(pts),
        f"- The scatter sigma = {model.params['sigma']:.2f} is large: steady runs passed more feed than the "
        "choked ones at nearby sizes, speeds and gates, so the data do not show a sharp boundary; the probability "
        "of steady flow falls gradually through the capacity. A warning is a flag to check, not a prediction "
        "that the plant will choke.",
        "- Sensitivity of the capacity (t/h) to the priors (`msmill.surrogate.capacity.PRIORS`); columns inside the "
        "run data move less than the extrapolated wide-gate one:",
        "",
        *prior_table(pts),
        "",
        _classifier_line(pts),
        "",
    ]


def _classifier_line(pts: list) -> str:
    """What the Gaussian-process classifier fitted to the same runs says (why the envelope is censored)."""
    from msmill.surrogate.capacity import CapacityModel

    cls = CapacityModel.fit(pts, method="classifier")
    cls_p = [cls.probability_steady(p.size_mm, p.feed_tph, p.speed_rpm, p.gate_deg)[0] for p in pts
             if p.outcome == "choked"]
    cls_cap = [cls.capacity_tph(*x) for x in CAPACITY_AT]
    return ("- The Gaussian-process classifier (`CapacityModel.fit(..., method='classifier')`, zero prior mean) "
            "fitted to the same runs gives the choked runs P(steady) "
            + ", ".join(f"{p:.2f}" for p in cls_p) + " at their own feeds and "
            + ("no capacity below 120 t/h at any of the four points above" if not np.isfinite(cls_cap).any() else
               "capacities " + ", ".join("none below 120 t/h" if not np.isfinite(x) else f"{x:.0f} t/h"
                                         for x in cls_cap) + " at the four points above")
            + ": with so few choked runs it calls everything steady, which is why the shipped envelope uses the "
            "censored model.")


# ------------------------------------------------------------------ the page
@dataclass
class CampaignReport:
    """What the page is made from: the export's runs, the surrogate and the envelope, and the numbers.

    Attributes
    ----------
    campaign : CampaignRuns
        The export (:func:`msmill.pipeline.results.load_campaign`).
    provider : SurrogateProvider
        The surrogate's provider.
    surrogate_path : Path
        Its file.
    envelope_path : Path or None
        The capacity envelope's file (None: none ships).
    runs, curve : DataFrame
        :func:`~msmill.pipeline.results.run_table` and :func:`~msmill.pipeline.results.learning_curve`.
    cost_fit : (float, float) or None
        ``wall_s ~ b * size_mm ** k`` as ``(k, b)`` (:func:`msmill.plots.campaign.plot_cost`).
    at : dict
        Centre of the trained domain (mm, t/h, rpm, deg).
    """

    campaign: CampaignRuns
    provider: Any
    surrogate_path: Path
    envelope_path: Path | None
    runs: Any = None
    curve: Any = None
    cost_fit: tuple[float, float] | None = None
    at: dict[str, float] | None = None


def _header(r: CampaignReport) -> list[str]:
    """Title, provenance line and the totals."""
    from msmill.dem.mill.run import VELOCITY_FIT_PARAMETERS, RunSettings
    from msmill.provenance import git_commit

    c, runs = r.campaign, r.runs
    n_bad = len(c.all_runs) - len(c.slices) - len(c.fulls)
    target_kl = RunSettings().target_velocity_sampling_kl
    return [
        "# Training campaign: results",
        "",
        f"Generated by `{COMMAND}` on "
        f"{dt.datetime.now(dt.UTC).strftime('%Y-%m-%d %H:%M UTC')} at commit {git_commit(short=True) or 'unknown'} "
        f"from the export `{_rel(c.folder)}` ({len(c.all_runs)} run documents) and the surrogate "
        f"`{_rel(r.surrogate_path)}`. Re-run it after every batch; every number below comes from those files.",
        "",
        "## Totals",
        "",
        f"- steady periodic-slice runs (training): **{len(c.slices)}**; full-mill runs: {len(c.fulls)}; "
        f"not steady, or outside the design space (capacity probes, for the envelope only): {n_bad}",
        f"- DEM wall time of the training runs: **{runs['wall_s'].sum() / 3600:.2f} h** "
        f"(2-core machine shared with other work: wall, not CPU; a re-run counts its own wall time, not its "
        f"predecessor's)",
        f"- runs meeting the adaptive window's sampling-KL target ({target_kl:g}, "
        f"{VELOCITY_FIT_PARAMETERS / (2 * target_kl):.0f} impacts in every stage): "
        f"**{int((runs['sampling_kl'] <= target_kl + 1e-12).sum())} of {len(runs)}**",
        f"- sizes {runs['size_mm'].min():g}-{runs['size_mm'].max():g} mm, feed "
        f"{runs['feed_tph'].min():.3g}-{runs['feed_tph'].max():.3g} t/h, speed {runs['speed_rpm'].min():.4g}-"
        f"{runs['speed_rpm'].max():.4g} rpm, gate {runs['gate_deg'].min():.3g}-{runs['gate_deg'].max():.3g} deg",
        "",
        "DEM hours by rock-size band (steady training runs; fine rock costs more per run: about (size)^-3 "
        "more rocks and (size)^-1 more steps):",
        "",
        *markdown_table(hours_by_size_band(runs).round(3)),
        "",
    ]


def _learning(r: CampaignReport) -> list[str]:
    """Learning curve (unless skipped) and KL against sample size."""
    from msmill.pipeline.results import PAPER_KL
    from msmill.surrogate.accuracy import FINE_SIZE_MM
    from msmill.surrogate.targets import N_LEVELS

    curve = r.curve
    head = ["## Learning curve", "", "Not computed (`--no-learning-curve`).", ""] if curve is None else [
        "## Learning curve",
        "",
        "![learning curve](img/campaign-learning-curve.png)",
        "",
        "Closed-form leave-one-out (fixed hyperparameters, `msmill.surrogate.accuracy`) on the first *n* runs "
        f"in the order they were computed. The velocity KL cannot fall below the {N_LEVELS}-quantile representation's "
        f"own KL (dotted: {curve['representation_kl'].iloc[-1]:.4f} on these runs; the paper's figure is "
        f"{PAPER_KL}). `runs_fine` and `kl_velocity_fine`: the runs of rock finer than {FINE_SIZE_MM:g} mm "
        "among the first *n* and their own mean velocity KL, the fine region's learning curve.",
        "",
        *markdown_table(curve.round(4)),
        "",
    ]
    return [
        *head,
        "**KL against sample size.** The shipped surrogate's leave-one-out velocity KL, primary and secondary "
        "distributions together, grouped by the number of impacts behind the held-out run's own fit. A fit of "
        "*n* impacts is off the true distribution by about (free parameters)/(2n), so the stages with few "
        "impacts (coarse rock, lower stages, the old 1-1.5 s windows) set most of the mean. The runs that "
        "missed the adaptive window's sampling-KL target (500 impacts in every stage) are re-run with long "
        "windows by `scripts/rerun_undersampled.py` (same point, seed and settings; the re-run replaces the "
        "original in the export); the totals above say how many runs meet it.",
        "",
        *markdown_table(kl_by_sample_size(r.provider.surrogate)),
        "",
    ]


def _design_and_trends(r: CampaignReport) -> list[str]:
    """Design points, DEM cost, the surrogate's trends and the paper's claims."""
    fit, at = r.cost_fit, r.at
    return [
        "## Design points",
        "",
        "![design points](img/campaign-design.png)",
        "",
        "## DEM cost per run",
        "",
        "![cost](img/campaign-cost.png)",
        "",
        (f"Power-law fit over the runs: wall time ~ size^{fit[0]:.2f} (the issue's planning figure: about "
         "size^-4)." if fit else "Too few runs with wall times for a fit."),
        "",
        "## Trends (surrogate) and the paper's claims",
        "",
        "![trends](img/campaign-trends.png)",
        "",
        "Each row varies one input over the trained range, the others at the centre of the trained domain "
        "(" + ", ".join(f"{k} {v:.4g}" for k, v in at.items()) + "). The claims are checked against the DEM "
        "runs directly (rank correlations across runs: the other inputs vary too) and against the surrogate's "
        "change across the trained range with its posterior spread (32 samples). Nothing was tuned.",
        "",
        *claims(r.provider, r.runs, at),
        "",
    ]


def _slice_to_full(r: CampaignReport) -> list[str]:
    """The slice-to-full-mill correction: paired runs and the shipped surrogate's factors."""
    m = r.provider.surrogate
    bias = getattr(m, "slice_to_full_", None)
    out = ["## Slice-to-full-mill correction", "", *pair_table(r.campaign.slices, r.campaign.fulls)]
    if bias is not None and bias.n_pairs:
        return [*out, f"{bias.n_pairs} paired runs ({', '.join(bias.pairs)}). Full/slice factor on the secondary "
                      "impacts per primary impact, per stage (exp of the log offset, +- 1 sd):", "",
                      "| stage | lambda factor | sd |", "|---|---|---|",
                      *(f"| {d['stage']} | {d['lambda_factor']:.3f} | {d['lambda_factor_sd']:.3f} |"
                        for d in bias.lambda_factors(m.training_.layout)), ""]
    return [*out, "The export holds no full-mill run paired with a slice run, so the shipped surrogate predicts "
                  "the slice (no correction). The one documented pair (10 mm, `docs/mill-dem.md`, 'Full-mill run') "
                  "had 19-36 % more secondary impacts per primary impact in the full mill and streams within "
                  "0.02.", ""]


def render(r: CampaignReport, img: Path) -> str:
    """The Markdown page of a computed :class:`CampaignReport` (writes the capacity figure into ``img``)."""
    lines = [*_header(r), *_learning(r), *_design_and_trends(r),
             "## Operating point: product P80 of `examples/ug2.toml`", "", *p80_table(r.provider), "",
             "## Rotation sense: the UG2 prediction per sense", "", *sense_table(), "",
             *_slice_to_full(r),
             "## Capacity (operating envelope)", "", *capacity_section(r.envelope_path, r.campaign.all_runs, img)]
    return "\n".join(lines) + "\n"


def _inputs(export: Path | None, surrogate: Path | None, envelope: Path | None) -> CampaignReport:
    """Read and check the export, the surrogate and the envelope (one-line errors naming the option)."""
    from msmill.model.providers import default_surrogate_path
    from msmill.surrogate.capacity import default_envelope_path
    from msmill.surrogate.provider import SurrogateProvider

    campaign = load_campaign(export, field="--export")
    spath = surrogate if surrogate is not None else default_surrogate_path()
    if spath is None:
        raise MsmillInputError("--surrogate", "none", "a surrogate file (none ships: run "
                               "scripts/build_default_surrogate.py first)")
    if not Path(spath).is_file():
        raise MsmillInputError("--surrogate", str(spath), "an existing surrogate JSON file")
    if envelope is not None and not Path(envelope).is_file():
        raise MsmillInputError("--envelope", str(envelope), "an existing envelope JSON file")
    return CampaignReport(campaign, SurrogateProvider.from_file(spath), Path(spath),
                          envelope if envelope is not None else default_envelope_path())


def write_campaign_report(export: Path | None = None, surrogate: Path | None = None, envelope: Path | None = None,
                          out: Path | None = None, echo: Callable[[str], None] = print,
                          with_learning_curve: bool = True) -> CampaignReport:
    """Write the results page and its figures (``<out folder>/img/campaign-*.png``).

    Parameters
    ----------
    export : path, optional
        Campaign export folder (default: the packaged ``msmill/data/campaigns/default``).
    surrogate : path, optional
        Surrogate JSON (default: the shipped one).
    envelope : path, optional
        Capacity envelope JSON (default: the shipped one; none: the page says so).
    out : path, optional
        The Markdown file (default: ``docs/campaign-results.md`` of the checkout).
    echo : callable
        Receives the closing lines (file written; runs, LOO mean velocity KL, DEM hours).
    with_learning_curve : bool
        Compute the learning curve (a surrogate fitted on each of 10 training-set sizes: minutes; the
        rest of the page takes seconds). False: the page says it was not computed.

    Returns
    -------
    CampaignReport
        What the page was made from.

    Raises
    ------
    MsmillInputError
        A missing export folder or one with fewer than 4 steady slice runs, a missing surrogate or envelope file.
    """
    from msmill.cli.output import atomic_write_bytes, check_writable

    r = _inputs(export, surrogate, envelope)
    out = Path(out) if out is not None else checkout_root() / "docs/campaign-results.md"
    if out.is_dir():
        raise MsmillInputError("--out", str(out), "a Markdown file path (this is a folder)")
    img = check_writable(out.parent / "img", "--out")
    img.mkdir(parents=True, exist_ok=True)
    r.runs = run_table(r.campaign.slices)
    if with_learning_curve:
        r.curve = learning_curve(r.campaign.slices, list(r.runs["file"]))
        plot_learning(r.curve, img / "campaign-learning-curve.png")
    plot_design(r.runs, img / "campaign-design.png")
    r.cost_fit = plot_cost(r.runs, img / "campaign-cost.png")
    r.at = domain_centre(r.provider.surrogate)
    plot_trends(r.provider, r.at, img / "campaign-trends.png")
    atomic_write_bytes(out, render(r, img).encode("utf-8"), "--out")
    echo(f"wrote {out} and its figures in {img}")
    last = None if r.curve is None else r.curve.iloc[-1]
    kl = "" if last is None else (f" loo_kl_velocity_mean={last['kl_velocity']:.4f} runs_fine={int(last['runs_fine'])}"
                                  f" loo_kl_velocity_mean_fine={last['kl_velocity_fine']:.4f}")
    echo(f"runs={len(r.runs)}{kl} dem_hours={r.runs['wall_s'].sum() / 3600:.2f}")
    return r
