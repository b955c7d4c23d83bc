"""SYNTHETIC experiments made by the model itself (for examples and tests; never measured data).

A synthetic survey is the model's steady-state product at a stated operating
point and ore, read at a standard sieve series, with optional multiplicative
noise on the mass retained on every sieve::

    m_i' = m_i exp(sigma z_i),   z_i ~ N(0, 1),   then renormalised,

which keeps the curve monotone and mimics sieving / sampling error of a
few percent of each fraction. A synthetic single-impact test is the same for
one impact at a given speed (``msmill.model.fitting.single_impact_product``).
Every experiment's ``source`` says SYNTHETIC and how it was made.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from msmill.model.experiments import Experiment, experiment_from_dict
from msmill.psd import PSD

__all__ = ["EXAMPLE_FEEDS", "EXAMPLE_POINTS", "EXAMPLE_SIGMA", "EXAMPLE_TRUE_L_REF_MM", "SIEVES_MM", "model_surveys", "noisy_passing", "synthetic_impact_test", "synthetic_survey"]

#: Sieve series (mm) used for synthetic products: the sqrt(2) series up to 13.2 mm, then the
#: 2^(1/4) series (16, 22.4, 31.5, 45 mm added) where the products' curves are steep.
SIEVES_MM = (0.075, 0.106, 0.15, 0.212, 0.3, 0.425, 0.6, 0.85, 1.18, 1.7, 2.36, 3.35, 4.75, 6.7,
             9.5, 13.2, 16.0, 19.0, 22.4, 26.5, 31.5, 37.5, 45.0, 53.0)


# The design of the SYNTHETIC example experiments (``scripts/make_example_experiments.py``).
#: Noise of the example surveys and lab tests: multiplicative sigma on every retained sieve mass.
EXAMPLE_SIGMA = 0.05
#: The "true" L_ref (mm) the example surveys were made with (the ore default is 29 mm).
EXAMPLE_TRUE_L_REF_MM = {"UG2": 20.0, "Platreef": 40.0}
#: ILLUSTRATIVE feeds of the example experiments (plausible crusher products), not measured.
EXAMPLE_FEEDS: dict[str, dict[str, list[float]]] = {
    "coarse": {"size_mm": [2.36, 4.75, 9.5, 13.2, 19.0, 26.5, 31.5], "passing_pct": [2.0, 6.0, 18.0, 32.0, 58.0, 88.0, 100.0]},
    "fine": {"size_mm": [1.18, 2.36, 4.75, 9.5, 13.2, 19.0, 26.5], "passing_pct": [3.0, 7.0, 16.0, 42.0, 63.0, 90.0, 100.0]},
}
#: Operating points of the example surveys per ore: (feed_tph, upper speed rpm, gate deg, feeds).
EXAMPLE_POINTS: dict[str, list[tuple[float, float, float, tuple[str, ...]]]] = {
    "UG2": [(30.0, 1500.0, 40.0, ("coarse", "fine")), (30.0, 1300.0, 40.0, ("coarse", "fine")),
            (40.0, 1700.0, 60.0, ("coarse", "fine")), (25.0, 1850.0, 50.0, ("coarse", "fine")),
            (30.0, 2000.0, 40.0, ("coarse",))],  # the last one lies outside the design space on purpose
    "Platreef": [(30.0, 1500.0, 40.0, ("coarse", "fine")), (45.0, 1400.0, 70.0, ("coarse", "fine")),
                 (20.0, 1800.0, 40.0, ("coarse", "fine"))],
}


def noisy_passing(psd: PSD, sieves_mm: np.ndarray, sigma: float, rng: np.random.Generator) -> np.ndarray:
    """% passing of ``psd`` at ``sieves_mm`` with multiplicative noise ``sigma`` on each retained mass."""
    s = np.asarray(sieves_mm, dtype=float)
    p = np.asarray(psd.passing_at(s), dtype=float)
    top = psd.grid.edges_mm[-1]
    s = s[s < top * 1.5]
    p = p[: s.size]
    m = np.diff(np.concatenate([[0.0], p, [100.0]]))  # pan, classes, oversize
    if sigma > 0:
        m = m * np.exp(sigma * rng.standard_normal(m.size))
    m = m / m.sum() * 100.0
    out = np.cumsum(m)[:-1]
    out[-1] = min(out[-1], 100.0)
    if p[-1] >= 100.0:
        out[-1] = 100.0
    return np.round(np.maximum.accumulate(out), 4)


def _table(sizes: np.ndarray, passing: np.ndarray) -> dict[str, list[float]]:
    s, p = sizes, passing
    first_full = int(np.argmax(p >= 100.0)) if np.any(p >= 100.0) else p.size - 1
    return {"size_mm": [float(x) for x in s[: first_full + 1]],
            "passing_pct": [float(x) for x in p[: first_full + 1]]}


def synthetic_survey(ident: str, ore_name: str, feed: dict[str, list[float]], feed_tph: float,
                     operating: dict[str, Any], product: PSD, sigma: float, rng: np.random.Generator,
                     how: str, power_kw: float | None = None) -> Experiment:
    """A survey Experiment whose product is ``product`` (the model's) read at :data:`SIEVES_MM` with noise."""
    sizes = np.array(SIEVES_MM)
    pas = noisy_passing(product, sizes, sigma, rng)
    doc = {"kind": "survey", "id": ident, "ore": ore_name,
           "source": f"SYNTHETIC (not measured): {how}; product noise sigma = {sigma:g} on retained masses",
           "feed": {"rate_tph": feed_tph, **feed}, "operating": operating,
           "product": _table(sizes[: pas.size], pas)}
    if power_kw is not None:
        doc["measured"] = {"power_kw": round(float(power_kw), 2)}
    return experiment_from_dict(doc, origin=ident)


def synthetic_impact_test(ident: str, ore_name: str, feed: dict[str, list[float]], speed_m_s: float,
                          product: PSD, sigma: float, rng: np.random.Generator, how: str) -> Experiment:
    """A single-impact Experiment whose product is ``product`` read at :data:`SIEVES_MM` with noise."""
    sizes = np.array(SIEVES_MM)
    pas = noisy_passing(product, sizes, sigma, rng)
    doc = {"kind": "single_impact", "id": ident, "ore": ore_name, "impact_speed_m_s": speed_m_s,
           "source": f"SYNTHETIC (not measured): {how}; product noise sigma = {sigma:g} on retained masses",
           "feed": feed, "product": _table(sizes[: pas.size], pas)}
    return experiment_from_dict(doc, origin=ident)


def model_surveys(ore_name: str, specs: list[tuple[str, dict, float, dict]], true_changes: dict[str, float],
                  sigma: float, rng: np.random.Generator, stage_parameters: Any = "default",
                  how: str = "", power: Any = None) -> list[Experiment]:
    """SYNTHETIC surveys of one ore made by the model at ``true_changes`` (e.g. ``{"l_ref_mm": 20}``).

    Parameters
    ----------
    specs : list of (id, feed table, feed_tph, operating dict)
        ``feed table`` has ``size_mm`` and ``passing_pct``.
    power : callable, optional
        ``(experiment, MillResult) -> power_kw`` giving a synthetic "measured" power.
    """
    from msmill.model.mill import Mill
    from msmill.model.validation import SurveyModel

    drafts = [experiment_from_dict({"kind": "survey", "id": i, "ore": ore_name, "source": "draft",
                                    "feed": {"rate_tph": tph, **feed}, "operating": opr,
                                    "product": {"size_mm": [1.0, 2.0], "passing_pct": [50.0, 100.0]}})
              for i, feed, tph, opr in specs]
    model = SurveyModel(ore_name, drafts, stage_parameters)
    true = model.with_ore(**true_changes)
    prods = model.products(true)
    mill = Mill(true, model.mill.provider, grid=model.grid) if power is not None else None
    out = []
    for e, frac in zip(drafts, prods, strict=True):
        kw = None
        if mill is not None:
            kw = power(e, mill.run(e.feed_psd, e.operating_point(), timeseries=False, held_below=False))
        text = how or ("msmill expected-value model at " + ", ".join(f"{k} = {v:g}" for k, v in true_changes.items()))
        out.append(synthetic_survey(e.id, ore_name, e.raw["feed"], e.feed_tph, e.operating,
                                    PSD(model.grid, frac, validate=False), sigma, rng, text, kw))
    return out
