"""Power draw and flinger-wear indicators of a prediction (paper, Conclusions: future work).

What is computed (and what is assumed)
--------------------------------------
* **Impact power** (kW): the impact energy the model delivers to the rock per
  second, ``specific_impact_energy_kwh_t * feed_tph`` (kWh/t x t/h = kW),
  per stage and in total. Impact energy is ``v**2 / 2`` of the relative normal
  impact speed of every primary (rock-flinger) and secondary impact
  (``msmill.model`` outputs). It ignores the tangential (sliding) part of the
  impacts, the kinetic energy the product carries out of the mill, rock-rock
  friction, windage of the rotors and bearing losses.
* **No-load power** (kW): the power of the empty mill at speed (windage,
  bearings, drives). msmill does not model it: it is a **user-stated term**,
  0 kW unless given (from a measured idle run, or fitted to surveys with
  measured power by :func:`fit_no_load`). The result says which.
* **Drive efficiency**: the shaft power is divided by ``drive_efficiency``
  (default 1.0, i.e. shaft power; give the motor/drive efficiency for the
  electrical power).

So ``total_kw = (impact_kw + no_load_kw) / drive_efficiency``. Without a
measured no-load term this is a lower bound of the draw, not an estimate of it.

* **Flinger wear indicator** per stage: the primary (rock-on-flinger) impact
  energy per tonne of feed (J/t), ``MillResult.stages.flinger_energy_j_per_t``,
  and its rate in kW. It is an *indicator* proportional to the abrasive-impact
  work done on the flingers, not a wear rate in g/t: turning it into mass loss
  needs a measured wear coefficient of the flinger material, which msmill does
  not have.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from msmill.errors import MsmillInputError

__all__ = ["PowerEstimate", "fit_no_load", "power_estimate"]

J_PER_KWH = 3.6e6


@dataclass(frozen=True)
class PowerEstimate:
    """Power draw and wear indicators of one prediction.

    Attributes
    ----------
    impact_kw : float
        Impact energy delivered to the rock per second (kW).
    no_load_kw : float
        Stated no-load power (kW); 0 unless given.
    drive_efficiency : float
        Shaft-to-electrical efficiency used (1.0 = shaft power).
    total_kw : float
        ``(impact_kw + no_load_kw) / drive_efficiency`` (kW).
    specific_energy_kwh_t : float
        ``total_kw / feed_tph`` (kWh/t).
    stages : pandas.DataFrame
        Per stage: ``stage, impact_kw, flinger_kw, flinger_energy_j_per_t``.
    assumptions : tuple of str
        What the figures include and leave out.
    """

    impact_kw: float
    no_load_kw: float
    drive_efficiency: float
    total_kw: float
    specific_energy_kwh_t: float
    stages: pd.DataFrame
    assumptions: tuple[str, ...]

    def summary(self) -> pd.Series:
        """Headline figures (index names carry the units)."""
        return pd.Series({"impact_kw": self.impact_kw, "no_load_kw": self.no_load_kw,
                          "drive_efficiency": self.drive_efficiency, "total_kw": self.total_kw,
                          "specific_energy_kwh_t": self.specific_energy_kwh_t})


def power_estimate(result, no_load_kw: float = 0.0, drive_efficiency: float = 1.0,
                   no_load_source: str = "") -> PowerEstimate:
    """Power draw and flinger-wear indicators of a :class:`~msmill.model.MillResult`.

    Parameters
    ----------
    result : MillResult
        A prediction (steady state).
    no_load_kw : float
        No-load power (kW), >= 0; msmill does not model it (module docstring).
    drive_efficiency : float
        In (0, 1]; 1.0 gives shaft power.
    no_load_source : str
        Where ``no_load_kw`` comes from (reported).
    """
    if not (np.isfinite(no_load_kw) and no_load_kw >= 0):
        raise MsmillInputError("no_load_kw", no_load_kw, "a power >= 0 kW")
    if not (np.isfinite(drive_efficiency) and 0 < drive_efficiency <= 1):
        raise MsmillInputError("drive_efficiency", drive_efficiency, "a number in (0, 1]")
    st = result.stages
    feed = float(result.feed_tph)
    impact_stage_kw = st["impact_energy_kwh_t"].to_numpy() * feed
    flinger_kw = st["flinger_energy_j_per_t"].to_numpy() / J_PER_KWH * feed
    impact = float(impact_stage_kw.sum())
    total = (impact + no_load_kw) / drive_efficiency
    stages = pd.DataFrame({"stage": st["stage"].to_numpy(), "impact_kw": impact_stage_kw,
                           "flinger_kw": flinger_kw,
                           "flinger_energy_j_per_t": st["flinger_energy_j_per_t"].to_numpy()})
    notes = ["impact power = impact energy (v^2/2 of the normal impact speed) delivered per second; "
             "tangential work, product kinetic energy, windage and bearings are not included"]
    if no_load_kw > 0:
        notes.append(f"no-load power {no_load_kw:.3g} kW as stated" + (f" ({no_load_source})" if no_load_source else ""))
    else:
        notes.append("no-load power not modelled and not given (0 kW): the total is a lower bound")
    notes.append("drive efficiency 1.0 (shaft power)" if drive_efficiency == 1.0
                 else f"drive efficiency {drive_efficiency:g} as stated")
    notes.append("flinger wear indicator = primary impact energy on the flingers per tonne of feed; "
                 "a mass-loss rate needs a measured wear coefficient")
    return PowerEstimate(impact, float(no_load_kw), float(drive_efficiency), float(total),
                         float(total / feed), stages, tuple(notes))


def fit_no_load(impact_kw: np.ndarray, measured_kw: np.ndarray) -> tuple[float, float, float]:
    """Fit ``measured = no_load + slope * impact`` by least squares.

    Returns
    -------
    no_load_kw, slope, rmse_kw : float
        Intercept (kW), slope (dimensionless; 1 would mean the impact power is
        the whole load-dependent draw) and the residual RMS (kW).

    Raises
    ------
    MsmillInputError
        Fewer than 3 pairs, or impact powers all equal.
    """
    x = np.asarray(impact_kw, dtype=float)
    y = np.asarray(measured_kw, dtype=float)
    ok = np.isfinite(x) & np.isfinite(y)
    x, y = x[ok], y[ok]
    if x.size < 3 or np.ptp(x) <= 0:
        raise MsmillInputError("measured power", int(x.size), "at least 3 surveys with measured power "
                               "at different predicted impact powers")
    slope, icpt = np.polyfit(x, y, 1)
    rmse = float(np.sqrt(np.mean((y - (icpt + slope * x)) ** 2)))
    return float(icpt), float(slope), rmse
