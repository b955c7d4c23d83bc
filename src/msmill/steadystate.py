"""Steady state of a fed mill from its time series: one criterion for the DEM and the model.

A mill fed at a constant rate ``F`` is at steady state when what it puts out
balances what it is fed and its hold-up no longer changes. Both are judged on
two consecutive windows ``A = [t - 2W, t - W)`` and ``B = [t - W, t]`` of
length ``W`` long against the pulsation of the flow (``window_s``, 0.65 s by
default: the flow through the mill pulsates on a time scale of a few tenths of
a second, and the LIGGGHTS reference averages over 0.6-0.7 s). At time ``t``
the flow is **steady** when

1. *mass balance*: the product rate over both windows, ``(P_A + P_B) / 2``
   (``P`` = product mass out of a window / ``W``), is within ``balance_tol``
   of the feed rate: ``|P / F - 1| <= balance_tol`` (0.10);
2. *no hold-up trend*: the least-squares slope of the hold-up over
   ``[t - 2W, t]`` is at most ``trend_tol`` of the feed rate in magnitude
   (``|dH/dt| <= trend_tol F``, 0.10);
3. *stable hold-up*: the mean hold-up of the two windows differs by less than
   ``holdup_tol`` (relative to ``B``'s mean).

The onset is ``t - 2W`` of the first passing ``t``. A slowly filling mill
fails (1) and (2) even when (3), the older count-only test, passes.

A run that ends without steady state is **choked** when the product rate is
persistently below the feed rate (both windows below ``(1 - balance_tol) F``)
and not catching up (``P_B - P_A < balance_tol F``): by conservation of mass
the difference then accumulates as hold-up, or backs up into the feed. The
measured product rate is the throughput the mill passes. Anything else is
**not steady** (still filling, emptying, or fluctuating beyond the
tolerances).

A choke is only called when the mill could be fed at all: given the
cumulative mass fed (``fed_cum``, the DEM source's inserted mass), a record
whose fed rate over its *first* window already falls short of
``(1 - balance_tol) F`` is **not steady** (feed-limited), never choked. In
the first window no rock can have backed up from the mill into the feed
region, so the shortfall is the feed source's own limit (the rate is beyond
what it can place), and a product rate below the nominal feed then says
nothing about the mill's capacity. A shortfall that appears later is rock
backing up into the feed: a choke.

Everything is a pure function of arrays (hold-up, cumulative product mass,
time), so the criterion is tested on hand-made series and used by both
:mod:`msmill.dem.mill.run` (hold-up and product mass out of the engine's time
series) and :mod:`msmill.model` (hold-up and product rate of the time
march). Units only need to be consistent (kg and kg/s, or t and t/h with time
in h); the tolerances are relative.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from msmill.errors import MsmillInputError
from msmill.stageparams import chain_residence_steps

__all__ = [
    "OUTCOMES",
    "FlowWindows",
    "Outcome",
    "SteadyStateCriterion",
    "SteadyStateVerdict",
    "assess",
    "count_only_onset",
    "expected_residence_time_s",
    "fed_ratio",
    "first_steady",
    "flow_windows",
]

Outcome = Literal["steady", "not_steady", "choked"]
OUTCOMES: tuple[str, ...] = ("steady", "not_steady", "choked")
_POINTS_PER_WINDOW = 20


@dataclass(frozen=True)
class SteadyStateCriterion:
    """Tolerances of the steady-state test (module docstring).

    Parameters
    ----------
    window_s : float
        Window length ``W`` (s), long against the pulsation of the flow.
    balance_tol : float
        Largest relative difference between product and feed rate over the two windows.
    trend_tol : float
        Largest hold-up slope as a fraction of the feed rate.
    holdup_tol : float
        Largest relative change of the mean hold-up between the two windows.
    """

    window_s: float = 0.65
    balance_tol: float = 0.10
    trend_tol: float = 0.10
    holdup_tol: float = 0.05

    def __post_init__(self) -> None:
        for name in ("window_s", "balance_tol", "trend_tol", "holdup_tol"):
            v = getattr(self, name)
            if not np.isfinite(v) or v <= 0:
                raise MsmillInputError(f"steady_state.{name}", v, "a number > 0")


@dataclass(frozen=True)
class FlowWindows:
    """Window figures for every end time ``end_s`` of a uniform grid (arrays of equal length).

    ``product_a``/``product_b``: product rate of window A/B divided by the feed
    rate; ``trend``: hold-up slope over both windows divided by the feed rate;
    ``holdup_change``: ``|mean_B - mean_A| / mean_B``.
    """

    end_s: np.ndarray
    product_a: np.ndarray
    product_b: np.ndarray
    trend: np.ndarray
    holdup_change: np.ndarray

    def steady(self, crit: SteadyStateCriterion) -> np.ndarray:
        """Boolean mask: the criterion holds at each end time."""
        with np.errstate(invalid="ignore"):
            return ((np.abs(0.5 * (self.product_a + self.product_b) - 1.0) <= crit.balance_tol)
                    & (np.abs(self.trend) <= crit.trend_tol)
                    & (self.holdup_change <= crit.holdup_tol))


@dataclass(frozen=True)
class SteadyStateVerdict:
    """Outcome at the end of a record and the figures of its last two windows.

    Attributes
    ----------
    outcome : {"steady", "not_steady", "choked"}
    onset_s, detected_s : float or None
        First steady onset ``t - 2W`` and the time ``t`` it was detected.
    product_ratio : float
        Product rate / feed rate over the last ``2W``.
    product_rate : float
        Product rate over the last ``2W`` (units of the input).
    trend : float
        Hold-up slope over the last ``2W`` / feed rate.
    """

    outcome: Outcome
    onset_s: float | None
    detected_s: float | None
    product_ratio: float
    product_rate: float
    trend: float
    message: str


def _check(time_s: np.ndarray, *arrays: np.ndarray) -> None:
    if time_s.ndim != 1 or any(a.shape != time_s.shape for a in arrays):
        raise MsmillInputError("time series", [a.shape for a in (time_s, *arrays)], "1-D arrays of equal length")
    if time_s.size > 1 and np.any(np.diff(time_s) <= 0):
        raise MsmillInputError("time_s", "not increasing", "strictly increasing times")


def flow_windows(time_s: np.ndarray, holdup: np.ndarray, product_cum: np.ndarray, feed_per_s: float,
                 window_s: float) -> FlowWindows | None:
    """Window figures for every end time with ``2 window_s`` of history (None if the record is shorter).

    Parameters
    ----------
    time_s : array
        Times (s), strictly increasing.
    holdup : array
        Mass (or count) in the mill at each time.
    product_cum : array
        Cumulative product mass out at each time (same mass unit as ``feed_per_s * s``).
    feed_per_s : float
        Feed rate (mass per s), > 0.
    window_s : float
        Window length ``W`` (s).
    """
    t = np.asarray(time_s, dtype=float)
    h = np.asarray(holdup, dtype=float)
    q = np.asarray(product_cum, dtype=float)
    _check(t, h, q)
    if not feed_per_s > 0:
        raise MsmillInputError("feed_per_s", feed_per_s, "a rate > 0")
    if t.size < 4 or t[-1] - t[0] < 2 * window_s - 1e-9:
        return None
    m = _POINTS_PER_WINDOW
    step = window_s / m
    n_grid = int(np.floor((t[-1] - t[0]) / step + 1e-9)) + 1
    grid = t[-1] - step * np.arange(n_grid)[::-1]  # aligned on the last time, so the end is always judged
    y = np.interp(grid, t, h)
    qg = np.interp(grid, t, q)
    i = np.arange(grid.size - 2 * m)  # window pair = grid points i .. i + 2m
    end = i + 2 * m
    pa = (qg[i + m] - qg[i]) / window_s / feed_per_s
    pb = (qg[end] - qg[i + m]) / window_s / feed_per_s
    # window means (trapezoid-free: mean of the grid points of each half) and LS slope over 2m + 1 points
    sl = _Sliding(y)
    ma, mb = sl.mean(i, m), sl.mean(i + m + 1, m)
    slope = sl.slope(i, 2 * m + 1) / step  # hold-up per s
    with np.errstate(divide="ignore", invalid="ignore"):
        change = np.where(mb > 0, np.abs(mb - ma) / mb, np.inf)
    return FlowWindows(end_s=grid[end], product_a=pa, product_b=pb, trend=slope / feed_per_s, holdup_change=change)


class _Sliding:
    """Means and least-squares slopes of ``y`` over runs of ``n`` grid points, from cumulative sums."""

    def __init__(self, y: np.ndarray) -> None:
        self.c = np.concatenate([[0.0], np.cumsum(y)])
        self.ck = np.concatenate([[0.0], np.cumsum(np.arange(y.size, dtype=float) * y)])

    def sum(self, start: np.ndarray, n: int) -> np.ndarray:
        """Sum of ``y[start : start + n]`` for every start."""
        return self.c[start + n] - self.c[start]

    def mean(self, start: np.ndarray, n: int) -> np.ndarray:
        """Mean of ``y[start : start + n]`` for every start."""
        return self.sum(start, n) / n

    def slope(self, start: np.ndarray, n: int) -> np.ndarray:
        """Least-squares slope (per grid step) of ``y[start : start + n]`` for every start."""
        sy = self.sum(start, n)
        sky = self.ck[start + n] - self.ck[start] - start * sy  # sum of local index * y
        kbar = (n - 1) / 2
        skk = n * (n * n - 1) / 12
        return (sky - kbar * sy) / skk


def count_only_onset(time_s: np.ndarray, count: np.ndarray, window_s: float = 0.4, rel_tol: float = 0.05,
                     trend_tol: float = 0.05) -> tuple[float, float] | None:
    """``(onset_s, detected_s)`` by the count-only test the DEM ran before the mass-balance criterion.

    Kept to re-judge runs that recorded it (their ``run_settings`` have no
    ``balance_tol``) by the test they were made with. The record is resampled
    every ``window_s / 20`` from its first time; at the first start ``t0`` where
    two consecutive windows ``[t0, t0 + W)`` and ``[t0 + W, t0 + 2W)`` have
    means within ``rel_tol`` (relative to the second) and the least-squares
    trend over both, times ``2W`` and over the mean, is within ``trend_tol``,
    the onset is ``t0`` and the detection ``t0 + 2W``. Only condition 3 of the
    module's criterion, on a trend relative to the hold-up instead of the feed.

    Parameters
    ----------
    time_s : array
        Times (s).
    count : array
        Particles (or mass) in the mill at each time.
    window_s, rel_tol, trend_tol : float
        Window length ``W`` (s) and the two tolerances.

    Returns
    -------
    (onset_s, detected_s) or None
        None if the record never passes or is shorter than ``2W``.
    """
    t = np.asarray(time_s, dtype=float)
    n = np.asarray(count, dtype=float)
    if t.size < 4 or t[-1] - t[0] < 2 * window_s:
        return None
    m = _POINTS_PER_WINDOW
    grid = np.arange(t[0], t[-1] + 1e-12, window_s / m)
    if grid.size < 2 * m:
        return None
    sl = _Sliding(np.interp(grid, t, n))
    i = np.arange(grid.size - 2 * m + 1)
    m1, m2 = sl.mean(i, m), sl.mean(i + m, m)
    mean = sl.mean(i, 2 * m)
    with np.errstate(divide="ignore", invalid="ignore"):
        rel = np.abs(m2 - m1) / m2
        trend = np.abs(sl.slope(i, 2 * m) * (2 * m)) / mean
    ok = (m2 > 0) & (rel < rel_tol) & (trend < trend_tol)
    if not ok.any():
        return None
    j = int(np.argmax(ok))
    return float(grid[j]), float(grid[j] + 2 * window_s)


def first_steady(time_s: np.ndarray, holdup: np.ndarray, product_cum: np.ndarray, feed_per_s: float,
                 crit: SteadyStateCriterion | None = None) -> tuple[float, float] | None:
    """``(onset_s, detected_s)`` of the first end time where the criterion holds, or None."""
    c = crit or SteadyStateCriterion()
    fw = flow_windows(time_s, holdup, product_cum, feed_per_s, c.window_s)
    if fw is None:
        return None
    ok = fw.steady(c)
    if not ok.any():
        return None
    j = int(np.argmax(ok))
    return float(fw.end_s[j] - 2 * c.window_s), float(fw.end_s[j])


def assess(time_s: np.ndarray, holdup: np.ndarray, product_cum: np.ndarray, feed_per_s: float,
           crit: SteadyStateCriterion | None = None, fed_cum: np.ndarray | None = None) -> SteadyStateVerdict:
    """Outcome of a record: steady (ever reached), choked or not steady at its end.

    The figures are those of the last two windows of the record. ``fed_cum``
    (cumulative mass fed, optional): a record fed short of the nominal rate
    over its first window is not steady (feed-limited), never choked.
    """
    c = crit or SteadyStateCriterion()
    fw = flow_windows(time_s, holdup, product_cum, feed_per_s, c.window_s)
    if fw is None:
        return SteadyStateVerdict("not_steady", None, None, float("nan"), float("nan"), float("nan"),
                                  f"record shorter than two windows of {c.window_s:g} s")
    found = first_steady(time_s, holdup, product_cum, feed_per_s, c)
    pa, pb, tr = float(fw.product_a[-1]), float(fw.product_b[-1]), float(fw.trend[-1])
    ratio = 0.5 * (pa + pb)
    figures = (f"product {100 * pa:.0f} % then {100 * pb:.0f} % of feed over two {c.window_s:g} s windows, "
               f"hold-up trend {100 * tr:+.0f} % of feed")
    if found is not None:
        return SteadyStateVerdict("steady", found[0], found[1], ratio, ratio * feed_per_s, tr,
                                  f"steady from {found[0]:.2f} s (detected {found[1]:.2f} s)")
    low = 1.0 - c.balance_tol
    t0 = float(np.asarray(time_s)[0])
    fed = fed_ratio(time_s, fed_cum, feed_per_s, t0, t0 + c.window_s) if fed_cum is not None else 1.0
    if fed < low:
        return SteadyStateVerdict("not_steady", None, None, ratio, ratio * feed_per_s, tr,
                                  f"not steady, feed-limited: the feed source placed only {100 * fed:.0f} % of the "
                                  f"nominal feed in the first {c.window_s:g} s, before any rock could back up "
                                  f"(the rate is beyond what the source can place; lower the feed rate); {figures}")
    if pa < low and pb < low and pb - pa < c.balance_tol:
        return SteadyStateVerdict("choked", None, None, ratio, ratio * feed_per_s, tr,
                                  f"choked: {figures}; it passes {100 * ratio:.0f} % of the feed")
    return SteadyStateVerdict("not_steady", None, None, ratio, ratio * feed_per_s, tr, f"not steady: {figures}")


def fed_ratio(time_s: np.ndarray, fed_cum: np.ndarray, feed_per_s: float, t_from_s: float, t_to_s: float) -> float:
    """Mass fed between two times of a record / (``feed_per_s`` x their interval); 1 for an empty interval."""
    t = np.asarray(time_s, dtype=float)
    f = np.asarray(fed_cum, dtype=float)
    if f.shape != t.shape:
        raise MsmillInputError("fed_cum", f"shape {f.shape}", f"one value per time (shape {t.shape})")
    a, b = max(float(t[0]), t_from_s), min(float(t[-1]), t_to_s)
    if b <= a:
        return 1.0
    return float((np.interp(b, t, f) - np.interp(a, t, f)) / (feed_per_s * (b - a)))


def expected_residence_time_s(kickback: np.ndarray, refeed: np.ndarray, pass_through: np.ndarray,
                              step_s: float) -> float:
    """Mean residence time (s) of rock fed to stage 1 of the stage-transport chain.

    Each step of ``step_s``, rock in stage ``s`` moves up (``kickback``, from
    stage 1 back to the feed, which re-enters stage 1 at once), stays
    (``refeed``) or moves down (``pass_through``, from the bottom stage out).
    The expected number of steps to leave, ``N = (I - Q)^-1 1`` for the
    transient-state matrix ``Q`` of this absorbing Markov chain, times ``step_s``
    (:func:`msmill.stageparams.chain_residence_steps`; inf when some rock never leaves).
    """
    k = np.asarray(kickback, dtype=float)
    r = np.asarray(refeed, dtype=float)
    p = np.asarray(pass_through, dtype=float)
    n = k.size
    chain = np.zeros((n, n + 1))  # destinations of stages 1..n, last column out of the bottom stage
    chain[np.arange(n), np.arange(n)] = r
    chain[np.arange(n), np.arange(1, n + 1)] = p
    chain[np.arange(1, n), np.arange(n - 1)] = k[1:]
    chain[0, 0] += k[0]  # kickback from stage 1 is refed with the feed
    return chain_residence_steps(chain) * step_s
