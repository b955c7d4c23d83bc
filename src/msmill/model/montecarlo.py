"""Monte-Carlo solver: follow parcels of rock through the same steps, drawn at random.

Every parcel carries a compartment (0 = inlet zone, 1..S = stages), a size
class, a continuous accumulated damage and a mass (t). All parcels are
vectorised numpy arrays; the only Python loops run over time steps, stages'
impact rounds (the k-th secondary impact) and nothing per parcel.

Per step (same semantics as the expected-value solver, docs/model.md):

1. transport: each parcel draws the compartment it is in one step later from
   its compartment's and size class's row of the transition
   (:class:`msmill.model.submodels.Transition`; with three streams: kickback /
   refeed / pass-through, and inlet-zone parcels move to stage 1);
2. impacts (on the parcels that stay, or on all parcels in the stages when
   ``impacted="all"``, in which case impacts come before the transport draw):
   a primary impact with the hit probability, at a velocity drawn from the
   mixture (clipped at 0); break with ``P_b(E, L, D)``; survivors take the
   Tavares damage and break if it reaches the threshold; survivors of the
   primary impact draw their number ``K`` of secondary impacts (a component
   ``c`` of the Poisson-mixture count distribution with probability ``w_c``,
   then ``K ~ Poisson(lambda_c)``; one component is the paper's Poisson),
   applied one after another until the parcel breaks;
3. a broken parcel keeps its mass and becomes one fragment parcel whose size
   class is drawn from the appearance column (probability = mass fraction), with
   damage 0 (unbiased for the expected PSD; mass conserved exactly);
4. parcels drawn to leave (the bottom stage's pass-through) leave as product;
   the step's fresh feed parcels (stratified over the feed PSD, equal mass)
   enter the feed compartment (stage 1 with three streams, the inlet zone with
   the DEM's matrix).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from msmill.errors import MsmillError
from msmill.model.expected_value import split_damage
from msmill.model.parameters import CountArrays, MixtureArrays
from msmill.model.submodels import (
    ImpactStatistics,
    as_transition,
    fragment_index,
    specific_energy_kwh_t,
)


@dataclass
class MonteCarloRun:
    """Raw output of a Monte-Carlo run (tonnes per step unless stated).

    Attributes
    ----------
    product : ndarray (T, N)
        Product mass per step and size class.
    holdup : ndarray (T,)
        Mass in the mill (inlet zone and stages) at the end of each step.
    fed : ndarray (T,)
        Fresh feed per step.
    mass_balance_error : ndarray (T,)
        ``|fed - held - product| / fed`` (cumulative) after each step.
    stage_mass : ndarray (S, N)
        Mass per stage and size class at the end, averaged over the collection window.
    counts : dict of ndarray (S,)
        Over the collection window: impacted tonnes (primary, secondary) and
        energy delivered (t kWh/t = kWh) per stage.
    """

    product: np.ndarray
    holdup: np.ndarray
    fed: np.ndarray
    mass_balance_error: np.ndarray
    stage_mass: np.ndarray
    counts: dict[str, np.ndarray]
    n_parcels_max: int


def _sample_mixture(rng: np.random.Generator, mix: MixtureArrays, st: np.ndarray,
                    cls: np.ndarray) -> np.ndarray:
    w = mix.weights[st, cls]  # (m, K)
    c = np.cumsum(w, axis=1)
    u = rng.random(st.size)[:, None] * c[:, -1:]
    k = np.minimum((c < u).sum(axis=1), w.shape[1] - 1)
    mu = mix.means_m_s[st, cls, k]
    sd = mix.sigmas_m_s[st, cls, k]
    return np.maximum(mu + sd * rng.standard_normal(st.size), 0.0)


def _sample_count(rng: np.random.Generator, counts: CountArrays, st: np.ndarray, cls: np.ndarray) -> np.ndarray:
    """Secondary-impact counts: draw the mixture component, then the Poisson count of its mean."""
    w = counts.weights[st, cls]  # (m, C)
    if w.shape[1] == 1:
        return rng.poisson(counts.means[st, cls, 0])
    c = _sample_class(rng, w)
    return rng.poisson(counts.means[st, cls, c])


def _sample_class(rng: np.random.Generator, cols: np.ndarray) -> np.ndarray:
    c = np.cumsum(cols, axis=1)
    u = rng.random(cols.shape[0])[:, None] * c[:, -1:]
    return np.minimum((c < u).sum(axis=1), cols.shape[1] - 1)


class _Parcels:
    """The parcels in the mill: compartment, size class, damage and mass (t) of each, as arrays."""

    def __init__(self) -> None:
        self.comp = np.zeros(0, dtype=np.int64)
        self.cls = np.zeros(0, dtype=np.int64)
        self.dmg = np.zeros(0)
        self.mass = np.zeros(0)

    def keep(self, mask: np.ndarray) -> None:
        """Keep only the parcels of ``mask``."""
        self.comp, self.cls, self.dmg, self.mass = self.comp[mask], self.cls[mask], self.dmg[mask], self.mass[mask]

    def add(self, compartment: int, classes: np.ndarray, mass_t: float) -> None:
        """Add undamaged parcels of ``mass_t`` each, of size ``classes``, in ``compartment``."""
        self.comp = np.concatenate([self.comp, np.full(classes.size, compartment, dtype=np.int64)])
        self.cls = np.concatenate([self.cls, classes])
        self.dmg = np.concatenate([self.dmg, np.zeros(classes.size)])
        self.mass = np.concatenate([self.mass, np.full(classes.size, mass_t)])


class _Impacts:
    """The primary and secondary impacts of parcels in the stages (updates their class and damage)."""

    def __init__(self, rng: np.random.Generator, parcels: _Parcels, edges: np.ndarray, stats: ImpactStatistics,
                 breakage, damage, damage_classes: int | None, n_stages: int) -> None:
        self.rng, self.pc, self.edges, self.stats = rng, parcels, edges, stats
        self.mids = np.sqrt(edges[:-1] * edges[1:])
        self.breakage, self.damage, self.damage_classes = breakage, damage, damage_classes
        self.threshold = float(damage.threshold)
        self.count_mix = stats.count_mixture()
        #: mass impacted (t) and impact energy (kWh) per stage, primary and secondary, while collecting
        self.counts = {k: np.zeros(n_stages) for k in ("primary_t", "primary_kwh", "secondary_t", "secondary_kwh")}

    def impact(self, idx: np.ndarray, mix: MixtureArrays, collect: bool, kind: str) -> np.ndarray:
        """One impact on parcels ``idx``; returns the mask of those that broke."""
        pc, rng, th = self.pc, self.rng, self.threshold
        st = pc.comp[idx] - 1
        c = pc.cls[idx]
        v = _sample_mixture(rng, mix, st, c)
        e = specific_energy_kwh_t(v)
        L = self.mids[c]
        d0 = pc.dmg[idx]
        pb = self.breakage.probability(e, L, d0)
        broke = rng.random(idx.size) < pb
        d_new = self.damage.after_impact(e, L, d0)
        broke |= d_new >= th
        if collect:
            np.add.at(self.counts[f"{kind}_t"], st, pc.mass[idx])
            np.add.at(self.counts[f"{kind}_kwh"], st, pc.mass[idx] * e)
        b = idx[broke]
        if b.size:
            u = fragment_index(self.breakage, e[broke], L[broke], d0[broke], pb[broke])
            cols = self.breakage.fragments(self.edges, pc.cls[b], u)
            pc.cls[b] = _sample_class(rng, cols)
            pc.dmg[b] = 0.0
        s = idx[~broke]
        ds = d_new[~broke]
        if self.damage_classes is not None and s.size:
            lo, frac = split_damage(ds, self.damage_classes, th)
            up = rng.random(s.size) < frac
            ds = (lo + up) * (th / self.damage_classes)
        pc.dmg[s] = ds
        return broke

    def impacts(self, idx: np.ndarray, collect: bool) -> None:
        """Parcels ``idx`` hit (by the hit probability), then their secondary impacts until they break."""
        pc = self.pc
        st = pc.comp[idx] - 1
        hit = self.rng.random(idx.size) < self.stats.hit_probability[st, pc.cls[idx]]
        h = idx[hit]
        if h.size == 0:
            return
        broke = self.impact(h, self.stats.primary_velocity, collect, "primary")
        alive = h[~broke]
        k = _sample_count(self.rng, self.count_mix, pc.comp[alive] - 1, pc.cls[alive])
        j = 0
        while alive.size:
            sel = k > j
            alive, k = alive[sel], k[sel]
            if alive.size == 0:
                break
            broke = self.impact(alive, self.stats.secondary_velocity, collect, "secondary")
            alive, k = alive[~broke], k[~broke]
            j += 1


class MonteCarloSolver:
    """Parcel Monte-Carlo of the mill (see the module docstring).

    Parameters
    ----------
    parcels_per_step : int
        Fresh feed parcels per step (all of equal mass).
    seed : int or numpy.random.Generator, optional
        Seed of the random stream.
    damage_classes : int or None
        ``None`` (default): continuous damage. An integer: damage snapped to the
        expected-value solver's classes by a random mass-conservative split
        (to check the two solvers on identical discretisations).
    """

    name = "monte_carlo"

    def __init__(self, parcels_per_step: int = 2000, seed=None, damage_classes: int | None = None):
        self.parcels_per_step = int(parcels_per_step)
        self.seed = seed
        self.damage_classes = damage_classes

    def __repr__(self) -> str:
        return f"MonteCarloSolver(parcels_per_step={self.parcels_per_step}, seed={self.seed!r})"

    def run(self, edges_mm: np.ndarray, streams: np.ndarray, stats: ImpactStatistics, breakage,
            damage, feed_fractions: np.ndarray, tonnes_per_step: float, n_steps: int,
            collect_from: int, impacted: str = "refeed") -> MonteCarloRun:
        """March ``n_steps`` steps from an empty mill; statistics from step ``collect_from``."""
        rng = np.random.default_rng(self.seed)
        edges = np.asarray(edges_mm, dtype=float)
        n = edges.size - 1
        tr = as_transition(streams)
        n_st = tr.n_stages
        cum_dest = np.cumsum(tr.matrix, axis=-1)  # (S+1, N, S+2)
        feed_cdf = np.cumsum(np.asarray(feed_fractions, dtype=float))
        feed_cdf /= feed_cdf[-1]
        m0 = tonnes_per_step / self.parcels_per_step
        pc = _Parcels()
        hits = _Impacts(rng, pc, edges, stats, breakage, damage, self.damage_classes, n_st)
        product = np.zeros((n_steps, n))
        holdup = np.zeros(n_steps)
        fed = np.full(n_steps, tonnes_per_step)
        err = np.zeros(n_steps)
        stage_mass = np.zeros((n_st, n))
        total_fed = total_out = 0.0
        n_max = 0
        for t in range(n_steps):
            collect = t >= collect_from
            in_stage = pc.comp >= 1
            if impacted == "all":
                hits.impacts(np.flatnonzero(in_stage), collect)
            # transport draw (post-impact size class when impacts come first)
            cs = cum_dest[pc.comp, pc.cls]  # (m, S+2)
            u = rng.random(pc.comp.size) * cs[:, -1]
            dest = np.minimum((cs <= u[:, None]).sum(axis=1), n_st + 1)
            if impacted == "refeed":
                hits.impacts(np.flatnonzero(in_stage & (dest == pc.comp)), collect)
            pc.comp = dest
            out = pc.comp > n_st
            if np.any(out):
                np.add.at(product[t], pc.cls[out], pc.mass[out])
                total_out += pc.mass[out].sum()
                pc.keep(~out)
            # fresh feed: stratified over the feed PSD, equal mass, undamaged, into the feed compartment
            u = (np.arange(self.parcels_per_step) + rng.random()) / self.parcels_per_step
            pc.add(tr.feed_compartment, np.minimum(np.searchsorted(feed_cdf, u, side="right"), n - 1), m0)
            total_fed += tonnes_per_step
            held = pc.mass.sum()
            holdup[t] = held
            err[t] = abs(total_fed - held - total_out) / total_fed
            n_max = max(n_max, pc.comp.size)
            if collect:
                sel = pc.comp >= 1
                np.add.at(stage_mass, (pc.comp[sel] - 1, pc.cls[sel]), pc.mass[sel])
            if pc.comp.size > 200 * self.parcels_per_step * max(n_st, 1):
                raise MsmillError("Monte-Carlo parcels keep accumulating: the mill does not empty")
        counts = hits.counts
        n_collect = max(n_steps - collect_from, 1)
        return MonteCarloRun(product=product, holdup=holdup, fed=fed, mass_balance_error=err,
                             stage_mass=stage_mass / n_collect, counts=counts, n_parcels_max=n_max)
