"""What the training campaign has shown: tables and figures' numbers from the export and the surrogate.

The analysis behind ``msmill campaign report`` (``docs/campaign-results.md``), without text or plots:

* :func:`load_campaign`: the export's runs, split into training slices and full-mill runs;
* :func:`run_table`: one row per steady slice run (inputs, wall time, streams, hit probability);
* :func:`learning_curve`: closed-form leave-one-out KL against the number of runs;
* :func:`kl_by_sample_size`: the shipped surrogate's LOO velocity KL by impacts behind each fit;
* :func:`sweep`, :func:`range_change`: the surrogate's quantities along one input, with posterior spread;
* :func:`spearman`: rank correlations across DEM runs (the paper's qualitative claims);
* capacity: :func:`run_settings_by_point`, :func:`warn_counts`, :func:`choked_loo`,
  :func:`prior_sensitivity`, :func:`passed_shares`.

Inputs are ``msmill.pipeline.export.ExportedRun`` lists, a fitted
``msmill.surrogate.StageSurrogate`` or its ``SurrogateProvider``, and the
capacity envelope's points (``msmill.surrogate.capacity``).
"""

from __future__ import annotations

import itertools
import json
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from msmill.errors import MsmillInputError
from msmill.stageparams import DESIGN_INPUTS, RunStatistics

__all__ = [
    "CAPACITY_AT",
    "IMPACT_BINS",
    "MIN_SLICE_RUNS",
    "PAPER_KL",
    "PAPER_RUNS",
    "PRIOR_VARIANTS",
    "QUANTITIES",
    "SIZE_BANDS_MM",
    "CampaignRuns",
    "ChokedRun",
    "choked_loo",
    "domain_centre",
    "hours_by_size_band",
    "kl_by_sample_size",
    "learning_curve",
    "load_campaign",
    "passed_shares",
    "point_key",
    "prior_sensitivity",
    "range_change",
    "rocks_per_s",
    "run_settings_by_point",
    "run_table",
    "sampling_kl",
    "spearman",
    "stage_quantities",
    "sweep",
    "warn_counts",
]

#: the paper's learning-curve figure: mean KL 0.012 after 177 DEM runs
PAPER_RUNS, PAPER_KL = 177, 0.012
#: the four stage quantities the trends and claims use
QUANTITIES = ("kickback", "refeed", "pass_through", "hit_probability")
#: bins of the number of impacts behind a held-out fit (KL against sample size)
IMPACT_BINS = (0, 100, 200, 300, 500, 1000, 2000, np.inf)
#: fewest steady slice runs a results page is made from
MIN_SLICE_RUNS = 4
#: points at which the capacity is tabulated (size mm, speed rpm, gate deg)
CAPACITY_AT = ((14.0, 1500.0, 5.0), (20.0, 1500.0, 10.0), (20.0, 1900.0, 10.0), (28.0, 1500.0, 40.0))
#: prior variants of the capacity's sensitivity table (entries of msmill.surrogate.capacity.PRIORS)
PRIOR_VARIANTS = (("shipped priors", {}), ("slopes sd 0.5", {"slope_sd": 0.5}), ("slopes sd 2", {"slope_sd": 2.0}),
                  ("sigma prior 0.1", {"log_sigma_mean": float(np.log(0.1))}),
                  ("sigma prior 0.4", {"log_sigma_mean": float(np.log(0.4))}))


@dataclass(frozen=True)
class CampaignRuns:
    """An export's run documents: all of them, the training slices and the steady full-mill runs.

    Attributes
    ----------
    folder : Path
        The export folder.
    all_runs, slices, fulls : list of ExportedRun
        Every run document; the steady slice runs in the design space; the steady full-mill runs
        (:func:`msmill.pipeline.export.split_runs`).
    """

    folder: Path
    all_runs: list
    slices: list
    fulls: list


def load_campaign(folder: str | Path | None = None, field: str = "--export") -> CampaignRuns:
    """Read a campaign export (default: the packaged one) with at least :data:`MIN_SLICE_RUNS` training runs.

    Raises
    ------
    MsmillInputError
        ``field`` names a folder that does not exist, or one with too few steady slice runs.
    """
    from msmill.pipeline.export import default_export_dir, read_export, split_runs

    f = Path(folder) if folder is not None else default_export_dir()
    if not f.is_dir():
        raise MsmillInputError(field, str(f), "an existing campaign export folder (run-*.json documents)")
    all_runs = read_export(f)
    slices, fulls = split_runs(all_runs)
    if len(slices) < MIN_SLICE_RUNS:
        raise MsmillInputError(field, str(f), f"an export with at least {MIN_SLICE_RUNS} steady slice runs in the "
                               f"design space (this one has {len(slices)} of {len(all_runs)} run documents)")
    return CampaignRuns(f, all_runs, slices, fulls)


def sampling_kl(st: RunStatistics) -> float:
    """Expected sampling KL (nats) ``p / (2 n)`` of a run's velocity fits at its fewest impacts in any stage/kind."""
    from msmill.dem.mill.run import VELOCITY_FIT_PARAMETERS

    n = min(min(s.n_primary_impacts, s.n_secondary_impacts) for s in st.stages)
    return VELOCITY_FIT_PARAMETERS / (2 * max(n, 1))


def run_table(slices: list) -> pd.DataFrame:
    """One row per steady slice run, in the order they were computed (date, then file name).

    Columns: ``file``, the :data:`~msmill.stageparams.DESIGN_INPUTS` (mm, t/h, rpm, deg), ``wall_s``
    (DEM wall time, s), ``date`` (UTC), ``sampling_kl`` (nats) and per stage ``s<i>.kickback``,
    ``s<i>.refeed``, ``s<i>.pass_through``, ``s<i>.hit_probability`` (fractions).
    """
    rows = []
    for r in slices:
        st = r.statistics
        row = {"file": r.path.name, **dict(zip(DESIGN_INPUTS, st.design.inputs(), strict=True)), "wall_s": r.wall_s,
               "date": str(st.provenance.get("date_utc", "")), "sampling_kl": sampling_kl(st)}
        for s in st.stages:
            row |= {f"s{s.stage}.kickback": s.kickback, f"s{s.stage}.refeed": s.refeed,
                    f"s{s.stage}.pass_through": s.pass_through, f"s{s.stage}.hit_probability":
                    s.primary_hit_probability}
        rows.append(row)
    return pd.DataFrame(rows).sort_values(["date", "file"]).reset_index(drop=True)


#: rock-size bands (mm) of the campaign's cost log: the fine bands the second campaign fills, then the first's
SIZE_BANDS_MM = (2.0, 4.0, 6.4, 10.0, 20.0, 30.0)


def hours_by_size_band(runs: pd.DataFrame, bands_mm: tuple[float, ...] = SIZE_BANDS_MM) -> pd.DataFrame:
    """Steady runs and DEM wall hours per rock-size band of a :func:`run_table`.

    Rows: one per band ``[lo, hi)`` (the last closed), below the first edge as ``< lo``; columns ``band``,
    ``runs``, ``dem_hours``, ``median_hours_per_run`` (NaN for an empty band).
    """
    edges = np.asarray(bands_mm, dtype=float)
    size = runs["size_mm"].to_numpy()
    hours = runs["wall_s"].fillna(0.0).to_numpy() / 3600.0
    idx = np.searchsorted(edges, size, side="right")  # 0: below the first edge
    idx[size == edges[-1]] = len(edges) - 1
    names = [f"< {edges[0]:g}"] + [f"{a:g}-{b:g}" for a, b in itertools.pairwise(edges)]
    rows = []
    for k, name in enumerate(names):
        h = hours[idx == k]
        rows.append({"band": f"{name} mm", "runs": int(h.size), "dem_hours": float(h.sum()),
                     "median_hours_per_run": float(np.median(h)) if h.size else float("nan")})
    return pd.DataFrame(rows)


def learning_curve(slices: list, order: list[str], n_points: int = 10) -> pd.DataFrame:
    """Closed-form LOO means of a surrogate fitted on the first ``n`` runs, for up to ``n_points`` values of n.

    Parameters
    ----------
    slices : list of ExportedRun
        The training runs.
    order : list of str
        Their file names in computation order (``run_table(slices)["file"]``).
    n_points : int
        Values of n, spread evenly from 4 to all runs (n < 3 skipped).

    Returns
    -------
    DataFrame
        ``runs``, ``kl_velocity``, ``kl_count``, ``representation_kl`` (mean KL, nats), ``stream_mae``,
        ``hit_mae`` (mean absolute errors of fractions), ``runs_fine`` and ``kl_velocity_fine`` (the runs
        of rock finer than :data:`msmill.surrogate.accuracy.FINE_SIZE_MM` among the first n, their mean
        velocity KL; NaN while there are none).
    """
    from msmill.surrogate.accuracy import FINE_SIZE_MM, loo_scores
    from msmill.surrogate.stage_model import StageSurrogate

    by_file = {r.path.name: r.statistics for r in slices}
    runs = [by_file[f] for f in order]
    ns = sorted(set(np.linspace(min(4, len(runs)), len(runs), n_points).round().astype(int)))
    out = []
    for n in ns:
        if n < 3:
            continue
        rep = loo_scores(StageSurrogate(n_restarts=0).fit(runs[:n]))
        s, fine = rep.summary(), rep.summary(below_size_mm=FINE_SIZE_MM)
        out.append({"runs": n, "kl_velocity": s["mean_kl_velocity"], "kl_count": s["mean_kl_count"],
                    "stream_mae": s["stream_mae"], "hit_mae": s["hit_probability_mae"],
                    "representation_kl": s["representation_kl"], "runs_fine": fine["n_runs"],
                    "kl_velocity_fine": fine["mean_kl_velocity"]})
    return pd.DataFrame(out)


def kl_by_sample_size(model: Any) -> pd.DataFrame:
    """Closed-form LOO velocity KL (nats) of a fitted surrogate by the number of impacts behind each held-out fit.

    A held-out DEM fit of ``n`` impacts is itself off the true distribution by
    about (free parameters) / (2 n) nats, a floor no surrogate can beat. Rows:
    :data:`IMPACT_BINS`, primary and secondary distributions together; columns
    ``distributions``, ``kl_velocity``, ``representation_kl``, ``share_of_total_kl``.
    """
    from msmill.surrogate.accuracy import loo_scores

    ts = model.training_
    runs = dict(zip(ts.run_ids, ts.runs, strict=True))
    rows = []
    for p in loo_scores(model).per_point.itertuples(index=False):
        st = runs[p.run_id].stages[int(p.stage) - 1]
        rows += [("primary", st.n_primary_impacts, p.kl_primary_velocity, p.representation_kl_primary),
                 ("secondary", st.n_secondary_impacts, p.kl_secondary_velocity, p.representation_kl_secondary)]
    d = pd.DataFrame(rows, columns=["impacts", "n", "kl", "representation_kl"])
    d["impacts per stage"] = pd.cut(d["n"], IMPACT_BINS, right=False)
    out = d.groupby("impacts per stage", observed=True).agg(
        distributions=("kl", "size"), kl_velocity=("kl", "mean"),
        representation_kl=("representation_kl", "mean"), share_of_total_kl=("kl", "sum")).reset_index()
    out["share_of_total_kl"] /= d["kl"].sum()
    out["impacts per stage"] = out["impacts per stage"].astype(str)
    return out.round(4)


def spearman(x: pd.Series, y: pd.Series) -> tuple[float, float]:
    """Spearman rank correlation and its two-sided p-value (nan, nan for fewer than 3 distinct x)."""
    from scipy.stats import spearmanr

    if x.nunique() < 3:
        return float("nan"), float("nan")
    r = spearmanr(x, y)
    return float(r.statistic), float(r.pvalue)


def domain_centre(model: Any) -> dict[str, float]:
    """Centre of a fitted surrogate's trained domain (geometric in size): mm, t/h, rpm, deg by input name."""
    d = model.domain_
    return {"size_mm": float(np.sqrt(d[0][0] * d[0][1])), "feed_tph": float(np.mean(d[1])),
            "speed_rpm": float(np.mean(d[2])), "gate_deg": float(np.mean(d[3]))}


def stage_quantities(p: Any) -> dict[str, np.ndarray]:
    """The :data:`QUANTITIES` of ``StageParameters`` as ``(stages, sizes)`` arrays (fractions)."""
    return {"kickback": p.streams[..., 0], "refeed": p.streams[..., 1], "pass_through": p.streams[..., 2],
            "hit_probability": p.hit_probability}


def _at_point(provider: Any, point: dict[str, float], n: int) -> Any:
    """Quantities at one design point: the posterior mean, or ``n`` posterior samples (seed 1)."""
    sizes = np.array([point["size_mm"]])
    args = (sizes, list(point["speed_rpm"] * provider.surrogate.speed_factors), point["feed_tph"], point["gate_deg"])
    if n:
        return [stage_quantities(p) for p in provider.sample_stage_parameters(sizes, n, *args[1:], seed=1)]
    return stage_quantities(provider.stage_parameters(*args))


def sweep(provider: Any, var: str, values: np.ndarray, at: dict[str, float],
          n_samples: int = 0) -> tuple[dict[str, np.ndarray], list[dict[str, np.ndarray]] | None]:
    """The surrogate's quantities along one input, the others at ``at`` (out-of-domain warnings silenced).

    Parameters
    ----------
    provider : SurrogateProvider
        The surrogate's provider (``msmill.surrogate.provider``).
    var : str
        One of :data:`~msmill.stageparams.DESIGN_INPUTS`.
    values : array
        Values of ``var`` (its unit: mm, t/h, rpm or deg).
    at : dict
        The other inputs (:func:`domain_centre`).
    n_samples : int
        Posterior samples to draw as well (0: none).

    Returns
    -------
    mean : dict of str to array
        ``(stages, len(values))`` posterior means of each of :data:`QUANTITIES`.
    samples : list of dict, or None
        ``n_samples`` dicts like ``mean``, one per posterior sample.
    """
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        if var == "size_mm":
            sizes = np.asarray(values, dtype=float)
            args = (list(at["speed_rpm"] * provider.surrogate.speed_factors), at["feed_tph"], at["gate_deg"])
            mean = stage_quantities(provider.stage_parameters(sizes, *args))
            samp = ([stage_quantities(p) for p in provider.sample_stage_parameters(sizes, n_samples, *args, seed=1)]
                    if n_samples else None)
            return mean, samp
        pts = [_at_point(provider, at | {var: float(v)}, 0) for v in values]
        mean = {q: np.concatenate([p[q] for p in pts], axis=1) for q in QUANTITIES}
        samp = None
        if n_samples:
            per = [_at_point(provider, at | {var: float(v)}, n_samples) for v in values]
            samp = [{q: np.concatenate([per[j][i][q] for j in range(len(values))], axis=1) for q in QUANTITIES}
                    for i in range(n_samples)]
    return mean, samp


def range_change(provider: Any, var: str, at: dict[str, float], q: str,
                 n: int = 32) -> tuple[np.ndarray, np.ndarray]:
    """Per stage: change of quantity ``q`` from the low to the high end of ``var``'s trained range, and its sd.

    The sd is over ``n`` posterior samples; the other inputs are at ``at``.
    """
    i = DESIGN_INPUTS.index(var)
    ends = np.array(provider.surrogate.domain_[i], dtype=float)
    mean, samp = sweep(provider, var, ends, at, n_samples=n)
    delta = mean[q][:, 1] - mean[q][:, 0]
    sd = np.std([s[q][:, 1] - s[q][:, 0] for s in samp], axis=0)
    return delta, sd


# ------------------------------------------------------------------ capacity (operating envelope)
def point_key(size_mm: float, feed_tph: float, speed_rpm: float, gate_deg: float) -> tuple[float, ...]:
    """A design point as a dictionary key (inputs rounded to 4 decimals)."""
    return tuple(round(float(v), 4) for v in (size_mm, feed_tph, speed_rpm, gate_deg))


def run_settings_by_point(all_runs: list) -> dict[tuple[float, ...], dict]:
    """The run settings each exported run was made with, by its :func:`point_key` (``{}`` when not recorded)."""
    out = {}
    for r in all_runs:
        doc = json.loads(r.path.read_text(encoding="utf-8"))
        out[point_key(*r.statistics.design.inputs())] = (doc.get("run") or {}).get("run_settings") or {}
    return out


def warn_counts(model: Any, pts: list) -> tuple[int, int, int, int]:
    """In sample: (steady runs fed above the capacity, steady runs, choked runs fed above it, choked runs)."""
    st = [p for p in pts if p.outcome == "steady"]
    ch = [p for p in pts if p.outcome == "choked"]

    def above(p: Any) -> bool:
        return p.feed_tph > model.capacity_tph(p.size_mm, p.speed_rpm, p.gate_deg)

    return sum(map(above, st)), len(st), sum(map(above, ch)), len(ch)


@dataclass(frozen=True)
class ChokedRun:
    """One choked run against the capacity model, fitted with and without it.

    Attributes
    ----------
    point : EnvelopePoint
        The run.
    capacity_tph, probability_steady : float
        Capacity (t/h) at its size, speed and gate, and P(steady) at its feed, from the model of all runs.
    loo_capacity_tph, loo_probability_steady : float or None
        The same from a fit without this run; None when no other run choked.
    """

    point: Any
    capacity_tph: float
    probability_steady: float
    loo_capacity_tph: float | None
    loo_probability_steady: float | None


def choked_loo(model: Any, pts: list) -> list[ChokedRun]:
    """Each choked run of ``pts`` held out in turn (a censored fit without it, the model's priors)."""
    from msmill.surrogate.capacity import CapacityModel

    out = []
    for p in (p for p in pts if p.outcome == "choked"):
        rest = [q for q in pts if q is not p]
        loo = CapacityModel.fit(rest, priors=model.params.get("priors")) if any(
            q.outcome == "choked" for q in rest) else None
        at = (p.size_mm, p.speed_rpm, p.gate_deg)
        prob = (p.size_mm, p.feed_tph, p.speed_rpm, p.gate_deg)
        out.append(ChokedRun(p, model.capacity_tph(*at), model.probability_steady(*prob)[0],
                             loo.capacity_tph(*at) if loo else None,
                             loo.probability_steady(*prob)[0] if loo else None))
    return out


def prior_sensitivity(pts: list, variants: tuple = PRIOR_VARIANTS,
                      at: tuple = CAPACITY_AT) -> list[tuple[str, float, list[float]]]:
    """Per prior variant: its name, the fitted sigma and the capacity (t/h) at each of ``at`` (size, speed, gate)."""
    from msmill.surrogate.capacity import CapacityModel

    out = []
    for name, pr in variants:
        m = CapacityModel.fit(pts, priors=pr)
        out.append((name, m.params["sigma"], [m.capacity_tph(*x) for x in at]))
    return out


def passed_shares(pts: list) -> tuple[np.ndarray, list[float]]:
    """Product rate passed in the measurement window over the feed: steady runs (array) and choked runs (list)."""
    st = np.array([p.throughput_tph / p.feed_tph for p in pts if p.outcome == "steady" and p.throughput_tph])
    ch = [p.throughput_tph / p.feed_tph for p in pts if p.outcome == "choked" and p.throughput_tph]
    return st, ch


def rocks_per_s(size_mm: float = 30.0, feed_tph: float = 10.0, slice_share: float = 1 / 3,
                density_kg_m3: float = 2700.0) -> float:
    """Rocks per second fed to a slice taking ``slice_share`` of the feed (spheres of ``size_mm``, kg/m^3)."""
    return feed_tph / 3.6 * slice_share / (density_kg_m3 * np.pi / 6 * (size_mm / 1000) ** 3)
