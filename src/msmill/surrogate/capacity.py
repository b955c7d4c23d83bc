"""Capacity of the mill as a predicted quantity: the largest feed rate it passes without choking.

Data are DEM runs with an outcome (:mod:`msmill.steadystate`): a **steady**
run at ``(size, feed, speeds, gate)`` passed its feed; a **choked** run did not
and passed only its measured product rate ``throughput_tph``. Not-steady runs
(the time limit was hit while still filling) carry no capacity information and
are left out.

Two models, both giving the probability that the mill is steady at a point and
the capacity where that probability is one half:

``"censored"`` (default): the capacity ``c`` itself is the modelled quantity,
    ``log c = b0 + b1 log2(size/15 mm) + b2 (speed - 1550 rpm)/350 rpm
    + b3 (gate - 40 deg)/40 deg + e``, ``e ~ N(0, sigma^2)`` (the scatter of
    real runs about the law). A steady run at feed ``F`` says ``c >= F``
    (right-censored); a choked run at ``F`` passing ``T`` says ``T <= c < F``
    (interval-censored: by conservation of mass the mill passes ``T``, and it
    did not pass ``F``). The coefficients and ``log sigma`` are the maximum a
    posteriori of that censored likelihood under weak normal priors
    (:data:`PRIORS`); their posterior covariance is the inverse Hessian there
    (Laplace). ``P(steady at F) = Phi((mu - log F) / sqrt(sigma^2 + z' S z))``:
    monotone in the feed rate by construction, the capacity is ``exp(mu)``.
    With few choked runs the coefficients are largely the priors' and the
    steady runs' lower bounds; the probability carries that uncertainty.
``"demonstrated"``: no choked run at all (what our DEM of the default
    machine gives: its slice passed every feed the chute's feed stream could
    deliver, up to 2520 t/h, docs/mill-dem.md 3.1). The data then bound the
    capacity from below only, and this method says exactly that: a steady
    run at feed ``F_i`` shows the capacity at its own point is **at least**
    ``F_i``; elsewhere the bound is ``max_i F_i 2^(-d_i)``, with ``d_i`` the
    distance to run ``i`` in units of a factor :data:`DEMONSTRATED_SIZE_FACTOR`
    in rock size, :data:`DEMONSTRATED_SPEED_RPM` in shaft speed and
    :data:`DEMONSTRATED_GATE_TOL_DEG` of gate *closing* (a gate opened further
    cannot pass less through the outlet, so opening costs nothing). That is
    the lower bound under one stated assumption, that the capacity at most
    halves over one such unit (log capacity Lipschitz in those units): it
    is continuous in every input (no jump from one nearest run to another),
    never falls as the gates open, rises wherever a run is added, and equals
    the largest feed run at a run's own point when no other run claims more.
    ``P(steady)`` is 1 at or below that feed and unknown (NaN) above it. The
    warning above it says that the feed is beyond what the DEM has shown the
    mill to pass, not that the mill chokes; sweeps and the optimiser flag
    such points and keep them feasible (there is no choke model to exclude
    them by).
``"classifier"``: a Gaussian-process classifier (scikit-learn, anisotropic
    RBF on ``log size``, ``feed``, ``speed``, ``gate`` scaled to about unit
    range) of steady (label 1, plus a steady pseudo-point at each choked run's
    throughput) against choked (label 0); the capacity is the smallest feed on
    a grid at which the probability falls below one half (``inf`` if none).
    Zero prior mean: far from choked runs the probability drifts to its prior,
    and with a handful of choked runs among many steady ones it stays above one
    half everywhere (docs/mill-dem.md, section 3.1).

An envelope file (:class:`EnvelopeData`, JSON) holds the points, the method and
the fitted parameters, and provenance; :func:`load_capacity` refits from the
points on load (no pickles) and checks the refit against the stored
parameters. The shipped one, ``msmill/data/envelopes/default.json``, is built
by ``scripts/build_envelope.py`` from the campaign export.

:func:`check_capacity` / :func:`warn_if_above_capacity` are the hooks
``Mill.run`` (so ``msmill predict``) and the practitioner tools call.
"""

from __future__ import annotations

import functools
import json
import math
import warnings
from dataclasses import asdict, dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from msmill.errors import MsmillInputError
from msmill.stageparams import DESIGN_INPUTS, RunStatistics, design_inputs

__all__ = [
    "METHODS",
    "PRIORS",
    "AboveCapacityWarning",
    "CapacityCheck",
    "CapacityModel",
    "EnvelopeData",
    "EnvelopePoint",
    "check_capacity",
    "default_capacity_model",
    "default_envelope_path",
    "demonstrated_rule",
    "load_capacity",
    "warn_if_above_capacity",
]

METHODS = ("censored", "classifier", "demonstrated")
#: ``"demonstrated"``: a steady run's feed is assumed to bound the capacity to within a factor 2 over one unit
#: of distance: this factor in rock size ...
DEMONSTRATED_SIZE_FACTOR = 1.5
#: ... this many rpm of shaft speed ...
DEMONSTRATED_SPEED_RPM = 250.0
#: ... and this many degrees of gate closing (a wider opening passes at least as much: opening costs nothing)
DEMONSTRATED_GATE_TOL_DEG = 5.0
#: the factor the bound may fall by over one unit of that distance
DEMONSTRATED_FALL_PER_UNIT = 2.0
ENVELOPE_KIND = "msmill_envelope"
_SCALE = np.array([1.0, 60.0, 1900.0, 80.0])  # log(size/mm), t/h, rpm, deg: about unit range over the design space
#: reference point and unit of each input of the censored model's log-linear law
_REF_SIZE_MM, _REF_SPEED_RPM, _SPEED_UNIT_RPM, _REF_GATE_DEG, _GATE_UNIT_DEG = 15.0, 1550.0, 350.0, 40.0, 40.0
#: priors of the censored model (normal, on log capacity): intercept mean log 40 t/h (mid feed range) sd 1
#: (a factor e either way); slopes 0 sd 1 (a factor e per unit: doubled size, 350 rpm, 40 deg);
#: log sigma mean log 0.2, sd 0.7 (run-to-run scatter of capacity ~ 10-40 %)
PRIORS = {"intercept_mean": math.log(40.0), "intercept_sd": 1.0, "slope_sd": 1.0,
          "log_sigma_mean": math.log(0.2), "log_sigma_sd": 0.7}
_COEFS = ("log_capacity_at_ref", "per_size_doubling", "per_350_rpm", "per_40_deg_gate")


class AboveCapacityWarning(UserWarning):
    """The requested feed rate is above the mill's predicted capacity."""


@dataclass(frozen=True)
class EnvelopePoint:
    """One DEM run's operating point and outcome (feed and throughput full-mill t/h)."""

    size_mm: float
    feed_tph: float
    speed_rpm: float
    gate_deg: float
    outcome: str
    throughput_tph: float | None = None

    @classmethod
    def from_statistics(cls, st: RunStatistics) -> EnvelopePoint:
        """The point of a run's statistics (``outcome`` None counts as steady)."""
        d = st.design
        return cls(size_mm=d.size_mm, feed_tph=d.feed_tph, speed_rpm=d.speed_rpm, gate_deg=d.gate_deg,
                   outcome=st.outcome or "steady", throughput_tph=st.throughput_tph)


@dataclass
class EnvelopeData:
    """Envelope points, the fitted model's method and parameters, and provenance (JSON).

    ``{"kind": "msmill_envelope", "points": [...], "model": {"method", "params"} or null, "provenance": {...}}``.
    """

    points: list[EnvelopePoint]
    provenance: dict[str, Any] = field(default_factory=dict)
    model: dict[str, Any] | None = None

    def to_json(self, path: str | Path) -> None:
        """Write the points, model and provenance as JSON."""
        doc = {"kind": ENVELOPE_KIND, "format_version": 1, "points": [asdict(p) for p in self.points],
               "model": self.model, "provenance": self.provenance}
        Path(path).write_text(json.dumps(doc, indent=1) + "\n", encoding="utf-8")

    @classmethod
    def from_json(cls, path: str | Path) -> EnvelopeData:
        """Read a file written by :meth:`to_json`; errors are one line."""
        p = Path(path)
        try:
            doc = json.loads(p.read_text(encoding="utf-8"))
            pts = [EnvelopePoint(**x) for x in doc["points"]]
        except (OSError, json.JSONDecodeError, KeyError, TypeError) as exc:
            raise MsmillInputError(str(p), type(exc).__name__, "an envelope JSON file ({'points': [...]})") from None
        return cls(pts, doc.get("provenance", {}), doc.get("model"))

    def counts(self) -> dict[str, int]:
        """Number of points per outcome."""
        out = {"steady": 0, "choked": 0, "not_steady": 0}
        for p in self.points:
            out[p.outcome] = out.get(p.outcome, 0) + 1
        return out


def _features(size_mm: Any, feed_tph: Any, speed_rpm: Any, gate_deg: Any) -> np.ndarray:
    cols = np.broadcast_arrays(*(np.asarray(v, dtype=float) for v in (size_mm, feed_tph, speed_rpm, gate_deg)))
    x = np.column_stack([c.ravel() for c in cols])
    x[:, 0] = np.log(x[:, 0])
    return x / _SCALE


def _design(size_mm: Any, speed_rpm: Any, gate_deg: Any) -> np.ndarray:
    """Rows ``[1, log2(size/15), (speed-1550)/350, (gate-40)/40]`` of the censored model's law."""
    s, v, g = (np.ravel(c) for c in np.broadcast_arrays(*(np.asarray(x, dtype=float)
                                                          for x in (size_mm, speed_rpm, gate_deg))))
    return np.column_stack([np.ones_like(s), np.log2(s / _REF_SIZE_MM), (v - _REF_SPEED_RPM) / _SPEED_UNIT_RPM,
                            (g - _REF_GATE_DEG) / _GATE_UNIT_DEG])


def _split(points: list[EnvelopePoint], need_choked: bool = True) -> tuple[list[EnvelopePoint], list[EnvelopePoint]]:
    steady = [p for p in points if p.outcome == "steady"]
    choked = [p for p in points if p.outcome == "choked"]
    if not steady and not need_choked:
        raise MsmillInputError("envelope points", "no steady run", "at least one steady run")
    if need_choked and (not steady or not choked):
        raise MsmillInputError("envelope points", f"{len(steady)} steady, {len(choked)} choked",
                               "at least one steady and one choked run")
    return steady, choked


def _neg_log_posterior(theta: np.ndarray, z_s, lf_s, z_c, lo_c, hi_c, pr: dict[str, float]) -> np.ndarray:
    """Censored negative log posterior; ``theta`` is ``(5, ...)`` (coefficients, log sigma), vectorised."""
    from scipy.special import log_ndtr

    beta, log_sigma = theta[:4], theta[4]
    sigma = np.exp(log_sigma)
    mu_s = np.tensordot(z_s, beta, axes=(1, 0))
    mu_c = np.tensordot(z_c, beta, axes=(1, 0))
    ll = log_ndtr((mu_s - lf_s.reshape(lf_s.shape + (1,) * (mu_s.ndim - 1))) / sigma).sum(axis=0)
    b = log_ndtr((hi_c.reshape(hi_c.shape + (1,) * (mu_c.ndim - 1)) - mu_c) / sigma)   # P(c < F)
    a = log_ndtr((lo_c.reshape(lo_c.shape + (1,) * (mu_c.ndim - 1)) - mu_c) / sigma)   # P(c < T)
    ll = ll + (b + np.log1p(-np.exp(np.minimum(a - b, -1e-12)))).sum(axis=0)           # log P(T <= c < F)
    lp = (-0.5 * ((beta[0] - pr["intercept_mean"]) / pr["intercept_sd"]) ** 2
          - 0.5 * (beta[1:] ** 2).sum(axis=0) / pr["slope_sd"] ** 2
          - 0.5 * ((log_sigma - pr["log_sigma_mean"]) / pr["log_sigma_sd"]) ** 2)
    return -(ll + lp)


def _fit_censored(points: list[EnvelopePoint], priors: dict[str, float] | None = None) -> dict[str, Any]:
    """MAP and Laplace covariance of the censored model; a JSON-able parameter dict."""
    from scipy.differentiate import hessian
    from scipy.optimize import minimize

    steady, choked = _split(points)
    z_s = _design([p.size_mm for p in steady], [p.speed_rpm for p in steady], [p.gate_deg for p in steady])
    lf_s = np.log([p.feed_tph for p in steady])
    z_c = _design([p.size_mm for p in choked], [p.speed_rpm for p in choked], [p.gate_deg for p in choked])
    hi_c = np.log([p.feed_tph for p in choked])
    # a choked run without a usable throughput only says c < F
    lo_c = np.log([p.throughput_tph if p.throughput_tph and p.throughput_tph < p.feed_tph else 1e-9 for p in choked])
    pr = {**PRIORS, **(priors or {})}
    args = (z_s, lf_s, z_c, lo_c, hi_c, pr)
    x0 = np.array([pr["intercept_mean"], 0.0, 0.0, 0.0, pr["log_sigma_mean"]])
    res = minimize(lambda t: float(_neg_log_posterior(t, *args)), x0, method="L-BFGS-B")
    h = hessian(lambda t: _neg_log_posterior(t, *args), res.x).ddf
    cov = np.linalg.inv(0.5 * (h + h.T))
    return {"coefficients": dict(zip(_COEFS, (float(v) for v in res.x[:4]), strict=True)),
            "sigma": float(np.exp(res.x[4])), "covariance": cov[:4, :4].tolist(),
            "log_sigma_sd": float(math.sqrt(max(cov[4, 4], 0.0))), "converged": bool(res.success),
            "neg_log_posterior": float(res.fun), "priors": pr,
            "law": "log c = b0 + b1 log2(size/15 mm) + b2 (speed-1550 rpm)/350 rpm + b3 (gate-40 deg)/40 deg"}


def _fit_classifier(points: list[EnvelopePoint], throughput_as_steady: bool, seed: int,
                    theta: list[float] | None) -> tuple[Any, dict[str, Any]]:
    from sklearn.exceptions import ConvergenceWarning
    from sklearn.gaussian_process import GaussianProcessClassifier
    from sklearn.gaussian_process.kernels import RBF, ConstantKernel

    _split(points)
    rows, labels = [], []
    for p in points:
        if p.outcome in ("steady", "choked"):
            rows.append(tuple(getattr(p, k) for k in DESIGN_INPUTS))
            labels.append(int(p.outcome == "steady"))
            if p.outcome == "choked" and throughput_as_steady and p.throughput_tph:
                rows.append((p.size_mm, p.throughput_tph, p.speed_rpm, p.gate_deg))
                labels.append(1)
    kernel = ConstantKernel(1.0, (1e-2, 1e5)) * RBF(np.ones(4), (0.05, 20.0))
    if theta is not None:
        kernel = kernel.clone_with_theta(np.asarray(theta, dtype=float))
    with warnings.catch_warnings():  # hyper-parameters at a bound are fine for a few points
        warnings.simplefilter("ignore", ConvergenceWarning)
        gpc = GaussianProcessClassifier(kernel=kernel, random_state=seed, n_restarts_optimizer=0,
                                        optimizer=None if theta is not None else "fmin_l_bfgs_b")
        gpc.fit(_features(*np.array(rows).T), np.array(labels))
    return gpc, {"kernel": str(gpc.kernel_), "theta": [float(v) for v in gpc.kernel_.theta],
                 "log_marginal_likelihood": float(gpc.log_marginal_likelihood_value_),
                 "throughput_as_steady": throughput_as_steady, "seed": seed, "n_labelled_steady": int(sum(labels))}


def demonstrated_rule() -> str:
    """The ``"demonstrated"`` lower bound in words, for the summaries and pages that show it."""
    return (f"a steady DEM run's feed, halved per {DEMONSTRATED_SIZE_FACTOR:g}x in rock size, "
            f"{DEMONSTRATED_SPEED_RPM:g} rpm or {DEMONSTRATED_GATE_TOL_DEG:g} deg of gate closing away from it; "
            "no run has choked")


def _demonstrated_params() -> dict[str, float]:
    return {"size_factor": DEMONSTRATED_SIZE_FACTOR, "speed_window_rpm": DEMONSTRATED_SPEED_RPM,
            "gate_tolerance_deg": DEMONSTRATED_GATE_TOL_DEG, "fall_per_unit": DEMONSTRATED_FALL_PER_UNIT}


def _demonstrated_tph(steady: np.ndarray, params: dict[str, float], size_mm: Any, speed_rpm: Any,
                      gate_deg: Any) -> np.ndarray:
    """Lower bound on the capacity (t/h) at each query from the steady runs ``steady`` (rows size, feed, speed,
    gate): ``max_i feed_i fall^(-d_i)``, ``d_i`` the distance to run ``i`` in the units of ``params``."""
    s, v, g = (np.ravel(c) for c in np.broadcast_arrays(*(np.asarray(x, dtype=float)
                                                          for x in (size_mm, speed_rpm, gate_deg))))
    d2 = ((np.log(steady[None, :, 0] / s[:, None]) / math.log(params["size_factor"])) ** 2
          + ((steady[None, :, 2] - v[:, None]) / params["speed_window_rpm"]) ** 2
          + (np.maximum(steady[None, :, 3] - g[:, None], 0.0) / params["gate_tolerance_deg"]) ** 2)
    log_bound = np.log(steady[None, :, 1]) - np.sqrt(d2) * math.log(params["fall_per_unit"])
    return np.exp(log_bound.max(axis=1))


@dataclass
class CapacityModel:
    """Probability of steady flow and capacity from steady and choked DEM points (module docstring).

    Attributes
    ----------
    method : {"censored", "classifier", "demonstrated"}
    params : dict
        Fitted parameters (JSON-able; stored in envelope files).
    n_steady, n_choked : int
        Runs used per outcome (the classifier's steady count includes its pseudo-points).
    domain : dict
        ``{input: [low, high]}`` over the steady and choked runs (size mm, speed rpm, gate deg, feed t/h).
    classifier : object or None
        The scikit-learn classifier (``"classifier"`` only).
    steady : ndarray or None
        ``"demonstrated"`` only: rows ``(size mm, feed t/h, speed rpm, gate deg)`` of the steady runs.
    """

    method: str
    params: dict[str, Any]
    n_steady: int
    n_choked: int
    domain: dict[str, list[float]]
    classifier: Any = None
    steady: np.ndarray | None = None

    @property
    def lower_bound(self) -> bool:
        """The capacity is a lower bound (``"demonstrated"``: no run choked), not an estimate."""
        return self.method == "demonstrated"

    @classmethod
    def fit(cls, points: list[EnvelopePoint], method: str = "censored", throughput_as_steady: bool = True,
            seed: int = 0, theta: list[float] | None = None, priors: dict[str, float] | None = None) -> CapacityModel:
        """Fit to steady and choked points (not-steady points are ignored).

        ``"demonstrated"`` needs steady points only (choked ones are ignored
        by it: with a choke, use ``"censored"``).

        ``priors`` (entries of :data:`PRIORS` to change) applies to the
        censored model; ``throughput_as_steady``, ``seed`` and ``theta`` (fixed
        log hyper-parameters, no optimisation) to the classifier.

        Raises
        ------
        MsmillInputError
            If the points hold no steady or no choked run (nothing to separate; ``"demonstrated"``: no
            steady run), or the method is unknown.
        """
        if method not in METHODS:
            raise MsmillInputError("method", method, " or ".join(METHODS))
        steady, choked = _split(points, need_choked=method != "demonstrated")
        if method == "demonstrated":
            rows = design_inputs(steady)
            dom = {k: [float(rows[:, j].min()), float(rows[:, j].max())]
                   for j, k in enumerate(DESIGN_INPUTS)}
            return cls(method, _demonstrated_params(), len(steady), 0, dom, steady=rows)
        used = steady + choked
        dom = {k: [float(min(getattr(p, k) for p in used)), float(max(getattr(p, k) for p in used))]
               for k in DESIGN_INPUTS}
        if method == "censored":
            return cls(method, _fit_censored(points, priors), len(steady), len(choked), dom)
        gpc, params = _fit_classifier(points, throughput_as_steady, seed, theta)
        return cls(method, params, params.pop("n_labelled_steady"), len(choked), dom, gpc)

    def log_capacity(self, size_mm: Any, speed_rpm: Any, gate_deg: Any) -> tuple[np.ndarray, np.ndarray]:
        """Censored model: mean and predictive sd of log capacity (sd includes the run scatter sigma)."""
        if self.method != "censored":
            raise MsmillInputError("method", self.method, "censored (log_capacity is the censored model's)")
        z = _design(size_mm, speed_rpm, gate_deg)
        beta = np.array([self.params["coefficients"][k] for k in _COEFS])
        cov = np.asarray(self.params["covariance"])
        var = self.params["sigma"] ** 2 + np.einsum("ni,ij,nj->n", z, cov, z)
        return z @ beta, np.sqrt(var)

    def probability_steady(self, size_mm: Any, feed_tph: Any, speed_rpm: Any, gate_deg: Any) -> np.ndarray:
        """Probability that the mill is steady (passes its feed) at the given points (broadcast).

        ``"demonstrated"``: 1 at or below the lower bound, NaN (unknown) above it.
        """
        if self.method == "demonstrated":
            f = np.ravel(np.broadcast_arrays(*(np.asarray(x, dtype=float)
                                               for x in (feed_tph, size_mm, speed_rpm, gate_deg)))[0])
            lb = _demonstrated_tph(self.steady, self.params, size_mm, speed_rpm, gate_deg)
            return np.where(f <= lb, 1.0, np.nan)
        if self.method == "classifier":
            return self.classifier.predict_proba(_features(size_mm, feed_tph, speed_rpm, gate_deg))[:, 1]
        from scipy.special import ndtr

        s, f, v, g = np.broadcast_arrays(*(np.asarray(x, dtype=float) for x in (size_mm, feed_tph, speed_rpm,
                                                                               gate_deg)))
        mu, sd = self.log_capacity(s, v, g)
        return ndtr((mu - np.log(f.ravel())) / sd)

    def capacity_tph(self, size_mm: float, speed_rpm: float, gate_deg: float,
                     feed_range_tph: tuple[float, float] = (1.0, 120.0), n_grid: int = 240) -> float:
        """Feed rate (t/h) at which the steady probability is 1/2.

        Censored model: ``exp(mu)`` in closed form. Classifier: the smallest
        feed on a grid over ``feed_range_tph`` where it falls below 1/2
        (``inf`` if none). Demonstrated: the lower bound (module docstring).
        """
        if self.method == "demonstrated":
            return float(_demonstrated_tph(self.steady, self.params, size_mm, speed_rpm, gate_deg)[0])
        if self.method == "censored":
            return float(np.exp(self.log_capacity(size_mm, speed_rpm, gate_deg)[0][0]))
        f = np.linspace(*feed_range_tph, n_grid)
        p = self.probability_steady(size_mm, f, speed_rpm, gate_deg)
        below = np.flatnonzero(p < 0.5)
        if below.size == 0:
            return float("inf")
        j = int(below[0])
        if j == 0:
            return float(f[0])
        # linear interpolation of the crossing between grid points j - 1 and j
        return float(f[j - 1] + (p[j - 1] - 0.5) / (p[j - 1] - p[j]) * (f[j] - f[j - 1]))

    def outside(self, size_mm: float, speed_rpm: float, gate_deg: float) -> list[str]:
        """The inputs outside the range of the runs the model was fitted to (an extrapolation there)."""
        vals = {"size_mm": size_mm, "speed_rpm": speed_rpm, "gate_deg": gate_deg}
        return [k for k, v in vals.items() if not self.domain[k][0] <= v <= self.domain[k][1]]

    def to_envelope(self, points: list[EnvelopePoint], provenance: dict[str, Any]) -> EnvelopeData:
        """The points with this model's method and parameters, for :meth:`EnvelopeData.to_json`."""
        return EnvelopeData(points, provenance, {"method": self.method, "params": self.params,
                                                 "n_steady": self.n_steady, "n_choked": self.n_choked,
                                                 "domain": self.domain})


def load_capacity(source: str | Path | EnvelopeData, refit: bool = False) -> CapacityModel:
    """The capacity model of an envelope file, rebuilt from its JSON (no pickles).

    A file without a ``model`` entry (``msmill dem envelope``) is fitted with
    the default method (``"demonstrated"`` when none of its runs choked). With one, the censored model is rebuilt from its
    stored parameters, the classifier refitted to the points at its stored
    hyper-parameters. ``refit`` refits the censored model from the points and
    checks it against the stored parameters: a mismatch (the fitting code or
    the points changed since the file was built) warns that the file should be
    rebuilt.
    """
    env = source if isinstance(source, EnvelopeData) else EnvelopeData.from_json(source)
    stored = env.model or {}
    # a points-only file: the censored model when some run choked, else what the runs demonstrate
    method = stored.get("method") or ("censored" if any(p.outcome == "choked" for p in env.points)
                                      else "demonstrated")
    params = stored.get("params") or {}
    if method == "censored" and params and not refit:
        try:
            return CapacityModel("censored", params, int(stored["n_steady"]), int(stored["n_choked"]),
                                 {k: list(v) for k, v in stored["domain"].items()})
        except (KeyError, TypeError, ValueError):
            raise MsmillInputError(str(source), "model", "an envelope whose model has params, counts and domain "
                                   "(scripts/build_envelope.py)") from None
    if method == "demonstrated":
        model = CapacityModel.fit(env.points, method=method)
        if params and params != model.params:
            warnings.warn(f"envelope {getattr(source, 'name', 'data')}: its neighbourhood {params} is not this "
                          f"version's {model.params} (rebuild it with scripts/build_envelope.py)", UserWarning,
                          stacklevel=2)
        return model
    model = CapacityModel.fit(env.points, method=method, seed=params.get("seed", 0),
                              theta=params.get("theta") if method == "classifier" else None,
                              priors=params.get("priors"))
    if method == "censored" and params:
        old = np.array([*params["coefficients"].values(), params["sigma"]])
        new = np.array([*model.params["coefficients"].values(), model.params["sigma"]])
        if not np.allclose(old, new, rtol=1e-3, atol=1e-3):
            warnings.warn(f"envelope {getattr(source, 'name', 'data')}: refitted capacity parameters differ from "
                          "the stored ones (rebuild it with scripts/build_envelope.py)", UserWarning, stacklevel=2)
    return model


def default_envelope_path() -> Path | None:
    """Path of the shipped envelope ``msmill/data/envelopes/default.json``, None when absent."""
    p = Path(str(resources.files("msmill").joinpath("data/envelopes/default.json")))
    return p if p.is_file() else None


@functools.lru_cache(maxsize=1)
def default_capacity_model() -> CapacityModel | None:
    """The shipped envelope's capacity model (loaded once), None when no envelope ships."""
    p = default_envelope_path()
    return load_capacity(p) if p is not None else None


@dataclass(frozen=True)
class CapacityCheck:
    """Requested feed against the predicted capacity at one point (t/h)."""

    feed_tph: float
    capacity_tph: float
    probability_steady: float
    size_mm: float
    speed_rpm: float
    gate_deg: float
    outside: tuple[str, ...] = ()
    largest_feed_tph: float = float("inf")
    lower_bound: bool = False

    @property
    def above(self) -> bool:
        """The feed exceeds the capacity (steady probability below one half)."""
        return self.feed_tph > self.capacity_tph

    def message(self) -> str:
        """One line: capacity, requested feed, by how much, probability of steady flow."""
        where = f"at {self.size_mm:.3g} mm, {self.speed_rpm:g} rpm, gate {self.gate_deg:g} deg"
        if self.lower_bound:
            if self.above:
                return (f"feed {self.feed_tph:g} t/h is above the feed the DEM has shown the mill to pass "
                        f"{where} ({self.capacity_tph:.0f} t/h, by {self.feed_tph - self.capacity_tph:.0f} t/h; "
                        f"{demonstrated_rule()}): the capacity above it is unknown, not exceeded")
            return (f"capacity at least {self.capacity_tph:.0f} t/h {where} ({demonstrated_rule()}); "
                    f"feed {self.feed_tph:g} t/h")
        extra = f"; extrapolated in {', '.join(self.outside)}" if self.outside else ""
        if self.capacity_tph > self.largest_feed_tph:
            extra += f"; above the largest DEM feed ({self.largest_feed_tph:.0f} t/h), so not measured"
        if self.above:
            return (f"feed {self.feed_tph:g} t/h is above the predicted capacity {self.capacity_tph:.1f} t/h {where} "
                    f"(by {self.feed_tph - self.capacity_tph:.1f} t/h, "
                    f"{100 * (self.feed_tph / self.capacity_tph - 1):.0f} %): probability of steady flow "
                    f"{self.probability_steady:.2f}, the mill is expected to choke{extra}")
        return (f"capacity {self.capacity_tph:.1f} t/h {where} (DEM envelope); feed {self.feed_tph:g} t/h, "
                f"probability of steady flow {self.probability_steady:.2f}{extra}")


def check_capacity(model: CapacityModel | None, size_mm: float, feed_tph: float, speed_rpm: float,
                   gate_deg: float) -> CapacityCheck | None:
    """The capacity and steady probability at a point; None without a model (or where it makes no statement)."""
    if model is None:
        return None
    cap = model.capacity_tph(size_mm, speed_rpm, gate_deg)
    if math.isnan(cap):
        return None
    return CapacityCheck(float(feed_tph), cap,
                         float(model.probability_steady(size_mm, feed_tph, speed_rpm, gate_deg)[0]),
                         float(size_mm), float(speed_rpm), float(gate_deg),
                         tuple(model.outside(size_mm, speed_rpm, gate_deg)), model.domain["feed_tph"][1],
                         lower_bound=model.lower_bound)


def warn_if_above_capacity(model: CapacityModel | None, size_mm: float, feed_tph: float, speed_rpm: float,
                           gate_deg: float, stacklevel: int = 2) -> float | None:
    """Warn (:class:`AboveCapacityWarning`) if ``feed_tph`` exceeds the predicted capacity; return the capacity.

    ``model`` None (no envelope data) does nothing and returns None.
    """
    chk = check_capacity(model, size_mm, feed_tph, speed_rpm, gate_deg)
    if chk is None:
        return None
    if chk.above:
        warnings.warn(chk.message(), AboveCapacityWarning, stacklevel=stacklevel)
    return chk.capacity_tph
