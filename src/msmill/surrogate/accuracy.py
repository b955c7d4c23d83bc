"""Accuracy of the surrogate as the paper measures it: leave-one-out KL divergences.

For every run ``i``: predict its design point from the other runs, rebuild
the predicted distributions and compare them with the distributions fitted to
run ``i``'s own DEM data:

* velocities: ``D_KL(DEM fit || predicted mixture)`` per stage, for primary
  and secondary impacts, by quadrature on a fine grid;
* counts: ``D_KL(DEM || predicted)`` of the secondary count per primary
  impact: Poisson closed form ``l1 ln(l1/l2) - l1 + l2``, or the pmf sum when
  the runs carry count distributions;
* streams: mean absolute error of ``kickback, refeed, pass_through``
  (fractions); hit probability: absolute error.

Two ways to leave one out: ``refit=False`` (default) uses the closed form
with the fitted hyperparameters (Rasmussen & Williams 2006, eq. 5.12; slightly
optimistic because the hyperparameters saw the held-out run); ``refit=True``
refits every GP without the run (warm-started), the honest figure.

``representation_kl_*`` columns are the floor set by the quantile
representation itself: the KL between a run's fitted mixture and the mixture
rebuilt from its own quantiles.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd
from scipy import stats

from msmill.surrogate.stage_model import StageSurrogate
from msmill.surrogate.targets import (
    StagePrediction,
    count_from_summary,
    decode_stage,
    encode_run,
    normal_pdf,
)

GRID_POINTS = 4001


#: rock finer than this (mm) is the fine region, scored apart (``LooReport.summary(below_size_mm=...)``):
#: the first campaign stopped there, and the surrogate is least accurate at its fine end
FINE_SIZE_MM = 6.4


def mixture_kl(p: tuple, q: tuple, n_grid: int = GRID_POINTS) -> float:
    """``D_KL(p || q)`` (nats) of two 1-D Gaussian mixtures ``(weights, means, sigmas)``, by quadrature."""
    wp, mp, sp = (np.asarray(a, dtype=float) for a in p)
    wq, mq, sq = (np.asarray(a, dtype=float) for a in q)
    lo = min(np.min(mp - 8 * sp), np.min(mq - 8 * sq))
    hi = max(np.max(mp + 8 * sp), np.max(mq + 8 * sq))
    v = np.linspace(lo, hi, n_grid)
    fp = np.sum(wp * normal_pdf((v[:, None] - mp) / sp) / sp, axis=1)
    fq = np.sum(wq * normal_pdf((v[:, None] - mq) / sq) / sq, axis=1)
    m = fp > 1e-300
    integrand = np.where(m, fp * np.log(np.where(m, fp, 1.0) / np.maximum(fq, 1e-300)), 0.0)
    return float(max(np.trapezoid(integrand, v), 0.0))


def poisson_kl(lam_p: float, lam_q: float) -> float:
    """``D_KL(Poisson(lam_p) || Poisson(lam_q))`` (nats), closed form."""
    lam_p, lam_q = max(float(lam_p), 1e-12), max(float(lam_q), 1e-12)
    return lam_p * np.log(lam_p / lam_q) - lam_p + lam_q


def count_kl(weights_p, means_p, weights_q, means_q, k_max: int = 200) -> float:
    """``D_KL(p || q)`` of two Poisson mixtures by a pmf sum over ``0..k_max``."""
    k = np.arange(k_max + 1)[:, None]
    fp = np.sum(np.asarray(weights_p) * stats.poisson.pmf(k, np.asarray(means_p)), axis=1)
    fq = np.sum(np.asarray(weights_q) * stats.poisson.pmf(k, np.asarray(means_q)), axis=1)
    m = fp > 0
    return float(np.sum(fp[m] * np.log(fp[m] / np.maximum(fq[m], 1e-300))))


@dataclass(frozen=True)
class LooReport:
    """Leave-one-out figures.

    Attributes
    ----------
    per_point : pandas.DataFrame
        One row per (run, stage): ``run_id, stage, size_mm, feed_tph, speed_rpm,
        gate_deg, kl_primary_velocity, kl_secondary_velocity, kl_count,
        stream_abs_error, hit_abs_error, representation_kl_primary,
        representation_kl_secondary``.
    per_stage : pandas.DataFrame
        Means of ``per_point`` over runs, per stage.
    pairs : pandas.DataFrame
        Predicted against DEM values, long format: ``run_id, stage, quantity,
        dem, predicted`` (quantities ``kickback, refeed, pass_through,
        hit_probability, primary_velocity_mean_m_s, secondary_velocity_mean_m_s,
        secondary_lambda``).
    method : str
        ``"closed-form LOO"`` or ``"refit LOO"``.
    """

    per_point: pd.DataFrame
    per_stage: pd.DataFrame
    pairs: pd.DataFrame
    method: str

    def summary(self, below_size_mm: float | None = None) -> dict[str, float]:
        """Headline means over all runs and stages, or over the runs of rock finer than ``below_size_mm`` (mm).

        With no run below ``below_size_mm`` the means are NaN and ``n_runs`` is 0.
        """
        d = self.per_point
        if below_size_mm is not None:
            d = d[d["size_mm"] < below_size_mm]
        if d.empty:
            return {"n_runs": 0} | dict.fromkeys(("mean_kl_velocity", "mean_kl_count", "mean_kl", "stream_mae",
                                                  "hit_probability_mae", "representation_kl"), float("nan"))
        kl_v = float(np.mean(np.r_[d["kl_primary_velocity"], d["kl_secondary_velocity"]]))
        return {"n_runs": int(d["run_id"].nunique()), "mean_kl_velocity": kl_v,
                "mean_kl_count": float(d["kl_count"].mean()),
                "mean_kl": float(np.mean(np.r_[d["kl_primary_velocity"], d["kl_secondary_velocity"],
                                              d["kl_count"]])),
                "stream_mae": float(d["stream_abs_error"].mean()),
                "hit_probability_mae": float(d["hit_abs_error"].mean()),
                "representation_kl": float(np.mean(np.r_[d["representation_kl_primary"],
                                                         d["representation_kl_secondary"]]))}


def _mixture(g) -> tuple:
    return np.asarray(g.weights), np.asarray(g.means_m_s), np.asarray(g.sigmas_m_s)


def _loo_rows(model: StageSurrogate, refit: bool) -> np.ndarray:
    ts = model.training_
    if not refit:
        return model.gp_.loo()[0]
    out = np.empty_like(ts.Y)
    hyper = model.gp_.hyperparameters()
    for i in range(ts.n_runs):
        keep = [r for j, r in enumerate(ts.runs) if j != i]
        sub = StageSurrogate(model.design_space, n_restarts=0, n_levels=ts.layout.n_levels).fit(keep, warm_start=hyper)
        out[i] = sub.gp_.predict(ts.X[i:i + 1])[0]
    return out


def _count_kl(st, pred: StagePrediction, i: int = 0) -> float:
    cd = getattr(st, "secondary_count", None)
    if cd is None or pred.count_var_ratio is None:
        return poisson_kl(st.secondary_lambda, pred.secondary_lambda[i])
    wq, mq = count_from_summary(pred.secondary_lambda[i], pred.count_var_ratio[i], pred.count_p_zero[i])
    return count_kl(cd.weights, cd.means, wq, mq)


def loo_scores(model: StageSurrogate, refit: bool = False) -> LooReport:
    """Leave-one-out accuracy of a fitted surrogate over its own training runs."""
    ts = model.training_
    if not ts.runs:
        raise ValueError("the surrogate carries no training runs to score")
    Yloo = _loo_rows(model, refit)
    rows, pairs = [], []
    for i, run in enumerate(ts.runs):
        own = encode_run(run, ts.layout)[0][None, :]
        for st in run.stages:
            pred = decode_stage(Yloo[i:i + 1], ts.layout, st.stage)
            back = decode_stage(own, ts.layout, st.stage)
            d = run.design
            pv = tuple(a[0] for a in pred.primary_velocity)
            sv = tuple(a[0] for a in pred.secondary_velocity)
            rows.append({
                "run_id": ts.run_ids[i], "stage": st.stage, "size_mm": d.size_mm, "feed_tph": d.feed_tph,
                "speed_rpm": d.speed_rpm, "gate_deg": d.gate_deg,
                "kl_primary_velocity": mixture_kl(_mixture(st.primary_velocity), pv),
                "kl_secondary_velocity": mixture_kl(_mixture(st.secondary_velocity), sv),
                "kl_count": _count_kl(st, pred),
                "stream_abs_error": float(np.mean(np.abs(pred.streams[0] - st.streams))),
                "hit_abs_error": float(abs(pred.hit_probability[0] - st.primary_hit_probability)),
                "representation_kl_primary": mixture_kl(_mixture(st.primary_velocity),
                                                        tuple(a[0] for a in back.primary_velocity)),
                "representation_kl_secondary": mixture_kl(_mixture(st.secondary_velocity),
                                                          tuple(a[0] for a in back.secondary_velocity)),
            })
            vals = {
                "kickback": (st.kickback, pred.streams[0, 0]), "refeed": (st.refeed, pred.streams[0, 1]),
                "pass_through": (st.pass_through, pred.streams[0, 2]),
                "hit_probability": (st.primary_hit_probability, pred.hit_probability[0]),
                "primary_velocity_mean_m_s": (st.primary_velocity.mean(), float(np.dot(pv[0], pv[1]))),
                "secondary_velocity_mean_m_s": (st.secondary_velocity.mean(), float(np.dot(sv[0], sv[1]))),
                "secondary_lambda": (st.secondary_lambda, pred.secondary_lambda[0]),
            }
            pairs += [{"run_id": ts.run_ids[i], "stage": st.stage, "quantity": k, "dem": float(a),
                       "predicted": float(b)} for k, (a, b) in vals.items()]
    per_point = pd.DataFrame(rows)
    metric_cols = [c for c in per_point.columns if c.startswith(("kl_", "stream_", "hit_", "representation_"))]
    per_stage = per_point.groupby("stage")[metric_cols].mean().reset_index()
    return LooReport(per_point, per_stage, pd.DataFrame(pairs), "refit LOO" if refit else "closed-form LOO")


#: target groups behind each kind of coverage (``count``: its first target, the mean)
COVERAGE_KINDS = {"streams": ("streams",), "hit": ("hit",), "count": ("count",),
                  "velocity": ("primary_velocity", "secondary_velocity")}


def loo_coverage(model: StageSurrogate, level: float = 0.9) -> dict[str, float]:
    """Share of held-out targets inside the closed-form leave-one-out predictive interval of ``level``.

    The interval is the LOO mean +- the normal quantile times the LOO sd, which includes the held-out
    run's own sampling noise and the fitted white noise (:meth:`SurrogateGP.loo`): what a new DEM run at
    the point should fall in. Per kind of target (:data:`COVERAGE_KINDS`, in the surrogate's target
    space: logits of the streams and hit probability, log mean count, velocity quantiles), over every
    run and stage. An honest band covers about ``level``.
    """
    ts = model.training_
    mean, var = model.gp_.loo()
    z = np.abs(ts.Y - mean) / np.sqrt(var)
    q = float(stats.norm.ppf(0.5 + 0.5 * level))
    names = ts.layout.names
    out = {}
    for kind, groups in COVERAGE_KINDS.items():
        cols = [j for j, n in enumerate(names) if n.startswith("s") and n.split(".")[1] in groups
                and (kind != "count" or n.endswith(".0"))]
        out[kind] = float(np.mean(z[:, cols] <= q)) if cols else float("nan")
    return out

