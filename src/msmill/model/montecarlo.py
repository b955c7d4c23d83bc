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
        mids = np.sqrt(edges[:-1] * edges[1:])
        n = mids.size
        tr = as_transition(streams)
        n_st = tr.n_stages
        th = float(damage.threshold)
        cum_dest = np.cumsum(tr.matrix, axis=-1)  # (S+1, N, S+2)
        feed_cdf = np.cumsum(np.asarray(feed_fractions, dtype=float))
        feed_cdf /= feed_cdf[-1]
        m0 = tonnes_per_step / self.parcels_per_step

        comp = np.zeros(0, dtype=np.int64)
        cls = np.zeros(0, dtype=np.int64)
        dmg = np.zeros(0)
        mass = np.zeros(0)
        product = np.zeros((n_steps, n))
        holdup = np.zeros(n_steps)
        fed = np.full(n_steps, tonnes_per_step)
        err = np.zeros(n_steps)
        stage_mass = np.zeros((n_st, n))
        keys = ("primary_t", "primary_kwh", "secondary_t", "secondary_kwh")
        counts = {k: np.zeros(n_st) for k in keys}
        total_fed = total_out = 0.0
        n_max = 0

        def impact(idx: np.ndarray, mix: MixtureArrays, collect: bool, kind: str) -> np.ndarray:
            """One impact on parcels ``idx``; returns the mask of those that broke."""
            st = comp[idx] - 1
            c = cls[idx]
            v = _sample_mixture(rng, mix, st, c)
            e = specific_energy_kwh_t(v)
            L = mids[c]
            d0 = dmg[idx]
            pb = breakage.probability(e, L, d0)
            broke = rng.random(idx.size) < pb
            d_new = damage.after_impact(e, L, d0)
            broke |= d_new >= th
            if collect:
                np.add.at(counts[f"{kind}_t"], st, mass[idx])
                np.add.at(counts[f"{kind}_kwh"], st, mass[idx] * e)
            b = idx[broke]
            if b.size:
                u = fragment_index(breakage, e[broke], L[broke], d0[broke], pb[broke])
                cols = breakage.fragments(edges, cls[b], u)
                cls[b] = _sample_class(rng, cols)
                dmg[b] = 0.0
            s = idx[~broke]
            ds = d_new[~broke]
            if self.damage_classes is not None and s.size:
                lo, frac = split_damage(ds, self.damage_classes, th)
                up = rng.random(s.size) < frac
                ds = (lo + up) * (th / self.damage_classes)
            dmg[s] = ds
            return broke

        count_mix = stats.count_mixture()

        def impacts(idx: np.ndarray, collect: bool) -> None:
            st = comp[idx] - 1
            hit = rng.random(idx.size) < stats.hit_probability[st, cls[idx]]
            h = idx[hit]
            if h.size == 0:
                return
            broke = impact(h, stats.primary_velocity, collect, "primary")
            alive = h[~broke]
            k = _sample_count(rng, count_mix, comp[alive] - 1, cls[alive])
            j = 0
            while alive.size:
                sel = k > j
                alive, k = alive[sel], k[sel]
                if alive.size == 0:
                    break
                broke = impact(alive, stats.secondary_velocity, collect, "secondary")
                alive, k = alive[~broke], k[~broke]
                j += 1

        for t in range(n_steps):
            collect = t >= collect_from
            in_stage = comp >= 1
            if impacted == "all":
                impacts(np.flatnonzero(in_stage), collect)
            # transport draw (post-impact size class when impacts come first)
            cs = cum_dest[comp, cls]  # (m, S+2)
            u = rng.random(comp.size) * cs[:, -1]
            dest = np.minimum((cs <= u[:, None]).sum(axis=1), n_st + 1)
            if impacted == "refeed":
                impacts(np.flatnonzero(in_stage & (dest == comp)), collect)
            comp = dest
            out = comp > n_st
            if np.any(out):
                np.add.at(product[t], cls[out], mass[out])
                total_out += mass[out].sum()
                keep = ~out
                comp, cls, dmg, mass = comp[keep], cls[keep], dmg[keep], mass[keep]
            # fresh feed: stratified over the feed PSD, equal mass, undamaged, into the feed compartment
            u = (np.arange(self.parcels_per_step) + rng.random()) / self.parcels_per_step
            new_cls = np.minimum(np.searchsorted(feed_cdf, u, side="right"), n - 1)
            comp = np.concatenate([comp, np.full(new_cls.size, tr.feed_compartment, dtype=np.int64)])
            cls = np.concatenate([cls, new_cls])
            dmg = np.concatenate([dmg, np.zeros(new_cls.size)])
            mass = np.concatenate([mass, np.full(new_cls.size, m0)])
            total_fed += tonnes_per_step
            held = mass.sum()
            holdup[t] = held
            err[t] = abs(total_fed - held - total_out) / total_fed
            n_max = max(n_max, comp.size)
            if collect:
                sel = comp >= 1
                np.add.at(stage_mass, (comp[sel] - 1, cls[sel]), mass[sel])
            if comp.size > 200 * self.parcels_per_step * max(n_st, 1):
                raise MsmillError("Monte-Carlo parcels keep accumulating: the mill does not empty")
        n_collect = max(n_steps - collect_from, 1)
        return MonteCarloRun(product=product, holdup=holdup, fed=fed, mass_balance_error=err,
                             stage_mass=stage_mass / n_collect, counts=counts, n_parcels_max=n_max)
