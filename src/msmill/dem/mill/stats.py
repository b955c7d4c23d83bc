"""Per-stage impact and transport statistics of a mill DEM run.

Everything here works on plain tables (the engine's event, removal, time-series
and snapshot tables), so the statistics can be recomputed from saved raw data
(``msmill dem stats DIR``) and tested on hand-made tables. All work is
vectorised with numpy/pandas; there are no Python loops over particles or
contacts.

Definitions (see also ``docs/mill-dem.md`` and :mod:`msmill.stageparams`)
-------------------------------------------------------------------------
* **Stage of a point**: the band of :meth:`msmill.machine.Machine.stage_band_m`
  containing its height; ``0`` is the inlet zone above stage 1 and ``n + 1``
  is below the outlet plane (left the mill). Rock-flinger contacts are
  assigned to the stage of the flinger's rotor (``stage = group // 2 + 1``).
* **Pass**: a maximal run of a rock's time-ordered record (its contacts and
  its snapshot positions) spent in one stage. A pass ends when the rock is
  seen in another stage.
* **Primary impact**: the first contact of a rock with a flinger of a given
  rotor within one pass (so at most two per stage pass, one per rotor).
* **Secondary impacts** of a primary impact: the rock's later contacts (with
  liners, gates, deflectors, hubs, the chute, other rocks, or further
  flinger contacts) in the same pass, up to its next primary impact, with a
  relative normal speed of at least ``min_secondary_speed_m_s`` (0.5 m/s by
  default: slower touches are resting or rolling contacts that carry no
  breakage energy, ``E = v^2/2 < 0.125 J/kg``). A rock-rock contact counts for
  both rocks.
* **Characteristic time** ``tau``: stage spacing / mean centre speed, the
  mean of ``|v|`` over every rock inside the stages (1..n) in the
  measurement snapshots; rounded to a whole number of snapshot intervals.
* **Streams**: rocks in stage ``s`` at a snapshot time ``t`` (tags) are
  located at ``t + tau``: higher stage or inlet zone = kickback, same stage =
  refeed, lower stage or left through the outlet = pass-through. Mass weighted.
* **Destinations**: the same tagging, also of rocks in the inlet zone
  (compartment 0, everything above stage 1 including the feed chute), gives
  the mass fractions found at ``t + tau`` in each compartment ``0..n`` or
  left through the outlet (``n + 1``): the full one-lag transition matrix
  (jumps of more than one stage, the inlet zone's dwell).
* **Hit probability**: mass fraction of the tagged rocks of stage ``s`` that
  receive at least one primary impact from a stage-``s`` rotor within
  ``(t, t + tau]``.
* **Touches**: contacts recorded at ``vn <= 0`` (opened without approach,
  e.g. a rock resting between two surfaces) are not impacts and are removed
  before anything else; their number is reported in ``provenance["stats"]``.
* **Numerical blow-ups**: a rock with any contact at a non-finite speed or
  above ``3 x`` the fastest tip speed ``+ 20 m/s`` (impossible here; an
  engine failure) is dropped from all tables; the number is reported in
  ``provenance["stats"]``. Bound: a rock hit head-on again and again by
  plates at tip speed ``V`` approaches ``V (1 + e)/(1 - e)``, so no normal
  impact exceeds ``2 V/(1 - e)`` = 2.5 V at e = 0.2 (2.8 V at the 0.29 the
  engine's step realises at worst, ``docs/dem.md``); the engine faults this
  guards against gave 10^2-10^4 m/s.
* **Secondary counts**: the number of secondary impacts of each primary
  impact (in the window) is kept as a histogram and fitted by every count
  family of :class:`msmill.distributions.CountFamilySelection`; the family with
  the lowest ``StatsSettings.count_criterion`` (BIC) becomes
  ``secondary_count``, ``secondary_lambda`` is its mean.
* **Sampling errors**: standard errors by batch means: the tag times (or
  primary impacts, for the secondary counts; the impact times, for the mean
  velocities) are split into ``n_batches`` consecutive blocks, the statistic
  is computed per block and ``SE = std(blocks, ddof=1) / sqrt(n_batches)``.
  (Until 2026-12-02 the mean velocities had ``std / sqrt(n)``, which ignores
  that impacts come in clusters and understated their error.)
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd

from msmill.distributions import (
    EM_TOL,
    CountFamilySelection,
    GaussianMixtureKLFit,
    count_batch_stderr,
)
from msmill.errors import MsmillError, MsmillInputError
from msmill.machine import Machine
from msmill.sampling import (
    ERROR_ESTIMATORS,
    RUN_ERROR_ESTIMATOR,
    SamplingError,
    default_between_run,
    error_estimator,
    slice_sums,
    statistic_kind,
)
from msmill.stageparams import (
    FILLING_BINS,
    FILLING_MIN_TAGS,
    N_REGIONS,
    DesignPoint,
    FillingTags,
    FillingTransport,
    GaussianMixture,
    RunStatistics,
    StageStatistics,
    filling_curve_from_tags,
)


class DemStatisticsError(MsmillError, ValueError):
    """The recorded run cannot give statistics (e.g. no rock ever reached the stages)."""


__all__ = [
    "MillStatistics",
    "StatsSettings",
    "characteristic_time",
    "compute_statistics",
    "destination_matrix",
    "filling_tags",
    "filling_transport",
    "identify_impacts",
    "snapshot_lag",
    "snapshots_frame",
    "stage_of_z",
    "tagged_moves",
    "transition_matrix",
]

_PLACEHOLDER = GaussianMixture.single(0.0, 1e-3)  # used (with n = 0 and kl None) when a stage has no sample


@dataclass(frozen=True)
class StatsSettings:
    """Settings of the statistics.

    Parameters
    ----------
    min_secondary_speed_m_s : float
        Slowest contact counted as a secondary impact (m/s).
    k_max : int
        Largest number of Gaussian-mixture components (chosen by BIC).
    n_batches : int
        Batches for batch-means standard errors.
    min_fit_samples : int
        Fewer velocity samples than this: the mixture is a single Gaussian
        from the sample mean and standard deviation (KL still reported).
    count_criterion : {"bic", "aic"}
        Information criterion choosing the secondary-impact count family
        (:class:`msmill.distributions.CountFamilySelection`).
    with_filling_transport : bool
        Measure :func:`filling_transport` (one more pass over the whole record);
        the adaptive window's convergence checks, which need only the sampling
        errors, turn it off.
    velocity_fit : {"ml", "binned_kl"}
        How a velocity mixture is fitted once ``K`` is chosen by BIC:
        ``"ml"`` (default) keeps the maximum-likelihood (EM) fit, which
        minimises the KL divergence (paper Eq. 15) from the sample's empirical
        distribution; ``"binned_kl"`` refines it by the KL to the
        Freedman-Diaconis histogram. With few impacts the histogram has about
        as many bins (10 at 100 impacts) as a 4-component mixture has free
        parameters (11), so the binned refinement shrinks components onto
        single bins (sigmas at the quarter-bin floor, binned KL near 0): a fit
        of the sampling noise that no surrogate can, or should, predict.
    """

    min_secondary_speed_m_s: float = 0.5
    k_max: int = 4
    n_batches: int = 5
    min_fit_samples: int = 20
    count_criterion: str = "bic"
    velocity_fit: str = "ml"
    with_filling_transport: bool = True
    #: record each statistic's per-slice numerator and denominator over this many equal slices of the window
    #: (:attr:`MillStatistics.series`; 0: none), the input of every estimator of :mod:`msmill.sampling`
    series_slices: int = 64
    #: within-run estimator of the errors of the statistics with a series (a name of
    #: :data:`msmill.sampling.ERROR_ESTIMATORS`; ``"batch_means"``: ``n_batches`` batch means, the errors
    #: of runs before 2026-12-05). Issue 36: five batch means are too rough (4 dof) and miss what differs
    #: between runs; the autocorrelation time (about 50 dof at 64 slices) is the choice
    error_estimator: str = RUN_ERROR_ESTIMATOR
    #: add the between-run deviation (:func:`msmill.sampling.default_between_run`) to those errors: the part
    #: of the scatter between feed-seed replicas that no window shows (``benchmarks/error_calibration.py``)
    between_run: bool = True
    #: the contacts analysed start this long before the window (s; None: the whole record). A contact's
    #: label needs its rock's pass through the stage (a primary is the pass's first hit by a rotor), and
    #: passes are short; the record before them only costs memory: a fine-rock run has 10 million
    #: contacts per simulated second. A pass longer than this that spans the cut is taken from the cut
    #: on, and a rock that blew up before it is not dropped (provenance ``n_passes_from_event_cut``: the passes
    #: holding a counted primary that start within a snapshot interval of the cut, the only ones it can change)
    event_lookback_s: float | None = 0.5

    def event_cut_s(self, window_start_s: float) -> float | None:
        """The onset time (s) of the first contact the statistics of a window from ``window_start_s`` read."""
        return None if self.event_lookback_s is None else max(0.0, window_start_s - self.event_lookback_s)

    def __post_init__(self) -> None:
        if self.velocity_fit not in ("ml", "binned_kl"):
            raise MsmillInputError("velocity_fit", self.velocity_fit, "ml or binned_kl")
        if self.error_estimator not in ERROR_ESTIMATORS:
            raise MsmillInputError("error_estimator", self.error_estimator, ", ".join(sorted(ERROR_ESTIMATORS)))
        if self.error_estimator != "batch_means" and self.series_slices < 8:
            raise MsmillInputError("series_slices", self.series_slices,
                                   f"at least 8 with error_estimator {self.error_estimator} (or batch_means)")
        if self.event_lookback_s is not None and not self.event_lookback_s >= 0:
            raise MsmillInputError("event_lookback_s", self.event_lookback_s, "a time >= 0 s, or None for the whole record")


@dataclass
class MillStatistics:
    """Result of :func:`compute_statistics`: the schema object plus raw samples for plots."""

    run: RunStatistics
    samples: dict[int, dict[str, np.ndarray]] = field(default_factory=dict)
    fits: dict[int, dict[str, Any]] = field(default_factory=dict)
    streams_by_size: pd.DataFrame | None = None
    #: standard error of the window's mean hold-up over that mean (batch means of the time series; NaN: none)
    holdup_rel_se: float = float("nan")
    #: ``StatsSettings.series_slices > 0``: per statistic (``"s<stage>.<name>"``, ``"holdup"``) its ratio's
    #: per-slice ``num`` and ``den`` over equal slices of the window (``window_s``: the slices' span, s)
    series: dict[str, dict[str, Any]] | None = None


# --------------------------------------------------------------------------- basics
def stage_of_z(machine: Machine, z_m: np.ndarray) -> np.ndarray:
    """Stage index of each height: 0 inlet zone, 1..n stages, n + 1 below the outlet plane."""
    edges = np.asarray(machine.stage_edges_z_m())  # ascending, n + 1 values: 0, top of n, ..., top of 1
    k = np.searchsorted(edges, np.asarray(z_m, dtype=float), side="right")  # 0 below outlet .. n+1 inlet
    return (machine.n_stages + 1 - k).astype(np.int64)


def snapshots_frame(snapshots: list[tuple[float, pd.DataFrame]] | pd.DataFrame) -> pd.DataFrame:
    """Snapshots as one long table with ``time_s`` and ``snap`` (index) columns."""
    if isinstance(snapshots, pd.DataFrame):
        df = snapshots.copy()
        if "snap" not in df:
            df["snap"] = pd.factorize(df["time_s"], sort=True)[0]
        return df
    if not snapshots:
        return pd.DataFrame(columns=["time_s", "snap", "particle_id", "x_m", "y_m", "z_m",
                                     "vx_m_s", "vy_m_s", "vz_m_s", "radius_m"])
    parts = [d.assign(time_s=t, snap=i) for i, (t, d) in enumerate(snapshots)]
    return pd.concat(parts, ignore_index=True)


def characteristic_time(
    machine: Machine, snaps: pd.DataFrame, snapshot_interval_s: float | None = None
) -> tuple[float, float]:
    """``(tau_s, mean_centre_speed_m_s)``: stage spacing / mean centre speed of rocks in the stages.

    ``tau`` is rounded to a whole number (>= 1) of ``snapshot_interval_s`` if given.
    """
    st = stage_of_z(machine, snaps["z_m"].to_numpy())
    inside = (st >= 1) & (st <= machine.n_stages)
    v = np.sqrt(snaps["vx_m_s"] ** 2 + snaps["vy_m_s"] ** 2 + snaps["vz_m_s"] ** 2).to_numpy()[inside]
    if v.size == 0 or not np.isfinite(v.mean()) or v.mean() <= 0:
        raise DemStatisticsError("no moving rocks inside the stages in the measurement window: cannot compute "
                                 "the characteristic time (was the run long enough for rock to reach the stages?)")
    speed = float(v.mean())
    tau = machine.stage_spacing_m / speed
    if snapshot_interval_s:
        tau = max(1, round(tau / snapshot_interval_s)) * snapshot_interval_s
    return float(tau), speed


# --------------------------------------------------------------------------- impacts
def _events_by_particle(events: pd.DataFrame) -> pd.DataFrame:
    """One row per (rock, contact): rock-rock contacts appear once for each rock."""
    cols = ["time_s", "particle_id", "partner_kind", "partner_id", "vn_m_s", "z_m", "partner_tag", "partner_group"]
    ev = events.loc[:, [c for c in cols if c in events]].copy()
    if "partner_tag" not in ev:
        ev["partner_tag"] = np.where(ev["partner_kind"] == 0, "particle", "")
    if "partner_group" not in ev:
        ev["partner_group"] = -1
    pp = ev[ev["partner_kind"] == 0]
    mirror = pp.rename(columns={"particle_id": "partner_id", "partner_id": "particle_id"})
    out = pd.concat([ev, mirror[ev.columns]], ignore_index=True)
    out["partner_tag"] = out["partner_tag"].where(out["partner_kind"] != 0, "particle")
    out["particle_id"] = out["particle_id"].astype(np.int64)
    return out


def identify_impacts(machine: Machine, events: pd.DataFrame, snaps: pd.DataFrame) -> pd.DataFrame:
    """Label every contact of every rock as primary / secondary (see module docstring).

    Returns
    -------
    DataFrame
        Per-rock contact table, sorted by rock and time, with columns
        ``stage`` (of the contact), ``pass_id``, ``is_primary``, ``primary_row``
        (row of the primary impact this contact follows in the same pass, -1
        if none) and ``rotor`` (flinger contacts: rotor index, else -1).
    """
    ev = _events_by_particle(events)
    is_fl = (ev["partner_kind"].to_numpy() != 0) & (ev["partner_tag"].to_numpy() == "flinger")
    grp = ev["partner_group"].fillna(-1).to_numpy().astype(np.int64)
    stage = np.where(is_fl, grp // 2 + 1, stage_of_z(machine, ev["z_m"].to_numpy()))
    ev = ev.assign(stage=stage, rotor=np.where(is_fl, grp, -1), is_flinger=is_fl)
    # one time line per rock, snapshots before contacts at equal times: sort keys only (numpy, stable),
    # then take the contacts in that order
    n_sn = len(snaps)
    sn_pid = snaps["particle_id"].to_numpy().astype(np.int64) if n_sn else np.zeros(0, np.int64)
    sn_t = snaps["time_s"].to_numpy(dtype=float) if n_sn else np.zeros(0)
    sn_stage = stage_of_z(machine, snaps["z_m"].to_numpy()) if n_sn else np.zeros(0, stage.dtype)
    pid = np.concatenate([sn_pid, ev["particle_id"].to_numpy().astype(np.int64)])
    t = np.concatenate([sn_t, ev["time_s"].to_numpy(dtype=float)])
    st = np.concatenate([sn_stage, stage])
    is_ev = np.arange(pid.size) >= n_sn
    order = np.lexsort((is_ev, t, pid))
    pid, st = pid[order], st[order]
    new_pass = np.ones(pid.size, dtype=bool)
    new_pass[1:] = (pid[1:] != pid[:-1]) | (st[1:] != st[:-1])
    pass_id = np.cumsum(new_pass)
    rows = is_ev[order]
    ev = ev.take(order[rows] - n_sn).reset_index(drop=True)
    ev["pass_id"] = pass_id[rows]
    fl = ev["is_flinger"].to_numpy()
    first = ~ev.duplicated(["pass_id", "rotor"])
    is_primary = fl & first.to_numpy()
    ev["is_primary"] = is_primary
    idx = np.arange(len(ev))
    last_primary = np.maximum.accumulate(np.where(is_primary, idx, -1)) if len(ev) else idx
    ok = last_primary >= 0
    lp = np.where(ok, last_primary, 0)
    same = ok & (ev["particle_id"].to_numpy()[lp] == ev["particle_id"].to_numpy()) & (
        ev["pass_id"].to_numpy()[lp] == ev["pass_id"].to_numpy()
    )
    ev["primary_row"] = np.where(same & ~is_primary, last_primary, -1)
    return ev


# --------------------------------------------------------------------------- streams
def _tag_pairs(
    machine: Machine, snaps: pd.DataFrame, removed: pd.DataFrame, times: np.ndarray, lag: int,
    rock_density_kg_m3: float, first_stage: int = 1,
) -> pd.DataFrame:
    """Tagged rocks (stage ``first_stage``..n at snapshot ``i``) with the stage they are in at ``i + lag``.

    ``first_stage = 0`` tags the inlet zone too (``destinations``).

    ``times`` are the sorted snapshot times of the window; columns of the
    result: ``time_s`` (tag time), ``t_to`` (time of snapshot ``i + lag``),
    ``particle_id``, ``y_m``, ``radius_m``, ``stage_from``, ``stage_to``,
    ``mass_kg``, ``category`` (0 kickback, 1 refeed, 2 pass-through). Rocks
    missing from the later snapshot were removed: by the outlet sink
    (``stage_to = n + 1``) or otherwise (lost: ``stage_to = 0``).
    """
    n = machine.n_stages
    idx = {t: i for i, t in enumerate(times)}
    sidx = snaps["time_s"].map(idx)
    snaps = snaps.assign(i=sidx.to_numpy())
    snaps = snaps[snaps["i"].notna()].astype({"i": np.int64})
    a = snaps[snaps["i"] + lag < times.size][["i", "time_s", "particle_id", "y_m", "z_m", "radius_m"]].copy()
    a["stage_from"] = stage_of_z(machine, a["z_m"].to_numpy())
    a = a[(a["stage_from"] >= first_stage) & (a["stage_from"] <= n)]
    a["i_to"] = a["i"] + lag
    a["t_to"] = times[a["i_to"].to_numpy()]
    b = snaps[snaps["i"] >= lag][["i", "particle_id", "z_m"]].rename(columns={"i": "i_to", "z_m": "z_to"})
    m = a.merge(b, on=["i_to", "particle_id"], how="left")
    m["stage_to"] = stage_of_z(machine, m["z_to"].fillna(0.0).to_numpy())
    missing = m["z_to"].isna().to_numpy()
    if missing.any():
        rem = removed[["particle_id", "time_s"] + (["tag"] if "tag" in removed else [])].rename(
            columns={"time_s": "t_removed"})
        mm = m.loc[missing, ["particle_id", "t_to"]].merge(rem, on="particle_id", how="left")
        t_rem = pd.to_numeric(mm["t_removed"], errors="coerce").to_numpy(dtype=float)
        gone = np.nan_to_num(t_rem, nan=np.inf) <= mm["t_to"].to_numpy(dtype=float) + 1e-12
        tag = mm["tag"].astype(str).to_numpy() if "tag" in mm else np.full(len(mm), "outlet")
        st_to = np.where(~gone, -1, np.where(tag == "outlet", n + 1, 0))
        m.loc[missing, "stage_to"] = st_to
    m = m[m["stage_to"] >= 0].copy()
    m["mass_kg"] = rock_density_kg_m3 * 4.0 / 3.0 * np.pi * m["radius_m"].to_numpy() ** 3
    m["category"] = np.select(
        [m["stage_to"] < m["stage_from"], m["stage_to"] == m["stage_from"]], [0, 1], default=2)
    return m.drop(columns=["z_m", "z_to", "i", "i_to"])


def _streams(pairs: pd.DataFrame, keys: list[str]) -> pd.DataFrame:
    """Mass fractions kickback / refeed / pass_through grouped by ``keys``."""
    w = pairs.pivot_table(index=keys, columns="category", values="mass_kg", aggfunc="sum", fill_value=0.0)
    w = w.reindex(columns=[0, 1, 2], fill_value=0.0)
    tot = w.sum(axis=1)
    f = w.div(tot, axis=0)
    f.columns = ["kickback", "refeed", "pass_through"]
    f["mass_kg"] = tot
    return f


def _destinations(pairs: pd.DataFrame, n: int) -> dict[int, list[float]]:
    """Mass fractions of the rock tagged in compartment ``c`` (0..n) found in ``0..n+1`` one lag later."""
    if not len(pairs):
        return {}
    w = pairs.pivot_table(index="stage_from", columns="stage_to", values="mass_kg", aggfunc="sum", fill_value=0.0)
    w = w.reindex(columns=range(n + 2), fill_value=0.0)
    f = w.div(w.sum(axis=1), axis=0)
    return {int(c): [float(v) for v in f.loc[c].to_numpy()] for c in f.index}


def transition_matrix(
    machine: Machine, snapshots: list[tuple[float, pd.DataFrame]] | pd.DataFrame, removed: pd.DataFrame,
    window_s: tuple[float, float], lag: int, rock_density_kg_m3: float = 2700.0,
) -> np.ndarray:
    """Mass-weighted transition matrix at ``lag`` snapshot intervals, tags in ``window_s``.

    Row ``c`` (0 = inlet zone, 1..n stages): fractions of the rock in ``c`` at a
    snapshot time in the window found ``lag`` snapshots later in ``0..n`` or
    gone through the outlet (``n + 1``); shape ``(n + 1, n + 2)``, rows of
    compartments without tags are NaN. The later snapshots may lie beyond the
    window. With the lag of ``tau`` these are the ``destinations``; at
    ``k tau`` they test whether the one-lag transport is Markov
    (``P(k tau) = P(tau)^k``).
    """
    pairs = tagged_moves(machine, snapshots, removed, lag, rock_density_kg_m3)
    pairs = pairs[(pairs["time_s"] >= window_s[0] - 1e-9) & (pairs["time_s"] <= window_s[1] + 1e-9)]
    return destination_matrix(pairs, machine.n_stages)


def tagged_moves(
    machine: Machine, snapshots: list[tuple[float, pd.DataFrame]] | pd.DataFrame, removed: pd.DataFrame,
    lag: int, rock_density_kg_m3: float = 2700.0,
) -> pd.DataFrame:
    """Every rock in the inlet zone or a stage at every snapshot, with its compartment ``lag`` snapshots later.

    Columns ``time_s`` (tag time), ``t_to``, ``particle_id``, ``stage_from``
    (0 inlet zone, 1..n), ``stage_to`` (0..n, ``n + 1`` out through the
    outlet), ``mass_kg`` (and ``y_m``, ``radius_m``, ``category``). The whole
    record, not only a measurement window: :func:`transition_matrix` selects
    the window's tags, studies of the filling mill select others.
    """
    snaps = snapshots_frame(snapshots)
    times = np.sort(snaps["time_s"].unique())
    return _tag_pairs(machine, snaps, removed, times, lag, rock_density_kg_m3, first_stage=0)


def slot_streams(
    machine: Machine, snapshots: list[tuple[float, pd.DataFrame]] | pd.DataFrame, removed: pd.DataFrame,
    lag: int, slot_s: float = 0.2, rock_density_kg_m3: float = 2700.0,
) -> pd.DataFrame:
    """Streams and hold-up of every compartment in consecutive slots of the whole record: how a run settles.

    The tagged moves (:func:`tagged_moves`, ``lag`` snapshots) grouped by the slot ``floor(time / slot_s)``
    of their tag time give each compartment's kickback, refeed and pass-through in that slot (the inlet
    zone has no kickback); the hold-up is the compartment's mass averaged over the slot's snapshots.
    ``docs/mill-dem.md`` (Section 3.2) reads the settle time after a table start off this table.

    Returns
    -------
    pandas.DataFrame
        One row per slot and compartment: ``slot_start_s``, ``stage`` (0 inlet zone, 1..n),
        ``kickback``, ``refeed``, ``pass_through``, ``tagged_kg`` (mass the fractions rest on) and
        ``holdup_kg``.
    """
    if not slot_s > 0:
        raise MsmillInputError("slot_s", slot_s, "a slot length > 0 (s)")
    snaps = snapshots_frame(snapshots)
    pairs = tagged_moves(machine, snaps, removed, lag, rock_density_kg_m3)
    pairs = pairs.assign(slot=np.floor(pairs["time_s"].to_numpy() / slot_s + 1e-9).astype(np.int64))
    streams = _streams(pairs, ["slot", "stage_from"]).rename(columns={"mass_kg": "tagged_kg"})
    streams.index = streams.index.set_names(["slot", "stage"])
    comp = stage_of_z(machine, snaps["z_m"].to_numpy())
    mass = rock_density_kg_m3 * 4.0 / 3.0 * np.pi * snaps["radius_m"].to_numpy() ** 3
    inside = comp <= machine.n_stages
    per_snap = (pd.DataFrame({"time_s": snaps["time_s"].to_numpy()[inside], "stage": comp[inside],
                              "mass_kg": mass[inside]})
                .pivot_table(index="time_s", columns="stage", values="mass_kg", aggfunc="sum", fill_value=0.0)
                .reindex(columns=range(machine.n_stages + 1), fill_value=0.0))
    slot = np.floor(per_snap.index.to_numpy() / slot_s + 1e-9).astype(np.int64)
    hold = per_snap.groupby(slot).mean().stack().rename("holdup_kg")
    hold.index = hold.index.set_names(["slot", "stage"])
    out = streams.join(hold, how="outer").reset_index()
    out.insert(0, "slot_start_s", out.pop("slot") * slot_s)
    return out.sort_values(["slot_start_s", "stage"], ignore_index=True)


def destination_matrix(pairs: pd.DataFrame, n_stages: int) -> np.ndarray:
    """Mass-weighted destinations ``(n + 1, n + 2)`` of tagged moves (:func:`tagged_moves`); NaN rows untagged."""
    out = np.full((n_stages + 1, n_stages + 2), np.nan)
    for c, row in _destinations(pairs, n_stages).items():
        out[c] = row
    return out


#: Width and upper end of the fine fill bins of :func:`filling_tags` (shares of the run's window hold-up).
FILLING_TAG_BIN = 0.05
FILLING_TAG_MAX = 1.5


def filling_tags(
    machine: Machine, snapshots: list[tuple[float, pd.DataFrame]] | pd.DataFrame, removed: pd.DataFrame,
    window_s: tuple[float, float], lag: int, rock_density_kg_m3: float = 2700.0,
    bin_width: float = FILLING_TAG_BIN, max_fill: float = FILLING_TAG_MAX, moves: pd.DataFrame | None = None,
) -> FillingTags | None:
    """The tags taken before the measurement window, binned finely by the mill's fill (None: none).

    The mill's fill at a snapshot is its hold-up (inlet zone and stages) over the
    window's mean. Tags (:func:`tagged_moves`, ``lag`` snapshot intervals) taken
    before the window are binned by the fill at their tag time (bins of
    ``bin_width`` up to ``max_fill``: runs of one point pool on a reference other
    than their own window's); per bin, the tagged mass by compartment and
    destination and the number of tags by compartment
    (:class:`msmill.stageparams.FillingTags`). ``moves``: the record's
    :func:`tagged_moves` at ``lag`` if already computed.
    """
    snaps = snapshots_frame(snapshots)
    n = machine.n_stages
    t0, t1 = map(float, window_s)
    c = stage_of_z(machine, snaps["z_m"].to_numpy())
    inside = (c >= 0) & (c <= n)
    mass = rock_density_kg_m3 * 4.0 / 3.0 * np.pi * snaps["radius_m"].to_numpy() ** 3
    held = pd.Series(mass * inside).groupby(snaps["time_s"].to_numpy()).sum()
    in_win = (held.index >= t0 - 1e-9) & (held.index <= t1 + 1e-9)
    if not in_win.any() or held[in_win].mean() <= 0 or held.index.min() >= t0 - 1e-9:
        return None
    times = held.index.to_numpy()
    fill = held / held[in_win].mean()
    if moves is None:
        moves = tagged_moves(machine, snaps, removed, lag, rock_density_kg_m3)
    moves = moves[moves["time_s"].to_numpy() < t0 - 1e-9]
    h = moves["time_s"].map(fill).to_numpy()
    k = np.floor(h / bin_width).astype(int)
    keep = h < max_fill
    if not keep.any():
        return None
    k, h = k[keep], h[keep]
    frm, to = moves["stage_from"].to_numpy()[keep], moves["stage_to"].to_numpy()[keep]
    w = moves["mass_kg"].to_numpy()[keep]
    used, b = np.unique(k, return_inverse=True)
    dest = np.zeros((used.size, n + 1, n + 2))
    np.add.at(dest, (b, frm, to), w)
    count = np.zeros((used.size, n + 1), dtype=int)
    np.add.at(count, (b, frm), 1)
    fill_b = np.bincount(b, weights=w * h) / np.bincount(b, weights=w)
    return FillingTags(lag_s=float(lag * np.median(np.diff(times))), window_holdup_kg=float(held[in_win].mean()),
                       fill=fill_b.tolist(), destination_kg=dest.tolist(), tag_count=count.tolist())


def filling_transport(
    machine: Machine, snapshots: list[tuple[float, pd.DataFrame]] | pd.DataFrame, removed: pd.DataFrame,
    window_s: tuple[float, float], lag: int, rock_density_kg_m3: float = 2700.0,
    bins: tuple[float, ...] = FILLING_BINS,
) -> FillingTransport | None:
    """How fast the one-lag transport runs while the mill fills, by the mill's fill (None: no tags before the window).

    The run's own tags (:func:`filling_tags`) against its own window
    (:func:`msmill.stageparams.filling_curve_from_tags`): tags taken before the
    window binned by the fill at their tag time; in each bin, every compartment
    with at least :data:`FILLING_MIN_TAGS` tags gets its bin destinations, the
    others keep the window's. ``residence_ratio`` is that chain's mean residence
    (:func:`chain_residence_steps`) over the window chain's; bins whose chain
    never empties are left out. ``lag_s`` is ``lag`` snapshot intervals.
    """
    snaps = snapshots_frame(snapshots)
    moves = tagged_moves(machine, snaps, removed, lag, rock_density_kg_m3)
    tags = filling_tags(machine, snaps, removed, window_s, lag, rock_density_kg_m3, moves=moves)
    if tags is None:
        return None
    t = moves["time_s"].to_numpy()
    steady = destination_matrix(moves[(t >= window_s[0] - 1e-9) & (t <= window_s[1] + 1e-9)], machine.n_stages)
    if not np.isfinite(steady).all():
        return None
    return filling_curve_from_tags([tags], (tags.window_holdup_kg, steady), bins=bins, min_tags=FILLING_MIN_TAGS)



def _batch_se(values: np.ndarray) -> float:
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]
    if v.size < 2:
        return float("nan")
    return float(v.std(ddof=1) / np.sqrt(v.size))


# --------------------------------------------------------------------------- main entry
def compute_statistics(
    machine: Machine,
    design: DesignPoint,
    events: pd.DataFrame,
    removed: pd.DataFrame,
    timeseries: pd.DataFrame,
    snapshots: list[tuple[float, pd.DataFrame]] | pd.DataFrame,
    window_s: tuple[float, float],
    mode: str = "slice",
    rock_density_kg_m3: float = 2700.0,
    characteristic_time_s: float | None = None,
    steady_state_time_s: float | None = None,
    settings: StatsSettings | None = None,
    size_edges_m: np.ndarray | None = None,
    provenance: dict[str, Any] | None = None,
) -> MillStatistics:
    """Per-stage statistics of one run over the measurement window.

    Parameters
    ----------
    machine : Machine
        Geometry (stage bands, rotor numbering).
    design : DesignPoint
        Operating point of the run.
    events, removed, timeseries : DataFrame
        Engine tables (``Simulation.events()``, ``removed()``, ``timeseries()``).
    snapshots : list of (time_s, DataFrame) or DataFrame
        Particle snapshots, regularly spaced, covering the window.
    window_s : (float, float)
        Measurement window ``(t0, t1)`` (s).
    mode : {"slice", "full"}
        Full mode adds the horizontal (6-region) statistics.
    rock_density_kg_m3 : float
        Rock density (for masses from radii).
    characteristic_time_s : float, optional
        Force ``tau`` instead of computing it.
    steady_state_time_s : float, optional
        Stored in the result.
    settings : StatsSettings, optional
    size_edges_m : array, optional
        Radius-class edges (m) for streams per size class (PSD feeds).
    provenance : dict, optional
        Stored in ``RunStatistics.provenance``.
    """
    s_ = settings or StatsSettings()
    t0, t1 = map(float, window_s)
    cut_s = s_.event_cut_s(t0)
    if cut_s is not None and len(events) and float(events["time_s"].iloc[0]) < cut_s:
        events = events[events["time_s"].to_numpy() >= cut_s]
    clean = _drop_blow_ups(machine, design, events, removed, snapshots_frame(snapshots))
    snaps = clean.snapshots[(clean.snapshots["time_s"] >= t0 - 1e-9) & (clean.snapshots["time_s"] <= t1 + 1e-9)]
    clock = _tag_clock(machine, snaps, characteristic_time_s)
    tr = _transport(machine, snaps, clean.removed, clock, rock_density_kg_m3, s_.n_batches)
    ev = identify_impacts(machine, clean.events, clean.snapshots)
    prim = ev[ev["is_primary"]]
    hits, hits_b, hit_tags = _hit_probabilities(tr.pairs, prim)
    counts = _secondary_counts(ev, (t0, t1), clock.tau_s, s_)
    region_streams = _region_streams(machine, snaps, tr.pairs) if mode == "full" and len(tr.pairs) else None
    holdup = snaps.assign(stage=stage_of_z(machine, snaps["z_m"].to_numpy()),
                          m=rock_density_kg_m3 * 4 / 3 * np.pi * snaps["radius_m"].to_numpy() ** 3)
    holdup_kg = holdup.groupby("stage")["m"].sum() / max(clock.times.size, 1)

    stages: list[StageStatistics] = []
    samples: dict[int, dict[str, np.ndarray]] = {}
    fits: dict[int, dict[str, Any]] = {}
    for s in range(1, machine.n_stages + 1):
        st, samples[s], fits[s] = _stage_statistics(s, tr, hits, hits_b, prim, counts, (t0, t1), s_,
                                                     region_streams, float(holdup_kg.get(s, 0.0)))
        stages.append(st)

    # ---- run level
    out_rate, hold_total, hold_rel_se = _outflow(clean.removed, timeseries, (t0, t1), rock_density_kg_m3, holdup_kg,
                                                 s_.n_batches)
    prov = dict(provenance or {})
    prov.setdefault("stats", {}).update({
        "min_secondary_speed_m_s": s_.min_secondary_speed_m_s, "k_max": s_.k_max, "n_batches": s_.n_batches,
        "count_criterion": s_.count_criterion, "velocity_fit": s_.velocity_fit,
        "velocity_em_tol": EM_TOL,
        "n_tag_times": int(clock.tag_times.size), "snapshot_interval_s": clock.interval_s,
        "mean_holdup_kg": hold_total, "holdup_rel_se": hold_rel_se if np.isfinite(hold_rel_se) else None,
        "blow_up_speed_limit_m_s": clean.speed_limit_m_s,
        "n_rocks_dropped_as_blow_ups": clean.n_rocks_dropped, "n_events_blow_up": clean.n_events_blow_up,
        "n_touch_events_vn_le_0": clean.n_touch,
        "event_cut_s": cut_s, "n_passes_from_event_cut": _passes_from_cut(ev, counts, cut_s, clock.interval_s),
    })
    by_size = None
    if size_edges_m is not None and len(tr.pairs):
        pairs = tr.pairs
        pairs["size_class"] = np.searchsorted(np.asarray(size_edges_m), pairs["radius_m"].to_numpy(), side="right") - 1
        by_size = _streams(pairs, ["stage_from", "size_class"]).reset_index()
        prov["streams_by_size"] = by_size.to_dict(orient="records")
    run = RunStatistics(
        design=design, mode="full" if mode == "full" else "slice", characteristic_time_s=clock.tau_s, stages=stages,
        steady_state_time_s=steady_state_time_s, measurement_window_s=t1 - t0,
        mass_out_rate_kg_s=out_rate, residence_time_s=hold_total / out_rate if out_rate > 0 else None,
        mean_centre_velocity_m_s=clock.speed_m_s, inlet_destinations=tr.destinations.get(0),
        inlet_holdup_kg=float(holdup_kg.get(0, 0.0)), provenance=prov,
        filling_transport=(filling_transport(machine, clean.snapshots, clean.removed, (t0, t1), clock.lag,
                                             rock_density_kg_m3) if s_.with_filling_transport else None),
    )
    series = (_slice_series(machine.n_stages, tr.pairs, hit_tags, prim, ev, counts, timeseries, (t0, t1), clock.tau_s,
                            s_.series_slices) if s_.series_slices > 0 else None)
    if series is not None and s_.error_estimator != "batch_means":
        stages, hold_rel_se, within = _series_errors(run.stages, series, design.size_mm, s_)
        prov["stats"].update({"error_estimator": s_.error_estimator, "between_run": s_.between_run,
                              "series_slices": s_.series_slices, "sampling_error_within": within,
                              "holdup_rel_se": hold_rel_se if np.isfinite(hold_rel_se) else None})
        run = run.model_copy(update={"stages": stages, "provenance": prov})
    return MillStatistics(run=run, samples=samples, fits=fits, streams_by_size=by_size, holdup_rel_se=hold_rel_se,
                          series=series)


def _slice_series(n_stages: int, pairs: pd.DataFrame, hit_tags: pd.DataFrame, prim: pd.DataFrame, ev: pd.DataFrame,
                  counts: _Counts, timeseries: pd.DataFrame, window_s: tuple[float, float], tau_s: float,
                  n: int) -> dict[str, dict[str, Any]]:
    """Every statistic's ratio as per-slice numerator and denominator (:attr:`MillStatistics.series`).

    Streams and hit probability: tagged mass going each way (hit) over tagged mass, by tag time; velocity
    means: speeds over impacts, by impact time; count mean: secondary impacts over primaries, by the
    primary's time in the window's counted part ``(t0, t1 - tau)``; hold-up: mass over samples of the
    time series.
    """
    def pack(span: tuple[float, float], t: np.ndarray, num_w: np.ndarray, den_w: np.ndarray | float) -> dict:
        return {"window_s": [float(span[0]), float(span[1])],
                "num": slice_sums(t, num_w, span, n).tolist(), "den": slice_sums(t, den_w, span, n).tolist()}

    t0, t1 = window_s
    out: dict[str, dict[str, Any]] = {}
    counted = (t0, max(t1 - tau_s, t0 + 1e-9))
    for s in range(1, n_stages + 1):
        p = pairs[pairs["stage_from"] == s] if len(pairs) else pairs
        if len(p):
            t, m, cat = p["time_s"].to_numpy(), p["mass_kg"].to_numpy(), p["category"].to_numpy()
            for k, name in enumerate(("kickback", "refeed", "pass_through")):
                out[f"s{s}.{name}"] = pack(window_s, t, m * (cat == k), m)
        h = hit_tags[hit_tags["stage"] == s] if len(hit_tags) else hit_tags
        if len(h):
            out[f"s{s}.primary_hit_probability"] = pack(window_s, h["time_s"].to_numpy(), h["mh"].to_numpy(),
                                                        h["mass_kg"].to_numpy())
        sp = prim["stage"].to_numpy() == s
        out[f"s{s}.primary_velocity_mean_m_s"] = pack(window_s, prim["time_s"].to_numpy()[sp],
                                                      prim["vn_m_s"].to_numpy()[sp], 1.0)
        rows = counts.sec_rows[counts.sec_stage == s]
        out[f"s{s}.secondary_velocity_mean_m_s"] = pack(window_s, counts.time_s[rows], counts.vn_m_s[rows], 1.0)
        pr = counts.pr_rows[counts.pr_stage == s]
        out[f"s{s}.secondary_lambda"] = pack(counted, counts.time_s[pr], counts.counts_all[pr], 1.0)
    if len(timeseries):
        out["holdup"] = pack(window_s, timeseries["time_s"].to_numpy(), timeseries["mass_kg"].to_numpy(), 1.0)
    return out


def _series_errors(stages: list[StageStatistics], series: dict[str, dict[str, Any]], size_mm: float,
                   s_: StatsSettings) -> tuple[list[StageStatistics], float, dict[str, list[float]]]:
    """Errors of the statistics with a series: ``s_.error_estimator`` within the run, plus the between-run
    deviation (``s_.between_run``); the stages with them, the hold-up's relative error and the within parts.

    ``within[name] = [se, dof]`` (``name`` as in ``series``).
    """
    est = error_estimator(s_.error_estimator)
    between = default_between_run() if s_.between_run else None
    within: dict[str, list[float]] = {}
    total: dict[str, SamplingError] = {}
    for name, sr in series.items():
        num, den = np.asarray(sr["num"], dtype=float), np.asarray(sr["den"], dtype=float)
        if not den.sum() > 0:
            continue
        e = est.standard_error(num, den)
        if not np.isfinite(e.se):
            continue
        within[name] = [e.se, e.dof]
        total[name] = between.total(statistic_kind(name), size_mm, num.sum() / den.sum(), e) if between else e
    out = []
    for st in stages:
        prefix = f"s{st.stage}."
        se = dict(st.sampling_error)
        se.update({k[len(prefix):]: v.se for k, v in total.items() if k.startswith(prefix)})
        out.append(st.model_copy(update={"sampling_error": se}))
    h = series.get("holdup")
    rel = (total["holdup"].se / (float(np.sum(h["num"])) / float(np.sum(h["den"])))
           if h is not None and "holdup" in total else float("nan"))
    return out, rel, within


@dataclass(frozen=True)
class _Clean:
    """The engine's tables without touches and without rocks that blew up (and what was dropped)."""

    events: pd.DataFrame
    removed: pd.DataFrame
    snapshots: pd.DataFrame
    speed_limit_m_s: float
    n_rocks_dropped: int
    n_events_blow_up: int
    n_touch: int


def _drop_blow_ups(machine: Machine, design: DesignPoint, events: pd.DataFrame, removed: pd.DataFrame,
                   snaps: pd.DataFrame) -> _Clean:
    """Drop touches (contacts opened at ``vn <= 0``) and every trace of rocks with an impossible contact speed.

    A contact at a non-finite speed or faster than 3 x the fastest tip speed +
    20 m/s is a numerical blow-up of the engine (module docstring): such rocks
    leave every table, and are counted in the provenance.
    """
    vn_all = events["vn_m_s"].to_numpy(dtype=float)
    touch = np.isfinite(vn_all) & (vn_all <= 0)
    events = events[~touch]
    vn_all = vn_all[~touch]
    v_bad = 3.0 * max(machine.tip_speed_m_s(v) for v in design.stage_speeds_rpm) + 20.0
    bad_ev = ~np.isfinite(vn_all) | (vn_all > v_bad)
    bad_ids = np.unique(np.concatenate([
        events["particle_id"].to_numpy()[bad_ev],
        events["partner_id"].to_numpy()[bad_ev & (events["partner_kind"].to_numpy() == 0)],
    ]))
    if bad_ids.size:
        events = events[~events["particle_id"].isin(bad_ids)
                        & ~((events["partner_kind"] == 0) & events["partner_id"].isin(bad_ids))]
        snaps = snaps[~snaps["particle_id"].isin(bad_ids)]
        removed = removed[~removed["particle_id"].isin(bad_ids)]
    return _Clean(events, removed, snaps, v_bad, int(bad_ids.size), int(bad_ev.sum()), int(touch.sum()))


@dataclass(frozen=True)
class _Clock:
    """Snapshot times of the window, ``tau`` as a whole number (``lag``) of snapshot intervals, tag times."""

    times: np.ndarray
    interval_s: float | None
    tau_s: float
    speed_m_s: float
    lag: int
    tag_times: np.ndarray


def snapshot_lag(times_s: np.ndarray, lag_s: float) -> int:
    """A lag of ``lag_s`` seconds in whole snapshot intervals (the median spacing of ``times_s``), at least one."""
    return max(1, round(float(lag_s) / float(np.median(np.diff(np.sort(np.unique(times_s)))))))


def _tag_clock(machine: Machine, snaps: pd.DataFrame, characteristic_time_s: float | None) -> _Clock:
    """The window's clock: tags at snapshot ``i`` are located at snapshot ``i + lag``."""
    times = np.sort(snaps["time_s"].unique())
    interval = float(np.median(np.diff(times))) if times.size > 1 else None
    if characteristic_time_s is None:
        tau, speed = characteristic_time(machine, snaps, None)
    else:
        tau = float(characteristic_time_s)
        speed = machine.stage_spacing_m / tau
    lag = snapshot_lag(times, tau) if interval else 1
    if interval:
        tau = lag * interval
    return _Clock(times, interval, tau, speed, lag, times[: max(times.size - lag, 0)])


@dataclass(frozen=True)
class _Transport:
    """Tagged moves (stages 1..n, with their batch), one-lag destinations (inlet zone too), streams."""

    pairs: pd.DataFrame
    destinations: dict[int, list[float]]
    streams: pd.DataFrame | None
    batch_streams: pd.DataFrame | None


def _transport(machine: Machine, snaps: pd.DataFrame, removed: pd.DataFrame, clock: _Clock,
               rock_density_kg_m3: float, n_batches: int) -> _Transport:
    pairs_all = _tag_pairs(machine, snaps, removed, clock.times, clock.lag, rock_density_kg_m3, first_stage=0)
    pairs = pairs_all[pairs_all["stage_from"] >= 1].copy()
    streams = _streams(pairs, ["stage_from"]) if len(pairs) else None
    tag_batch = {t: b for b, chunk in enumerate(np.array_split(clock.tag_times, n_batches)) for t in chunk}
    pairs["batch"] = pairs["time_s"].map(tag_batch)
    bstreams = _streams(pairs, ["stage_from", "batch"]) if len(pairs) else None
    return _Transport(pairs, _destinations(pairs_all, machine.n_stages), streams, bstreams)


def _hit_probabilities(pairs: pd.DataFrame, prim: pd.DataFrame) -> tuple[pd.Series, pd.DataFrame, pd.DataFrame]:
    """Per stage (and per stage and batch): mass share of tagged rock hit by a rotor of its stage in (t, t + tau];
    and the tags with their hit mass ``mh``."""
    if not len(pairs):
        return pd.Series(dtype=float), pd.DataFrame(), pd.DataFrame()
    tags = pairs[["time_s", "t_to", "particle_id", "stage_from", "mass_kg", "batch"]].rename(
        columns={"stage_from": "stage"}).sort_values("time_s")
    p = prim[["time_s", "particle_id", "stage"]].rename(columns={"time_s": "t_hit"}).sort_values("t_hit")
    p = p.astype({"particle_id": np.int64, "stage": np.int64})
    tags = tags.astype({"particle_id": np.int64, "stage": np.int64})
    nxt = pd.merge_asof(tags, p, left_on="time_s", right_on="t_hit", by=["particle_id", "stage"],
                        direction="forward", allow_exact_matches=False)
    nxt["hit"] = nxt["t_hit"] <= nxt["t_to"] + 1e-12
    nxt["mh"] = nxt["mass_kg"] * nxt["hit"]
    g = nxt.groupby("stage")[["mh", "mass_kg"]].sum()
    gb = nxt.groupby(["stage", "batch"])[["mh", "mass_kg"]].sum()
    return g["mh"] / g["mass_kg"], (gb["mh"] / gb["mass_kg"]).rename("p").reset_index(), nxt


def _passes_from_cut(ev: pd.DataFrame, counts: _Counts, cut_s: float | None, interval_s: float) -> int:
    """Passes holding a counted primary whose first contact is within a snapshot interval of the event cut."""
    if cut_s is None or cut_s <= 0 or not counts.pr_rows.size:
        return 0
    first = ev.groupby("pass_id")["time_s"].transform("min").to_numpy()[counts.pr_rows]
    return int(np.unique(ev["pass_id"].to_numpy()[counts.pr_rows][first < cut_s + interval_s]).size)


@dataclass(frozen=True)
class _Counts:
    """Primary impacts inside the window with a full follow-up, and their counted secondary impacts."""

    pr_rows: np.ndarray  # rows of ``ev``
    pr_stage: np.ndarray
    pr_batch: np.ndarray
    counts_all: np.ndarray  # secondary count per row of ``ev`` (non-zero on primaries)
    sec_rows: np.ndarray
    sec_stage: np.ndarray  # stage of each secondary's primary
    vn_m_s: np.ndarray
    time_s: np.ndarray  # of every row of ``ev``


def _secondary_counts(ev: pd.DataFrame, window_s: tuple[float, float], tau_s: float, s_: StatsSettings) -> _Counts:
    t0, t1 = window_s
    pr_rows = np.flatnonzero(ev["is_primary"].to_numpy())
    t_ev = ev["time_s"].to_numpy()
    pr_rows = pr_rows[(t_ev[pr_rows] >= t0) & (t_ev[pr_rows] <= t1 - tau_s)]
    vn = ev["vn_m_s"].to_numpy()
    primary_row = ev["primary_row"].to_numpy()
    sec = (primary_row >= 0) & (vn >= s_.min_secondary_speed_m_s)
    counts_all = np.bincount(primary_row[sec], minlength=len(ev))
    counted = np.zeros(len(ev), dtype=bool)
    counted[pr_rows] = True
    sec_rows = np.flatnonzero(sec & counted[np.maximum(primary_row, 0)])
    stage = ev["stage"].to_numpy()
    pr_batch = np.minimum(((t_ev[pr_rows] - t0) / max(t1 - tau_s - t0, 1e-12) * s_.n_batches).astype(int),
                          s_.n_batches - 1)
    return _Counts(pr_rows, stage[pr_rows], pr_batch, counts_all, sec_rows, stage[primary_row[sec_rows]], vn, t_ev)


def _region_streams(machine: Machine, snaps: pd.DataFrame, pairs: pd.DataFrame) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Full mode: solid volume per (stage, region) and streams of the tagged moves per (stage, region)."""
    edges_y = np.linspace(0.0, machine.casing_length_m, N_REGIONS + 1)
    sn_in = snaps.assign(stage=stage_of_z(machine, snaps["z_m"].to_numpy()),
                         region=np.clip(np.searchsorted(edges_y, snaps["y_m"].to_numpy(), side="right") - 1,
                                        0, N_REGIONS - 1),
                         vol=4.0 / 3.0 * np.pi * snaps["radius_m"].to_numpy() ** 3)
    vol = sn_in.pivot_table(index="stage", columns="region", values="vol", aggfunc="sum", fill_value=0.0)
    vol = vol.reindex(columns=range(N_REGIONS), fill_value=0.0)
    pairs["region"] = np.clip(np.searchsorted(edges_y, pairs["y_m"].to_numpy(), side="right") - 1,
                              0, N_REGIONS - 1)
    return vol, _streams(pairs, ["stage_from", "region"])


def _stage_regions(s: int, region_streams: tuple[pd.DataFrame, pd.DataFrame] | None,
                   mean: list[float]) -> tuple[list[float] | None, list[list[float]] | None]:
    """Region weights and streams of stage ``s`` (full mode; a region without tagged rock gets ``mean``)."""
    if region_streams is None:
        return None, None
    vol, rstreams = region_streams
    if s not in vol.index or vol.loc[s].sum() <= 0:
        return None, None
    w = vol.loc[s].to_numpy()
    rs = []
    for r in range(N_REGIONS):
        if (s, r) in rstreams.index and rstreams.at[(s, r), "mass_kg"] > 0:
            row = rstreams.loc[(s, r), ["kickback", "refeed", "pass_through"]].to_numpy(dtype=float)
            rs.append(list(map(float, row / row.sum())))
        else:
            rs.append(mean)
    return list(map(float, w / w.sum())), rs


def _stage_statistics(
    s: int, tr: _Transport, hits: pd.Series, hits_b: pd.DataFrame, prim: pd.DataFrame, counts: _Counts,
    window_s: tuple[float, float], s_: StatsSettings,
    region_streams: tuple[pd.DataFrame, pd.DataFrame] | None, holdup_kg: float,
) -> tuple[StageStatistics, dict[str, np.ndarray], dict[str, Any]]:
    """Statistics of stage ``s``, its samples and its fits."""
    t0, t1 = window_s
    se: dict[str, float] = {}
    if tr.streams is not None and s in tr.streams.index:
        kick, ref, pt = (float(tr.streams.at[s, c]) for c in ("kickback", "refeed", "pass_through"))
        bs = tr.batch_streams.xs(s, level="stage_from")
        for c in ("kickback", "refeed", "pass_through"):
            se[c] = _batch_se(bs[c].to_numpy())
        n_tr = int((tr.pairs["stage_from"] == s).sum())
    else:
        kick, ref, pt, n_tr = 0.0, 1.0, 0.0, 0
    tot = kick + ref + pt
    kick, ref, pt = kick / tot, ref / tot, pt / tot
    ph = float(hits.get(s, 0.0)) if len(hits) else 0.0
    if len(hits_b):
        se["primary_hit_probability"] = _batch_se(hits_b.loc[hits_b["stage"] == s, "p"].to_numpy())

    t_prim = prim["time_s"].to_numpy()
    in_prim = (prim["stage"].to_numpy() == s) & (t_prim >= t0) & (t_prim <= t1)
    v_prim, t_prim = prim["vn_m_s"].to_numpy()[in_prim], t_prim[in_prim]
    gm_p, kl_p, fit_p = _fit_velocity(v_prim, s_)
    sel = counts.pr_stage == s
    cnt = counts.counts_all[counts.pr_rows[sel]]
    sec_rows = counts.sec_rows[counts.sec_stage == s]
    v_sec, t_sec = counts.vn_m_s[sec_rows], counts.time_s[sec_rows]
    count_fit = _fit_counts(cnt, counts.pr_batch[sel], s_, se)
    gm_s, kl_s, fit_s = _fit_velocity(v_sec, s_)
    se["primary_velocity_mean_m_s"] = _mean_se(v_prim, t_prim, window_s, s_.n_batches)
    se["secondary_velocity_mean_m_s"] = _mean_se(v_sec, t_sec, window_s, s_.n_batches)
    se = {k: v for k, v in se.items() if np.isfinite(v)}
    rw, rs = _stage_regions(s, region_streams, [kick, ref, pt])
    stage = StageStatistics(
        stage=s, kickback=kick, refeed=ref, pass_through=pt,
        region_weights=rw, region_streams=rs,
        primary_hit_probability=min(max(ph, 0.0), 1.0),
        primary_velocity=gm_p, primary_velocity_kl=kl_p,
        secondary_lambda=count_fit["lambda"], secondary_lambda_kl=count_fit["poisson_kl"],
        secondary_count=count_fit["distribution"], secondary_count_histogram=count_fit["histogram"],
        secondary_count_selection=count_fit["selection"],
        secondary_velocity=gm_s, secondary_velocity_kl=kl_s,
        n_primary_impacts=int(v_prim.size), n_secondary_impacts=int(v_sec.size),
        n_transport_samples=n_tr, mean_holdup_kg=holdup_kg,
        sampling_error=se, destinations=tr.destinations.get(s),
    )
    samples = {"primary_velocity_m_s": v_prim, "secondary_counts": cnt, "secondary_velocity_m_s": v_sec}
    fits = {"primary": fit_p, "secondary_velocity": fit_s, "secondary_count": count_fit["fit"],
            "secondary_count_families": count_fit["families"]}
    return stage, samples, fits


def _mean_se(v: np.ndarray, t_s: np.ndarray, window_s: tuple[float, float], n_batches: int) -> float:
    """Standard error of the mean of ``v`` (samples at times ``t_s``) by batch means over the window.

    Impacts are not independent (a rock's secondary impacts cluster after its
    primary, a rock-rock contact counts for both rocks, the flow pulsates), so
    ``std / sqrt(n)`` understates the error; the means of ``n_batches`` equal
    time slices carry the correlation. Fewer than two batches with samples:
    ``std / sqrt(n)`` (NaN below two samples).
    """
    if v.size < 2:
        return float("nan")
    t0, t1 = window_s
    b = np.minimum(((t_s - t0) / max(t1 - t0, 1e-12) * n_batches).astype(int), n_batches - 1)
    n_b = np.bincount(b, minlength=n_batches)
    if np.count_nonzero(n_b) < 2:
        return float(v.std(ddof=1) / np.sqrt(v.size))
    means = np.bincount(b, weights=v, minlength=n_batches)[n_b > 0] / n_b[n_b > 0]
    return _batch_se(means)


def _outflow(removed: pd.DataFrame, timeseries: pd.DataFrame, window_s: tuple[float, float],
             rock_density_kg_m3: float, holdup_kg: pd.Series, n_batches: int) -> tuple[float, float, float]:
    """Product mass rate out of the outlet over the window (kg/s), the mean hold-up (kg) and its relative error.

    The error is the batch-means standard error of the time series' mean mass over that mean
    (``n_batches`` consecutive blocks of the window's samples; NaN with fewer samples than batches
    or without a time series).
    """
    t0, t1 = window_s
    rem = removed
    if "tag" in rem:
        rem = rem[rem["tag"].astype(str) == "outlet"]
    rem_w = rem[(rem["time_s"] >= t0) & (rem["time_s"] <= t1)]
    mass_col = rem_w["mass_kg"] if "mass_kg" in rem_w else rock_density_kg_m3 * 4 / 3 * np.pi * rem_w["radius_m"] ** 3
    out_rate = float(mass_col.sum()) / (t1 - t0) if t1 > t0 else 0.0
    ts = timeseries[(timeseries["time_s"] >= t0) & (timeseries["time_s"] <= t1)]
    if not len(ts):
        return out_rate, float(holdup_kg.sum()), float("nan")
    mass = ts["mass_kg"].to_numpy(dtype=float)
    mean = float(mass.mean())
    rel = _batch_se(np.array([b.mean() for b in np.array_split(mass, n_batches)])) / mean \
        if mass.size >= n_batches and mean > 0 else float("nan")
    return out_rate, mean, rel


def _fit_counts(cnt: np.ndarray, batch: np.ndarray, s_: StatsSettings, se: dict[str, float]) -> dict[str, Any]:
    """Poisson and family-selected fits of one stage's secondary-impact counts (fills ``se``).

    Standard errors by batch means: ``secondary_lambda`` (the mean count) and
    every native parameter of the chosen family, as ``secondary_count.<name>``.
    """
    if cnt.size == 0:
        return {"fit": None, "families": None, "lambda": 0.0, "poisson_kl": None, "distribution": None,
                "histogram": [], "selection": None}
    hist = np.bincount(cnt)
    sel = CountFamilySelection(criterion=s_.count_criterion).fit_histogram(hist)
    dist = sel.to_count_distribution()
    batches = [cnt[batch == b] for b in range(s_.n_batches) if np.any(batch == b)]
    se["secondary_lambda"] = _batch_se(np.asarray([b.mean() for b in batches]))
    se.update({f"secondary_count.{k}": v for k, v in count_batch_stderr(sel.chosen_, batches).items()
               if k != "mean"})
    return {"fit": sel.fits_["poisson"], "families": sel, "lambda": dist.mean, "poisson_kl": sel.poisson_kl_,
            "distribution": dist, "histogram": [int(h) for h in hist], "selection": sel.to_selection()}


def _fit_velocity(v: np.ndarray, s_: StatsSettings) -> tuple[GaussianMixture, float | None, Any]:
    """Mixture fit of a velocity sample; placeholder when empty."""
    if v.size == 0:
        return _PLACEHOLDER, None, None
    if v.size < s_.min_fit_samples or np.ptp(v) == 0:
        sd = float(v.std(ddof=1)) if v.size > 1 and np.ptp(v) > 0 else 1e-3
        fit = GaussianMixtureKLFit(k_max=1, refine=False).fit(v) if v.size > 1 else None
        return GaussianMixture.single(float(v.mean()), max(sd, 1e-3)), (float(fit.kl_) if fit else None), fit
    fit = GaussianMixtureKLFit(k_max=s_.k_max, refine=s_.velocity_fit == "binned_kl").fit(v)
    return fit.to_stageparams(), float(fit.kl_), fit
