"""The result of a mill-model prediction: one frozen dataclass with pandas objects."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from msmill.psd import PSD
from msmill.steadystate import SteadyStateCriterion, first_steady


@dataclass(frozen=True)
class MillResult:
    """Prediction of one mill at one operating point (units in every name).

    Attributes
    ----------
    feed_psd, product_psd : msmill.psd.PSD
        Feed and steady-state product PSDs on the model grid.
    psd_table : pandas.DataFrame
        Per size class: ``lower_mm, upper_mm, mid_mm, feed_mass_fraction,
        product_mass_fraction, feed_passing_pct, product_passing_pct`` (passing
        at ``upper_mm``).
    p50_mm, p80_mm, f80_mm : float
        Product P50, product P80 and feed F80 (mm).
    reduction_ratio : float
        ``F80 / P80``.
    passing_pct : pandas.Series
        Product % passing at the chosen sizes (index ``size_mm``).
    timeseries : pandas.DataFrame
        ``time_s, feed_tph, holdup_t, product_tph`` from an empty mill (paper
        Fig. 14); ``holdup_t`` includes the inlet zone.
    time_to_steady_state_s : float
        Onset of steady state by the criterion the DEM uses
        (:mod:`msmill.steadystate`: product within 10 % of the feed and no
        hold-up trend over two 0.65 s windows), NaN if not reached.
    stages : pandas.DataFrame
        Per stage at steady state: ``stage, holdup_t, p80_mm,
        primary_impacts_per_t, secondary_impacts_per_t,
        impact_energy_kwh_t, flinger_energy_j_per_t`` (per tonne of feed).
    stage_psd : pandas.DataFrame
        Mass fraction per size class (rows, index ``upper_mm``) of each stage's
        hold-up (columns ``stage_1 ...``).
    primary_impacts_per_t, secondary_impacts_per_t : float
        Impacted tonnes per tonne of feed, i.e. the mean number of primary /
        secondary impacts a unit mass of feed receives on its way through.
    specific_impact_energy_kwh_t : float
        Impact energy delivered to the rock per tonne of feed (kWh/t).
    mass_balance_error : float
        Largest relative mass-balance error over all steps (and of the steady state).
    feed_tph : float
        Feed rate (t/h).
    characteristic_time_s : float
        Model time step (s).
    solver : str
        ``"expected_value"`` or ``"monte_carlo"``.
    submodels : dict
        The sub-models used, by step.
    notes : tuple of str
        Defaults in use, providers' sources, other remarks.
    extrapolated_feed_pct, extrapolated_product_pct : float
        Mass % of the feed and of the product in size classes whose stage
        parameters were extrapolated outside the sizes the statistics cover.
    thin_data_feed_pct, thin_data_product_pct : float
        Mass % of the feed and of the product in size classes inside the sizes
        covered whose stage parameters rest on thin data (far from every
        training run, :class:`msmill.errors.ThinDataWarning`).
    p80_band_mm : tuple of float or None
        5-95 % band of P80 (mm) over posterior samples of the stage
        parameters, when the provider gives them (the GP surrogate); else None
        (see :func:`with_band`).
    psd_band : pandas.DataFrame or None
        Per size class (index ``upper_mm``): ``product_passing_pct_p05,
        product_passing_pct_p50, product_passing_pct_p95`` (p50 is the
        prediction itself).
        The same p05/p95 columns are appended to ``psd_table``.
    band_samples : int
        Number of posterior samples behind the band (0: no band).
    capacity_tph, probability_steady : float or None
        Capacity at the feed's F80, speed and gate from the mill's DEM
        envelope (:mod:`msmill.surrogate.capacity`), and the probability that the mill
        passes the requested feed there; None without an envelope.
    held_below_mm, held_below_p80_mm, held_below_passing_75um_pct : float
        The other bounding rule for rock finer than the stage statistics cover (issue 38): the smallest
        size they cover (mm), and the product's P80 (mm) and % passing 75 um with the statistics held at
        that size below it (:class:`msmill.model.providers.HeldBelow`) instead of the provider's own
        extrapolation; NaN when no class lies below.
    capacity_is_lower_bound : bool
        The envelope has no choked run (method ``"demonstrated"``): ``capacity_tph``
        is the largest feed a steady DEM run near this point passed, and
        ``probability_steady`` is NaN (unknown) above it.
    """

    feed_psd: PSD
    product_psd: PSD
    psd_table: pd.DataFrame
    p50_mm: float
    p80_mm: float
    f80_mm: float
    reduction_ratio: float
    passing_pct: pd.Series
    timeseries: pd.DataFrame
    time_to_steady_state_s: float
    stages: pd.DataFrame
    stage_psd: pd.DataFrame
    primary_impacts_per_t: float
    secondary_impacts_per_t: float
    specific_impact_energy_kwh_t: float
    mass_balance_error: float
    feed_tph: float
    characteristic_time_s: float
    solver: str
    submodels: dict[str, str] = field(default_factory=dict)
    notes: tuple[str, ...] = ()
    extrapolated_feed_pct: float = float("nan")
    extrapolated_product_pct: float = float("nan")
    thin_data_feed_pct: float = float("nan")
    thin_data_product_pct: float = float("nan")
    #: per model size class: stage statistics extrapolated in size / from thin data (None: not known)
    extrapolated_classes: np.ndarray | None = None
    thin_data_classes: np.ndarray | None = None
    p80_band_mm: tuple[float, float] | None = None
    psd_band: pd.DataFrame | None = None
    band_samples: int = 0
    capacity_tph: float | None = None
    probability_steady: float | None = None
    capacity_is_lower_bound: bool = False
    held_below_mm: float = float("nan")
    held_below_p80_mm: float = float("nan")
    held_below_passing_75um_pct: float = float("nan")

    def summary(self) -> pd.Series:
        """Headline figures as a Series (index names carry the units)."""
        return pd.Series({
            "feed_tph": self.feed_tph,
            "f80_mm": self.f80_mm,
            "p80_mm": self.p80_mm,
            "p50_mm": self.p50_mm,
            "reduction_ratio": self.reduction_ratio,
            "time_to_steady_state_s": self.time_to_steady_state_s,
            "holdup_t": float(self.stages["holdup_t"].sum()),
            "primary_impacts_per_t": self.primary_impacts_per_t,
            "secondary_impacts_per_t": self.secondary_impacts_per_t,
            "specific_impact_energy_kwh_t": self.specific_impact_energy_kwh_t,
            "mass_balance_error": self.mass_balance_error,
            "extrapolated_feed_pct": self.extrapolated_feed_pct,
            "extrapolated_product_pct": self.extrapolated_product_pct,
            "thin_data_feed_pct": self.thin_data_feed_pct, "thin_data_product_pct": self.thin_data_product_pct,
            "passing_75um_pct": float(self.product_psd.passing_at(0.075)),
            "held_below_mm": self.held_below_mm, "held_below_p80_mm": self.held_below_p80_mm,
            "held_below_passing_75um_pct": self.held_below_passing_75um_pct,
        })


#: the per-stage table as users read it (CLI summary, report): column -> (label, factor to the display unit)
STAGE_DISPLAY = {
    "stage": ("stage", 1),
    "holdup_t": ("hold-up (kg)", 1000.0),
    "p80_mm": ("P80 (mm)", 1.0),
    "primary_impacts_per_t": ("primary impacts per rock", 1.0),
    "secondary_impacts_per_t": ("secondary impacts per rock", 1.0),
    "impact_energy_kwh_t": ("impact energy (kWh/t feed)", 1.0),
    "flinger_energy_j_per_t": ("flinger energy (kJ/t feed)", 1e-3),
    "impact_kw": ("impact power (kW)", 1.0),
    "flinger_kw": ("flinger power (kW)", 1.0),
}


def stage_display(stages: pd.DataFrame) -> pd.DataFrame:
    """``stages`` (``MillResult.stages``, optionally merged with the power's per-stage kW) in display units and
    labels (:data:`STAGE_DISPLAY`: hold-up in kg, flinger energy in kJ/t), the columns it has, in that order."""
    cols = [c for c in STAGE_DISPLAY if c in stages.columns]
    out = pd.DataFrame({STAGE_DISPLAY[c][0]: stages[c].to_numpy() * STAGE_DISPLAY[c][1] for c in cols})
    out["stage"] = out["stage"].astype(int)
    return out


def display_number(value: float) -> str:
    """A figure as people read it: three significant digits, thousands whole with separators, '-' if not finite."""
    v = float(value)
    if not np.isfinite(v):
        return "-"
    return f"{v:,.0f}" if abs(v) >= 1000 else f"{v:.3g}"


def time_to_steady_state(time_s: np.ndarray, product_tph: np.ndarray, feed_tph: float,
                         tol: float = 0.01, holdup_t: np.ndarray | None = None,
                         criterion: SteadyStateCriterion | None = None) -> float:
    """Time to steady state (s) of a march from an empty mill.

    With ``holdup_t`` (t, same times): the onset by the DEM's criterion
    (:func:`msmill.steadystate.first_steady` on the hold-up and the cumulative
    product, the record starting empty at ``t = 0``), so model and DEM are
    comparable; NaN if never steady. Without it: the first time after which
    ``|product - feed| <= tol * feed`` holds for all later times (the strict
    test the Monte-Carlo warm-up uses).
    """
    if holdup_t is not None:
        t = np.concatenate([[0.0], np.asarray(time_s, dtype=float)])
        dt_h = np.diff(t) / 3600.0
        product_t = np.concatenate([[0.0], np.cumsum(np.asarray(product_tph, dtype=float) * dt_h)])
        held = np.concatenate([[0.0], np.asarray(holdup_t, dtype=float)])
        found = first_steady(t, held, product_t, feed_tph / 3600.0, criterion)
        return float("nan") if found is None else found[0]
    bad = np.abs(np.asarray(product_tph) - feed_tph) > tol * feed_tph
    if not bad.any():
        return float(time_s[0])
    last = int(np.flatnonzero(bad)[-1])
    if last + 1 >= len(time_s):
        return float("nan")
    return float(time_s[last + 1])


def with_band(result: MillResult, passing_pct: np.ndarray, p80_mm: np.ndarray) -> MillResult:
    """``result`` with a 5-95 % band from sampled product passing (n_samples, N) and P80 (mm).

    The band is the samples' 5 % and 95 % quantiles relative to their median,
    added to the result's own (full-resolution) passing and P80: the samples
    may be solved at a coarser resolution, whose bias cancels in the spread.
    Passing is clipped to 0-100 %.
    """
    import dataclasses

    q = np.percentile(passing_pct, [5.0, 50.0, 95.0], axis=0)
    own = result.psd_table["product_passing_pct"].to_numpy()
    lo_p = np.clip(own + q[0] - q[1], 0.0, 100.0)
    hi_p = np.clip(own + q[2] - q[1], 0.0, 100.0)
    band = pd.DataFrame({"product_passing_pct_p05": lo_p, "product_passing_pct_p50": own,
                         "product_passing_pct_p95": hi_p},
                        index=pd.Index(result.psd_table["upper_mm"].to_numpy(), name="upper_mm"))
    table = result.psd_table.copy()
    table["product_passing_pct_p05"] = lo_p
    table["product_passing_pct_p95"] = hi_p
    p05, p50, p95 = np.percentile(p80_mm, [5.0, 50.0, 95.0])
    p80_band = (float(result.p80_mm + p05 - p50), float(result.p80_mm + p95 - p50))
    return dataclasses.replace(result, p80_band_mm=p80_band, psd_band=band, psd_table=table,
                               band_samples=len(p80_mm))
