"""A circuit of units and streams, and its steady state by tear streams.

The streams that close recycle loops are torn (the back edges of a depth-first
walk from the fresh feeds); the units are then evaluated in a fixed order, one
pass ``g`` mapping guessed tear-stream flows ``x`` (t/h per size class) to new
ones. Steady state is the fixed point ``x = g(x)``, found by direct
substitution (``x <- g(x)``) or by Wegstein's method (per element, the secant
slope ``s`` of ``g`` between the last two iterates, ``q = s / (s - 1)`` bounded
to [``WEGSTEIN_Q_MIN``, ``WEGSTEIN_Q_MAX``], ``x <- q x + (1 - q) g(x)``). The
relative mass-balance error is ``sum |g(x) - x| / fresh feed``, the rock that a
pass would accumulate in (or take out of) the loops per hour of fresh feed; the
solve stops when it is at most ``tol`` (default 1e-10). With the mills' operators
fixed the circuit is linear; the mills are then rebuilt at their new feed rates
and the streams converged again until every mill's operators were built within
``RATE_TOL`` of its feed rate (:meth:`Circuit.solve`). :meth:`Circuit.band` solves
posterior samples of the mills' stage parameters together for 5-95 % bands.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd

from msmill.errors import MsmillError, MsmillInputError
from msmill.model.circuit.units import RATE_TOL, FreshFeed, MillUnit, Product, SampleTransfers, Unit
from msmill.model.mill import BAND_LIMITS_PCT, DEFAULT_BAND_SAMPLES, MAX_BAND_SAMPLES
from msmill.psd import PSD, SQRT2_SIEVES_MM, SizeGrid

METHODS = ("wegstein", "direct")
DEFAULT_TOL = 1e-10
DEFAULT_MAX_ITERATIONS = 500
DEFAULT_MAX_REBUILDS = 30
#: Smallest reach of the band's feed rates below and above the circuit's (relative).
BAND_MIN_RATE_STEP = 0.02
#: Feed rates at which the band builds every sample's mill transfer matrices, and how far beyond
#: the samples' first-pass rates they reach (fraction of their span).
BAND_RATE_NODES = 7
BAND_RATE_MARGIN = 0.15
#: Bounds of Wegstein's relaxation ``q`` (negative: acceleration; 0: direct substitution).
WEGSTEIN_Q_MIN = -20.0
WEGSTEIN_Q_MAX = 0.0


class CircuitNotConverged(MsmillError):
    """The tear-stream iteration did not reach its tolerance (one line: iterations, last residual)."""


@dataclass(frozen=True)
class Stream:
    """A stream from ``source`` unit's outlet ``outlet`` to ``target`` unit's inlet."""

    name: str
    source: str
    outlet: str
    target: str
    recycle: bool = False


class Circuit:
    """Units joined by streams, checked at construction.

    Parameters
    ----------
    units : list of Unit
    streams : list of Stream
    grid : SizeGrid, optional
        Size grid of every stream; default the sqrt(2) series from 0.038 mm up to the
        coarsest fresh feed's top size.
    title : str
    prefix : str
        Prefix of every error's field name (the circuit file's name).

    Checks (one-line :class:`MsmillInputError`): unit and stream names unique; every
    stream's ends exist; every outlet has exactly one stream (an outlet without one sends
    rock nowhere) and every unit with an inlet at least one; at least one fresh feed and
    one product; every recycle loop holds a unit that breaks rock (a mill).
    """

    def __init__(self, units: list[Unit], streams: list[Stream], grid: SizeGrid | None = None,
                 title: str = "", prefix: str = "circuit") -> None:
        self.title = title
        self.prefix = prefix
        self.units: dict[str, Unit] = {}
        for i, u in enumerate(units):
            if u.name in self.units:
                raise MsmillInputError(f"{prefix}.units[{i}].name", u.name, "a name no other unit has")
            self.units[u.name] = u
        self.streams: dict[str, Stream] = {}
        used: dict[tuple[str, str], str] = {}
        for i, s in enumerate(streams):
            where = f"{prefix}.streams[{i}]"
            if s.name in self.streams:
                raise MsmillInputError(f"{where}.name", s.name, "a name no other stream has")
            if s.source not in self.units:
                raise MsmillInputError(f"{where}.from", s.source, _one_of("a unit", self.units))
            src = self.units[s.source]
            if s.outlet not in src.outlets:
                allowed = (f"one of its outlets: {', '.join(f'{s.source}.{o}' for o in src.outlets)}"
                           if src.outlets else f"a unit with outlets ({s.source} is a product)")
                raise MsmillInputError(f"{where}.from", f"{s.source}.{s.outlet}", allowed)
            if (s.source, s.outlet) in used:
                raise MsmillInputError(f"{where}.from", f"{s.source}.{s.outlet}",
                                       f"an outlet no other stream leaves ({used[s.source, s.outlet]} does; "
                                       "split a stream with a splitter)")
            used[s.source, s.outlet] = s.name
            if s.target not in self.units:
                raise MsmillInputError(f"{where}.to", s.target, _one_of("a unit", self.units))
            if not self.units[s.target].has_inlet:
                raise MsmillInputError(f"{where}.to", s.target, "a unit with an inlet (a fresh feed has none)")
            self.streams[s.name] = s
        for u in self.units.values():
            for o in u.outlets:
                if (u.name, o) not in used:
                    raise MsmillInputError(f"{prefix}.units.{u.name}", f"outlet {o}",
                                           "every outlet joined to a stream (this one goes nowhere)")
            if u.has_inlet and not any(s.target == u.name for s in self.streams.values()):
                raise MsmillInputError(f"{prefix}.units.{u.name}", "no stream in",
                                       "a stream into every unit but fresh feeds")
        if not any(isinstance(u, FreshFeed) for u in self.units.values()):
            raise MsmillInputError(f"{prefix}.units", "no fresh feed", "at least one unit of type feed")
        if not any(isinstance(u, Product) for u in self.units.values()):
            raise MsmillInputError(f"{prefix}.units", "no product", "at least one unit of type product")
        self._check_loops()
        self.tears, self.order = _tear_streams(list(self.units), list(self.streams.values()))
        if grid is None:
            top = max(u.top_mm for u in self.units.values() if isinstance(u, FreshFeed))
            grid = SizeGrid.geometric(0.038, max(top, 0.076))
        self.grid = grid
        for u in self.units.values():
            u.bind(grid)
        self._into: dict[str, list[str]] = {u: [s.name for s in self.streams.values() if s.target == u]
                                            for u in self.units}
        self._out_of = {(s.source, s.outlet): s.name for s in self.streams.values()}

    def _check_loops(self) -> None:
        """Every strongly connected group of units (a recycle loop) holds a unit that breaks rock."""
        from scipy.sparse import csr_matrix
        from scipy.sparse.csgraph import connected_components

        names = list(self.units)
        idx = {n: i for i, n in enumerate(names)}
        edges = [(idx[s.source], idx[s.target]) for s in self.streams.values()]
        r, c = zip(*edges, strict=True) if edges else ((), ())
        g = csr_matrix((np.ones(len(edges)), (r, c)), shape=(len(names), len(names)))
        _, label = connected_components(g, directed=True, connection="strong")
        for lab in np.unique(label):
            members = [names[i] for i in np.flatnonzero(label == lab)]
            looped = len(members) > 1 or any(s.source == s.target == members[0] for s in self.streams.values())
            if looped and not any(self.units[m].breaks_rock for m in members):
                raise MsmillInputError(f"{self.prefix}.streams", "a loop through " + " -> ".join(members),
                                       "recycle loops that pass a mill (without one the loop only holds rock back)")

    # ------------------------------------------------------------------ solving
    @property
    def fresh_tph(self) -> float:
        """Total fresh feed (t/h)."""
        return float(sum(u.rate_tph for u in self.units.values() if isinstance(u, FreshFeed)))

    def evaluate(self, x: np.ndarray) -> tuple[np.ndarray, dict[str, np.ndarray], dict[str, np.ndarray]]:
        """One pass through the units with tear-stream flows ``x`` (..., T, N) (t/h per class).

        Returns the new tear flows ``g(x)`` (..., T, N), every stream's flow and every unit's feed
        (leading axes: posterior samples, when the band is solved).
        """
        lead = x.shape[:-2]
        flows: dict[str, np.ndarray] = {t: x[..., k, :] for k, t in enumerate(self.tears)}
        new: dict[str, np.ndarray] = {}
        feeds: dict[str, np.ndarray] = {}
        for name in self.order:
            feed = np.zeros((*lead, self.grid.n_classes))
            for sname in self._into[name]:
                feed = feed + flows[sname]
            feeds[name] = feed
            for outlet, q in self.units[name].apply(feed).items():
                sname = self._out_of[name, outlet]
                (new if sname in self.tears else flows)[sname] = np.broadcast_to(q, feed.shape)
        gx = np.stack([new[t] for t in self.tears], axis=-2) if self.tears else np.zeros((*lead, 0, self.grid.n_classes))
        return gx, flows, feeds

    def iterate(self, x: np.ndarray, method: str = "wegstein", tol: float = DEFAULT_TOL,
                max_iterations: int = DEFAULT_MAX_ITERATIONS) -> tuple[np.ndarray, dict, dict, list[float]]:
        """Tear-stream iteration from ``x`` (..., T, N) with the units as they are (a mill's operators fixed).

        Returns the converged tear flows, the streams' and units' feeds of the last pass and the
        residual of every pass (the largest over samples); raises :class:`CircuitNotConverged`.
        """
        fresh = self.fresh_tph
        x_prev = g_prev = None
        history: list[float] = []
        for _ in range(max_iterations):
            gx, flows, feeds = self.evaluate(x)
            res = float(np.abs(gx - x).sum(axis=(-2, -1)).max(initial=0.0)) / fresh
            history.append(res)
            if res <= tol:
                return x, flows, feeds, history
            if not np.all(np.isfinite(gx)):
                break
            if method == "wegstein" and x_prev is not None:
                dx = x - x_prev
                dg = gx - g_prev
                with np.errstate(divide="ignore", invalid="ignore"):
                    s = np.where(np.abs(dx) > 1e-14 * (np.abs(x) + 1e-300), dg / dx, 0.0)
                    q = np.where(np.abs(s - 1.0) > 1e-12, s / (s - 1.0), 0.0)
                q = np.clip(np.nan_to_num(q), WEGSTEIN_Q_MIN, WEGSTEIN_Q_MAX)
                x_new = np.maximum(q * x + (1.0 - q) * gx, 0.0)
            else:
                x_new = gx
            x_prev, g_prev = x, gx
            x = x_new
        raise CircuitNotConverged(
            f"{self.prefix}: the {method} tear-stream iteration did not converge in {len(history)} iterations: "
            f"relative mass-balance error {history[-1]:.3g} (tolerance {tol:.3g}); raise max_iterations, try "
            f"method={'direct' if method == 'wegstein' else 'wegstein'}, or check the recycle")

    def solve(self, method: str = "wegstein", tol: float = DEFAULT_TOL,
              max_iterations: int = DEFAULT_MAX_ITERATIONS, max_rebuilds: int = DEFAULT_MAX_REBUILDS) -> CircuitResult:
        """Steady state by tear streams (module docstring); raises :class:`CircuitNotConverged`.

        With the mills' operators fixed the circuit is linear; :meth:`iterate` converges it. Then
        every mill whose feed rate ``r`` differs from the rate ``r_0`` its operators were built at
        by more than :data:`~msmill.model.circuit.units.RATE_TOL` is rebuilt at the next rate of the
        same method on the rate (direct: ``r``; Wegstein: the secant step through the last two
        ``(r_0, r)`` pairs) and the streams are converged again from where they were, until no mill
        needs rebuilding (at most ``max_rebuilds`` rounds).
        """
        from msmill.validate import integer, number

        if method not in METHODS:
            raise MsmillInputError("method", method, " or ".join(METHODS))
        tol = number(tol, "tol", gt=0, lt=1)
        max_iterations = integer(max_iterations, "max_iterations", ge=1, le=100000)
        max_rebuilds = integer(max_rebuilds, "max_rebuilds", ge=0, le=1000)
        mills = {n: u for n, u in self.units.items() if isinstance(u, MillUnit)}
        for u in mills.values():
            u.samples = None
        x = np.zeros((len(self.tears), self.grid.n_classes))
        history: list[float] = []
        last: dict[str, tuple[float, float]] = {}  # mill: (rate its operators were built at, its feed rate)
        for round_ in range(max_rebuilds + 1):
            x, flows, feeds, h = self.iterate(x, method, tol, max(max_iterations - len(history), 1))
            history += h
            loose = {n: u for n, u in mills.items() if u.rate_mismatch(float(feeds[n].sum())) > RATE_TOL}
            if not loose:
                for u in mills.values():
                    for message, category in u.build_warnings:
                        warnings.warn(message, category, stacklevel=2)
                return self._result(x, flows, feeds, method, len(history), history[-1], history)
            for n, u in loose.items():
                r0, r = u.operator_rate_tph, float(feeds[n].sum())
                if round_ == max_rebuilds:
                    last[n] = (r0, r)
                    continue
                nxt = r
                if method == "wegstein" and n in last and last[n][0] != r0:
                    s = (r - last[n][1]) / (r0 - last[n][0])
                    if abs(s - 1.0) > 1e-12:
                        q = min(max(s / (s - 1.0), WEGSTEIN_Q_MIN), WEGSTEIN_Q_MAX)
                        nxt = q * r0 + (1.0 - q) * r
                last[n] = (r0, r)
                u.rebuild(nxt if nxt > 0 else r)
        n = max(loose, key=lambda m: abs(last[m][1] - last[m][0]) / last[m][0])
        r0, r = last[n]
        raise CircuitNotConverged(
            f"{self.prefix}: mill {n}'s feed rate did not settle in {max_rebuilds} rebuilds of its operators: fed "
            f"{r:.6g} t/h, built at {r0:.6g} t/h (relative difference {abs(r - r0) / r0:.3g}, tolerance "
            f"{RATE_TOL:.3g}); raise max_rebuilds or try method=direct")

    def band(self, result: CircuitResult, n_samples: int = DEFAULT_BAND_SAMPLES, seed: int = 0,
             method: str | None = None, tol: float = DEFAULT_TOL,
             max_iterations: int = DEFAULT_MAX_ITERATIONS, rate_nodes: int = BAND_RATE_NODES) -> CircuitBand:
        """5-95 % band of the circulating load, product P80 and mill feed rates from posterior samples.

        ``n_samples`` posterior samples of every mill's stage parameters
        (:func:`msmill.model.providers.posterior_samples`, ``seed``) are solved together: each
        mill unit gets every sample's transfer matrix (at the band's resolution,
        :meth:`msmill.model.Mill.batch_products`) at the mill's feed rate in ``result``; a first
        pass with those gives the samples' feed rates; then every sample's matrix is built at
        ``rate_nodes`` rates spanning them and interpolated piecewise linearly at that sample's
        own feed rate, and the tear-stream iteration runs again on all samples at once (streams
        (K, N)). The band is the samples' 5 % and 95 %
        quantiles relative to their median, added to ``result``'s own figures (so the band's
        coarser resolution cancels, as in the mill's band).
        """
        from msmill.model.providers import posterior_samples
        from msmill.validate import integer

        n_samples = integer(n_samples, "band_samples", ge=2, le=MAX_BAND_SAMPLES)
        rate_nodes = integer(rate_nodes, "rate_nodes", ge=2, le=50)
        method = method or result.method
        mills = {n: u for n, u in self.units.items() if isinstance(u, MillUnit)}
        if not mills:
            raise MsmillInputError("band_samples", n_samples, "0 for a circuit without a mill unit (nothing in it "
                                   "has posterior samples)")
        for n, u in mills.items():
            if not hasattr(u.mill.provider, "sample_stage_parameters"):
                raise MsmillInputError(f"{self.prefix}.units.{n}.stage_parameters", u.mill.provider.source,
                                       "a provider with posterior samples (the default surrogate) for the band; "
                                       "band samples = 0 without one")
        members = {n: posterior_samples(u.mill.provider, n_samples, seed) for n, u in mills.items()}
        rate = {n: float(result.unit_feeds_tph[n].sum()) for n in mills}
        at_rate = {n: self._sample_transfers(u, members[n], rate[n]) for n, u in mills.items()}
        x0 = np.broadcast_to(np.stack([result.flows_tph[t] for t in self.tears]) if self.tears
                             else np.zeros((0, self.grid.n_classes)),
                             (n_samples, len(self.tears), self.grid.n_classes)).copy()
        try:
            for n, u in mills.items():  # first pass: every sample's operators at the circuit's rate
                u.samples = SampleTransfers([rate[n]], at_rate[n][None])
            x, flows, feeds, h1 = self.iterate(x0, method, tol, max_iterations)
            for n, u in mills.items():  # then at rates spanning the samples' own
                rates = self._band_rates(rate[n], feeds[n].sum(axis=-1), rate_nodes)
                u.samples = SampleTransfers(rates, np.stack([
                    at_rate[n] if r == rate[n] else self._sample_transfers(u, members[n], r) for r in rates]))
            x, flows, feeds, h2 = self.iterate(x, method, tol, max_iterations)
        finally:
            for u in mills.values():
                u.samples = None
        product = sum(flows[s.name] for s in self.streams.values() if isinstance(self.units[s.target], Product))
        cl = 100.0 * sum(flows[r].sum(axis=-1) for r in result.recycle_streams) / self.fresh_tph
        p80 = np.array([PSD(self.grid, q / q.sum(), validate=False).p80_mm for q in np.clip(product, 0.0, None)])
        feeds_tph = {n: feeds[n].sum(axis=-1) for n in mills}
        return CircuitBand(
            n_samples=n_samples, seed=seed, iterations=len(h1) + len(h2),
            circulating_load_pct=cl, product_p80_mm=p80, mill_feed_tph=feeds_tph,
            circulating_load_band_pct=_shifted(result.circulating_load_pct, cl),
            product_p80_band_mm=_shifted(result.product_p80_mm, p80),
            mill_feed_band_tph={n: _shifted(rate[n], v) for n, v in feeds_tph.items()})

    @staticmethod
    def _band_rates(own_tph: float, samples_tph: np.ndarray, n_nodes: int) -> np.ndarray:
        """``n_nodes`` evenly spaced feed rates (t/h) from below to above the samples' (widened by
        :data:`BAND_RATE_MARGIN` of the span, at least :data:`BAND_MIN_RATE_STEP` of ``own_tph`` each
        side), with ``own_tph`` (the circuit's rate, whose matrices are built already) one of them."""
        lo = min(float(samples_tph.min()), own_tph * (1.0 - BAND_MIN_RATE_STEP))
        hi = max(float(samples_tph.max()), own_tph * (1.0 + BAND_MIN_RATE_STEP))
        pad = BAND_RATE_MARGIN * (hi - lo)
        rates = np.linspace(max(lo - pad, 1e-3 * own_tph), hi + pad, n_nodes)
        rates[np.argmin(np.abs(rates - own_tph))] = own_tph
        return np.unique(rates)

    def _sample_transfers(self, unit: MillUnit, members: list, feed_tph: float) -> np.ndarray:
        """Transfer matrices (K, N, N) of posterior-sample ``members`` of ``unit``'s mill at ``feed_tph``."""
        with warnings.catch_warnings():  # the circuit's own solve gave the stage parameters' warnings
            warnings.simplefilter("ignore")
            op = unit.operating_point(feed_tph)
            speeds = op.stage_speeds(unit.mill.provider.n_stages)
            params = [m.stage_parameters(self.grid.mids_mm, speeds, op.feed_tph, op.gate_deg) for m in members]
            return unit.mill.batch_products(self.grid, op, params, np.eye(self.grid.n_classes), np.ones(len(members)))

    def _result(self, x, flows, feeds, method, iterations, residual, history) -> CircuitResult:
        for k, t in enumerate(self.tears):
            flows[t] = x[k]
        flows = {s: flows[s] for s in self.streams}
        product = sum(flows[s.name] for s in self.streams.values() if isinstance(self.units[s.target], Product))
        fresh = self.fresh_tph
        recycle = [s.name for s in self.streams.values() if s.recycle] or list(self.tears)
        cl = 100.0 * sum(float(flows[r].sum()) for r in recycle) / fresh
        return CircuitResult(circuit=self, method=method, iterations=iterations, residual=residual,
                             residual_history=tuple(history), flows_tph=flows, unit_feeds_tph=feeds,
                             product_tph_by_class=np.asarray(product, dtype=float),
                             mass_balance_error=abs(fresh - float(np.sum(product))) / fresh,
                             circulating_load_pct=cl, recycle_streams=tuple(recycle))


def _shifted(own: float, samples: np.ndarray) -> tuple[float, float]:
    """``own`` plus the 5 % and 95 % quantiles of ``samples`` relative to their median."""
    lo, mid, hi = np.percentile(samples, [BAND_LIMITS_PCT[0], 50.0, BAND_LIMITS_PCT[1]])
    return float(own + lo - mid), float(own + hi - mid)


def _one_of(what: str, names: Any) -> str:
    return f"{what} of this circuit: " + ", ".join(names)


def _tear_streams(units: list[str], streams: list[Stream]) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """Tear streams (back edges of a depth-first walk from the units in order, feeds first) and the
    evaluation order of the units once they are torn (topological, stable in file order)."""
    out: dict[str, list[Stream]] = {u: [] for u in units}
    for s in streams:
        out[s.source].append(s)
    state = dict.fromkeys(units, 0)  # 0 new, 1 on the walk's stack, 2 done
    tears: list[str] = []
    for root in units:
        if state[root]:
            continue
        stack = [(root, iter(out[root]))]
        state[root] = 1
        while stack:
            node, it = stack[-1]
            s = next(it, None)
            if s is None:
                state[node] = 2
                stack.pop()
            elif state[s.target] == 1:
                tears.append(s.name)
            elif state[s.target] == 0:
                state[s.target] = 1
                stack.append((s.target, iter(out[s.target])))
    torn = set(tears)
    indeg = dict.fromkeys(units, 0)
    for s in streams:
        if s.name not in torn:
            indeg[s.target] += 1
    order: list[str] = []
    ready = [u for u in units if indeg[u] == 0]
    while ready:
        u = ready.pop(0)
        order.append(u)
        for s in out[u]:
            if s.name not in torn:
                indeg[s.target] -= 1
                if indeg[s.target] == 0:
                    ready.append(s.target)
    return tuple(tears), tuple(order)


@dataclass(frozen=True)
class CircuitBand:
    """5-95 % band of a circuit's figures from posterior samples of its mills' stage parameters.

    Attributes
    ----------
    n_samples, seed : int
    iterations : int
        Tear-stream passes of the samples' solve (all samples at once).
    circulating_load_pct, product_p80_mm : ndarray (K,)
        Each sample's circulating load (%) and product P80 (mm), at the band's resolution.
    mill_feed_tph : dict
        Each mill's feed rate (fresh plus recycle, t/h) per sample.
    circulating_load_band_pct, product_p80_band_mm : (float, float)
        The band: the circuit's own figure plus the samples' 5 % and 95 % quantiles relative to
        their median.
    mill_feed_band_tph : dict
        The same for each mill's feed rate.
    """

    n_samples: int
    seed: int
    iterations: int
    circulating_load_pct: np.ndarray
    product_p80_mm: np.ndarray
    mill_feed_tph: dict[str, np.ndarray]
    circulating_load_band_pct: tuple[float, float]
    product_p80_band_mm: tuple[float, float]
    mill_feed_band_tph: dict[str, tuple[float, float]]

    def samples_frame(self) -> pd.DataFrame:
        """One row per sample: circulating load (%), product P80 (mm), each mill's feed (t/h)."""
        return pd.DataFrame({"sample": np.arange(self.n_samples), "circulating_load_pct": self.circulating_load_pct,
                             "product_p80_mm": self.product_p80_mm,
                             **{f"{n}_feed_tph": v for n, v in self.mill_feed_tph.items()}})


@dataclass(frozen=True)
class CircuitResult:
    """Steady state of a circuit.

    Attributes
    ----------
    method : str
        ``"wegstein"`` or ``"direct"``.
    iterations : int
        Passes through the units until the tolerance was met.
    residual : float
        Relative mass-balance error of the last pass (``sum |g(x) - x| / fresh feed``).
    flows_tph : dict
        Flow of every stream (t/h per size class of ``circuit.grid``).
    unit_feeds_tph : dict
        Feed of every unit (t/h per size class).
    product_tph_by_class : ndarray
        All circuit products together (t/h per size class).
    mass_balance_error : float
        ``|fresh feed - products| / fresh feed``.
    circulating_load_pct : float
        Flow of the recycle streams (those marked ``recycle``, else the tear streams) over the
        fresh feed (%).
    """

    circuit: Circuit
    method: str
    iterations: int
    residual: float
    residual_history: tuple[float, ...]
    flows_tph: dict[str, np.ndarray]
    unit_feeds_tph: dict[str, np.ndarray]
    product_tph_by_class: np.ndarray
    mass_balance_error: float
    circulating_load_pct: float
    recycle_streams: tuple[str, ...]
    notes: tuple[str, ...] = field(default=())

    @property
    def product_tph(self) -> float:
        """Circuit product rate (t/h)."""
        return float(self.product_tph_by_class.sum())

    @property
    def product_psd(self) -> PSD:
        """PSD of all circuit products together."""
        p = np.clip(self.product_tph_by_class, 0.0, None)
        return PSD(self.circuit.grid, p / p.sum(), validate=False)

    @property
    def product_p80_mm(self) -> float:
        return self.product_psd.p80_mm

    def stream_psd(self, name: str) -> PSD | None:
        """PSD of stream ``name`` (None when it carries nothing)."""
        q = np.clip(self.flows_tph[name], 0.0, None)
        return PSD(self.circuit.grid, q / q.sum(), validate=False) if q.sum() > 0 else None

    def stream_table(self, name: str, sieves_mm: Any = SQRT2_SIEVES_MM) -> pd.DataFrame:
        """Sieve table of stream ``name``: t/h and % retained on each sieve, cumulative % passing.

        Sieves: ``sieves_mm`` (the standard sqrt(2) series by default) from the smallest one at or
        above the stream's top size down to the finest one above the circuit grid's lowest edge,
        coarse first, then the pan (``sieve_mm`` 0). Passing at each sieve is read off the stream's
        PSD (log interpolation on the circuit grid).
        """
        q = np.clip(np.asarray(self.flows_tph[name], dtype=float), 0.0, None)
        tot = float(q.sum())
        g = self.circuit.grid
        s = np.sort(np.asarray(sieves_mm, dtype=float))
        nz = np.flatnonzero(q > 1e-12 * max(tot, 1e-300))
        top = float(g.edges_mm[nz[-1] + 1]) if nz.size else float(g.edges_mm[-1])
        above = s[s >= top * (1 - 1e-9)]
        s = s[(s > g.edges_mm[0]) & (s <= (above[0] if above.size else s[-1]))][::-1]
        passing = (np.asarray(PSD(g, q / tot, validate=False).passing_at(s), dtype=float) if tot > 0
                   else np.zeros(s.size))
        retained = np.clip(-np.diff(np.concatenate([[100.0], passing, [0.0]])), 0.0, None)  # on each sieve, the pan
        return pd.DataFrame({"sieve_mm": np.concatenate([s, [0.0]]), "retained_tph": retained / 100.0 * tot,
                             "retained_pct": retained, "passing_pct": np.concatenate([passing, [0.0]])})

    def streams_frame(self) -> pd.DataFrame:
        """One row per stream: from, to, t/h, P80 (mm)."""
        rows = []
        for s in self.circuit.streams.values():
            psd = self.stream_psd(s.name)
            rows.append({"stream": s.name, "from": f"{s.source}.{s.outlet}", "to": s.target,
                         "tph": float(self.flows_tph[s.name].sum()),
                         "p80_mm": psd.p80_mm if psd is not None else math.nan,
                         "recycle": s.name in self.recycle_streams})
        return pd.DataFrame(rows)

    def mill_summaries(self) -> dict[str, dict[str, Any]]:
        """Per mill unit: its feed rate, the rate its operators were built at, impact energy and power,
        and the capacity check of its total feed (fresh plus recycle)."""
        from msmill.model.power import power_estimate
        from msmill.surrogate.capacity import AboveCapacityWarning

        out = {}
        for name, u in self.circuit.units.items():
            if not isinstance(u, MillUnit):
                continue
            q = self.unit_feeds_tph[name]
            rate = float(q.sum())
            feed = PSD(self.circuit.grid, q / rate, validate=False)
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                res = u.mill.run(feed, u.operating_point(u.operator_rate_tph), timeseries=False, held_below=False)
            chk = u.mill.check_capacity(feed, u.operating_point(rate))
            for w in caught:
                if not issubclass(w.category, AboveCapacityWarning):
                    warnings.warn(w.message, w.category, stacklevel=2)
            if chk is not None and chk.above:
                warnings.warn(f"{name}: fresh feed plus recycle is {rate:.4g} t/h (circulating load "
                              f"{self.circulating_load_pct:.3g} %): {chk.message()}", AboveCapacityWarning,
                              stacklevel=2)
            out[name] = {"feed_tph": rate, "operator_rate_tph": u.operator_rate_tph, "operator_rebuilds": u.rebuilds,
                         "impact_energy_kwh_t_feed": res.specific_impact_energy_kwh_t,
                         "impact_kw": power_estimate(res).impact_kw, "result": res, "capacity": chk}
        return out
