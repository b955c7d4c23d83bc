"""Swappable sub-models of the mill model: transport, impacts, breakage, damage.

Each step of the paper's workflow (Section 3, Fig. 5) is one small interface
(a :class:`typing.Protocol`). A sub-model declares the parameters it needs in
``requires`` and is looked up by name in one table per step
(:data:`SUBMODELS`); an unknown name raises a one-line
:class:`~msmill.errors.MsmillInputError` with a "did you mean" suggestion.

Both solvers use the same sub-model objects: the expected-value solver
evaluates them on arrays over (quadrature node, size class, damage class), the
Monte-Carlo solver on arrays over parcels. Every method is therefore a
vectorised function of numpy arrays.

Adding a sub-model: write a class with the protocol's attributes and methods,
add it to the step's table in :data:`SUBMODELS` (or pass an instance to
:class:`msmill.model.Mill`). See docs/interfaces.md, "Mill model: how to add a
sub-model".
"""

from __future__ import annotations

import dataclasses
import difflib
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import numpy as np

from msmill import breakage as _bk
from msmill.errors import MsmillInputError
from msmill.model.parameters import CountArrays, MixtureArrays, StageParameters
from msmill.psd import SizeGrid

KWH_T_PER_J_KG = 1.0 / _bk.J_KG_PER_KWH_T  # 1 kWh/t = 3600 J/kg
#: Tavares gamma used when the ore gives none (published values ~3-5.4).
DEFAULT_GAMMA = 4.0
#: Damage threshold used when the ore gives none (project default, docs/model.md).
DEFAULT_DAMAGE_THRESHOLD = 0.7
#: ``energy_t10`` fineness ratio used when the ore gives none: 1 is ``ab_t10``'s fragments (t10 = A P_b).
DEFAULT_FINENESS_RATIO = 1.0


def specific_energy_kwh_t(v_m_s: np.ndarray) -> np.ndarray:
    """Mass-specific impact energy ``E_cs = v**2 / 2`` (J/kg) in kWh/t; ``v`` clipped at 0."""
    v = np.maximum(np.asarray(v_m_s, dtype=float), 0.0)
    return 0.5 * v * v * KWH_T_PER_J_KG


# --------------------------------------------------------------------- ore data
@dataclass(frozen=True)
class BreakageParameters:
    """Ore breakage parameters used by the breakage and damage sub-models.

    Attributes
    ----------
    name : str
        Ore name.
    A_pct : float
        Pulverisability ``A`` (%), paper Eq. 12.
    b_t_per_kwh : float
        Breakability ``b`` (t/kWh), paper Eq. 11.
    l_ref_mm : float
        Reference size ``L_ref`` (mm), paper Eq. 11.
    tn : msmill.breakage.TnConstants or None
        Constants of ``t_n = k t10**s``; ``None`` uses the packaged default fit.
    gamma : float
        Tavares damage exponent (dimensionless).
    damage_threshold : float
        Accumulated damage at which a rock breaks (dimensionless, 0-1).
    fineness_ratio : float or None
        ``energy_t10`` only: ``c`` of the fragments' ``t10 = A (1 - exp(-c x))`` (dimensionless);
        None: the ore gives none (:data:`DEFAULT_FINENESS_RATIO` is used, and said).
    notes : tuple of str
        Defaults in use (reported with the results).
    """

    name: str
    A_pct: float
    b_t_per_kwh: float
    l_ref_mm: float
    tn: Any = None
    gamma: float = DEFAULT_GAMMA
    damage_threshold: float = DEFAULT_DAMAGE_THRESHOLD
    fineness_ratio: float | None = None
    notes: tuple[str, ...] = ()
    ore: Any = None

    @classmethod
    def from_ore(cls, ore: Any) -> BreakageParameters:
        """Adapt an ``msmill.ore.Ore`` (or any object with its attribute names)."""
        tn = getattr(ore, "tn", None)
        if tn is not None and not isinstance(tn, _bk.TnConstants):
            tn = _bk.TnConstants.from_mapping(tn)
        name = str(getattr(ore, "name", "ore"))
        notes = (f"L_ref of {name} is the default reference size",) if getattr(ore, "l_ref_is_default", False) else ()
        fineness, gamma, threshold = (getattr(ore, k, None) for k in ("fineness_ratio", "gamma", "damage_threshold"))
        return cls(
            name=name,
            A_pct=float(ore.A_pct),
            b_t_per_kwh=float(ore.b_t_per_kwh),
            l_ref_mm=float(ore.l_ref_mm),
            tn=tn,
            gamma=DEFAULT_GAMMA if gamma is None else float(gamma),
            damage_threshold=DEFAULT_DAMAGE_THRESHOLD if threshold is None else float(threshold),
            fineness_ratio=None if fineness is None else float(fineness),
            notes=notes,
            ore=ore,
        )


# ------------------------------------------------------------------ interfaces
@runtime_checkable
class TransportModel(Protocol):
    """Step (a): where the rock mass in a stage goes in one characteristic time."""

    name: str
    requires: tuple[str, ...]

    def streams(self, params: StageParameters) -> np.ndarray:
        """``[kickback, refeed, pass_through]`` per (stage, size class): shape (S, N, 3), rows sum 1."""
        ...


@dataclass(frozen=True)
class ImpactStatistics:
    """What the impact sub-model hands to the solvers (all arrays (S, N) or mixtures).

    Attributes
    ----------
    hit_probability : ndarray (S, N)
        Probability that an impacted-eligible rock gets one primary impact per step.
    primary_velocity : MixtureArrays
        Primary impact velocity (m/s), clipped at 0 when used.
    secondary_lambda : ndarray (S, N)
        Poisson mean of secondary impacts after a non-breaking primary impact.
    secondary_velocity : MixtureArrays
        Secondary impact velocity (m/s), clipped at 0 when used.
    secondary_count : CountArrays or None
        Poisson-mixture distribution of the number of secondary impacts (mean
        ``secondary_lambda``); None: Poisson of ``secondary_lambda``.
    """

    hit_probability: np.ndarray
    primary_velocity: MixtureArrays
    secondary_lambda: np.ndarray
    secondary_velocity: MixtureArrays
    secondary_count: CountArrays | None = None

    def count_mixture(self) -> CountArrays:
        """The secondary-count distribution the solvers use (S, N, C)."""
        if self.secondary_count is None:
            return CountArrays.poisson(self.secondary_lambda)
        return self.secondary_count


def without_stopped_rotors(stats: ImpactStatistics, stage_speeds_rpm: np.ndarray) -> ImpactStatistics:
    """The impact statistics with no primary impacts (hence no secondary ones) where a stage's rotors stand.

    Whatever the impact sub-model: the DEM statistics were measured with turning
    rotors; a stage at 0 rpm has no flinger impacts.
    """
    speeds = np.asarray(stage_speeds_rpm, dtype=float)
    stopped = speeds <= 0.0
    if not np.any(stopped):
        return stats
    h = np.where(stopped[:, None], 0.0, stats.hit_probability)
    return dataclasses.replace(stats, hit_probability=h)


@runtime_checkable
class ImpactModel(Protocol):
    """Step (b): how often and how hard the rocks that stay in a stage are hit."""

    name: str
    requires: tuple[str, ...]

    def impacts(self, params: StageParameters, stage_speeds_rpm: np.ndarray) -> ImpactStatistics:
        """Impact statistics at the given stage speeds (rpm)."""
        ...


@runtime_checkable
class BreakageModel(Protocol):
    """Steps (c)-(d): breakage probability of one impact and the fragments it makes."""

    name: str
    requires: tuple[str, ...]

    def probability(self, ecs_kwh_t: np.ndarray, size_mm: np.ndarray, damage: np.ndarray) -> np.ndarray:
        """Probability that one impact of specific energy ``ecs_kwh_t`` breaks the rock."""
        ...

    def fragments(self, edges_mm: np.ndarray, parent: np.ndarray, pb: np.ndarray) -> np.ndarray:
        """Mass fractions per class (last axis) of the fragments of parents in class ``parent``.

        ``pb`` is the breakage probability, or for a sub-model with a
        ``fragment_index(ecs_kwh_t, size_mm, damage)`` method what that returns
        (:func:`fragment_index`: solvers call it, so fragments may depend on the
        impact energy beyond what ``P_b`` tells).
        """
        ...


@runtime_checkable
class DamageModel(Protocol):
    """Step (c): damage accumulated by a rock that survives an impact."""

    name: str
    requires: tuple[str, ...]
    threshold: float

    def after_impact(self, ecs_kwh_t: np.ndarray, size_mm: np.ndarray, damage: np.ndarray) -> np.ndarray:
        """Accumulated damage after surviving an impact (>= ``damage``); >= threshold breaks."""
        ...


@dataclass(frozen=True)
class Transition:
    """One-step transport of every compartment, as the solvers use it.

    Attributes
    ----------
    matrix : ndarray (S+1, N, S+2)
        ``matrix[c, i, c2]``: fraction of the class-``i`` mass in compartment ``c``
        (0 = inlet zone, 1..S = stages) found one step later in ``c2``
        (``S+1`` = left the mill as product). Rows sum to 1.
    feed_compartment : int
        Compartment the fresh feed of a step enters at the end of the step.
    note : str
        Remark for the result's notes (e.g. a fallback), or empty.
    filling : (ndarray (K,), ndarray (K,) or (N, K)) or None
        Mill fills (share of the steady hold-up) and the transport's mean residence
        there over its steady one (:meth:`speed_at`), one curve for every size class
        (K,) or one per class (N, K); None: the transport does not depend on the
        fill (``matrix`` at every step).
    """

    matrix: np.ndarray
    feed_compartment: int = 1
    note: str = ""
    filling: tuple[np.ndarray, np.ndarray] | None = None

    @property
    def per_class_filling(self) -> bool:
        """Whether the fill-dependent speed differs by size class (``filling`` ratios of shape (N, K))."""
        return self.filling is not None and np.ndim(self.filling[1]) == 2

    def speed_at(self, fill: float) -> float | np.ndarray:
        """How many times faster than at steady state the rock moves at mill fill ``fill`` (1 at and above 1).

        ``1 / ratio``, the ratio linear in the fill between the ``filling`` points and
        ``(1, 1)``, the first point's below them: a float, or per size class (N,)
        when the curves are per class. A step at speed ``g`` moves a compartment's
        rock by ``g (matrix - I)``: the time spent per visit divided by ``g``, the
        destinations of the rock that leaves kept (docs/model.md).
        """
        if self.filling is None:
            return 1.0
        h, r = self.filling
        f = min(float(fill), 1.0)
        hh = np.append(h, 1.0)
        rows = np.atleast_2d(r)  # one curve is one row
        rr = np.concatenate([rows, np.ones((rows.shape[0], 1))], axis=1)
        k = int(np.clip(np.searchsorted(hh, f, side="right") - 1, 0, hh.size - 2))
        t = float(np.clip((f - hh[k]) / (hh[k + 1] - hh[k]), 0.0, 1.0))
        speed = 1.0 / (rr[:, k] + t * (rr[:, k + 1] - rr[:, k]))
        return float(speed[0]) if np.ndim(r) == 1 else speed

    def max_speed(self) -> np.ndarray:
        """Largest speed that keeps the rows non-negative: per compartment (C,), or per class (C, N).

        ``1 / (1 - matrix[c, i, c])``; ``inf`` where the rock always moves. With one
        filling curve for all classes the speed is one per compartment (the
        smallest over its classes), so that a step at speed ``g`` stays linear in the
        state whether impacts come before or after the move (``impacted``); with
        per-class curves (:attr:`per_class_filling`) it is per class (exact for
        ``impacted="refeed"``; with ``"all"`` fragments move at their parent class's
        speed in the step they are made).
        """
        c = np.arange(self.matrix.shape[0])
        stay = self.matrix[c, :, c]  # (C, N)
        leave = 1.0 - (stay if self.per_class_filling else stay.min(axis=1))
        return np.where(leave > 1e-12, 1.0 / np.maximum(leave, 1e-12), np.inf)

    def staying(self) -> np.ndarray:
        """The matrix of a transport that moves nothing: every compartment's rock stays (``matrix``'s shape)."""
        eye = np.zeros_like(self.matrix)
        c = np.arange(self.matrix.shape[0])
        eye[c, :, c] = 1.0
        return eye

    def at_speed(self, g: float | np.ndarray) -> np.ndarray:
        """The one-step matrix at speed ``g`` (a float, or per class (N,)), capped by :meth:`max_speed`."""
        cap = self.max_speed()
        gs = np.minimum(g, cap if cap.ndim == 2 else cap[:, None])[:, :, None]
        return self.matrix + (gs - 1.0) * (self.matrix - self.staying())

    @property
    def n_stages(self) -> int:
        """Number of stages ``S``."""
        return int(self.matrix.shape[0] - 1)

    @classmethod
    def from_streams(cls, streams: np.ndarray, note: str = "") -> Transition:
        """Three streams per stage (S, N, 3): kickback to ``s - 1``, refeed, pass-through to ``s + 1``.

        The inlet zone empties into stage 1 in one step and the fresh feed enters stage 1
        (the paper's scheme, ``msmill.stageparams``).
        """
        st = np.asarray(streams, dtype=float)
        n_st, n, _ = st.shape
        T = np.zeros((n_st + 1, n, n_st + 2))
        T[0, :, 1] = 1.0
        s = np.arange(1, n_st + 1)
        T[s, :, s - 1] = st[:, :, 0]
        T[s, :, s] = st[:, :, 1]
        T[s, :, s + 1] = st[:, :, 2]
        return cls(T, 1, note)


def as_transition(transport: Any) -> Transition:
    """A :class:`Transition`, or three streams (S, N, 3) turned into one."""
    if isinstance(transport, Transition):
        return transport
    return Transition.from_streams(transport)


def transition_of(model: Any, params: StageParameters) -> Transition:
    """The one-step transport a transport sub-model gives (its ``transition`` or its streams)."""
    if hasattr(model, "transition"):
        return model.transition(params)
    return Transition.from_streams(np.asarray(model.streams(params), dtype=float))


# -------------------------------------------------------------- implementations
#: Condition number of the eigenvector matrix above which :func:`fractional_powers` uses
#: scipy's Schur-Pade algorithm for that matrix instead of the eigendecomposition.
EIG_COND_MAX = 1e6


def fractional_powers(Q: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Real part of the principal powers ``Q_b ** p_b`` of a stack of square matrices (B, m, m).

    By eigendecomposition (``V diag(w**p) V^-1``, principal branch of ``w**p``),
    batched over the stack; a matrix whose eigenvectors are ill-conditioned
    (``cond(V) > EIG_COND_MAX``, e.g. nearly defective) goes through
    ``scipy.linalg.fractional_matrix_power`` instead. Both are the principal
    fractional power, so they agree to rounding (``cond(V) * eps``).
    """
    import scipy.linalg

    Q = np.asarray(Q, dtype=float)
    p = np.asarray(p, dtype=float)
    out = np.empty(Q.shape)
    if Q.shape[0] == 0:
        return out
    w, V = np.linalg.eig(Q)
    try:
        Vinv = np.linalg.inv(V)
    except np.linalg.LinAlgError:  # an exactly singular V somewhere: all through scipy
        Vinv = np.full(V.shape, np.nan)
    cond = np.abs(V).sum(axis=-2).max(axis=-1) * np.abs(Vinv).sum(axis=-2).max(axis=-1)  # 1-norm
    ok = np.isfinite(cond) & (cond <= EIG_COND_MAX)
    if ok.any():
        wp = np.power(w[ok].astype(complex), p[ok, None])
        out[ok] = np.real((V[ok] * wp[:, None, :]) @ Vinv[ok])
    for b in np.flatnonzero(~ok):
        out[b] = np.real(scipy.linalg.fractional_matrix_power(Q[b], p[b]))
    return out


def _to_step(T: np.ndarray, lag_s: np.ndarray, step_s: float) -> np.ndarray:
    """Transition matrices measured at ``lag_s`` (per class) as matrices for one step of ``step_s``.

    ``P(step) = P(lag)**(step / lag)`` (the Markov chain's own rule; real part of the
    principal fractional power, clipped at 0 and re-normalised; all classes in one
    batch, :func:`fractional_powers`). Needed when a table's runs have different
    characteristic times and the model steps at their mean.
    """
    out = T.copy()
    c = T.shape[0]
    sel = np.flatnonzero(np.abs(lag_s / step_s - 1.0) > 1e-6)
    Q = np.broadcast_to(np.eye(c + 1), (sel.size, c + 1, c + 1)).copy()
    Q[:, :c] = np.swapaxes(T[:, sel, :], 0, 1)  # (classes, c, c + 1)
    R = np.maximum(fractional_powers(Q, step_s / lag_s[sel])[:, :c], 0.0)
    out[:, sel, :] = np.swapaxes(R / R.sum(axis=-1, keepdims=True), 0, 1)
    return out


class MatrixTransport:
    """The DEM's one-lag transition matrix of every compartment, the inlet zone included.

    Rock tagged in compartment ``c`` (inlet zone or stage) is found one
    characteristic time later in any compartment or has left
    (``StageStatistics.destinations``, ``RunStatistics.inlet_destinations``),
    so jumps over more than one stage and the time rock spends above stage 1
    (feed chute, rock thrown up) are as measured; the fresh feed enters the
    inlet zone. A class whose matrix was measured at a lag other than the
    model step (a table whose runs have different characteristic times) gets
    the matrix's fractional power ``step / lag``. Stage parameters without
    these fields fall back to the ``regions`` streams (with a note).
    """

    name = "dem_matrix"
    requires = ("transition",)

    def transition(self, params: StageParameters) -> Transition:
        if params.transition is None:
            return Transition.from_streams(RegionWeightedTransport().streams(params),
                                           note="transport: the stage parameters have no one-lag destinations; "
                                           "used the three streams ('regions')")
        T = np.asarray(params.transition, dtype=float)
        lag = params.transition_lag_s
        if lag is not None:
            T = _to_step(T, np.asarray(lag, dtype=float), float(params.characteristic_time_s))
        return Transition(T, feed_compartment=0)

    def streams(self, params: StageParameters) -> np.ndarray:
        """The three streams per stage implied by the matrix (kickback / refeed / pass-through)."""
        T = self.transition(params).matrix
        s = np.arange(1, T.shape[0])
        up = np.cumsum(T[1:], axis=-1)  # (S, N, S+2)
        kick = up[np.arange(s.size), :, s - 1]
        ref = T[s, :, s]
        return np.stack([kick, ref, 1.0 - kick - ref], axis=-1)

    def __repr__(self) -> str:
        return "MatrixTransport()"


class FillingMatrixTransport:
    """``dem_matrix`` whose speed depends on how full the mill is, as the DEM measured while it filled.

    At steady state (mill hold-up at or above its steady value) this is
    :class:`MatrixTransport` exactly, so the steady hold-ups, residence times and
    products are the same. While the mill fills, a step at mill fill ``h``
    (hold-up over the steady hold-up) moves every compartment's rock by
    ``g(h) (P - I)`` instead of ``P - I``, ``g = 1 / ratio(h)`` with ``ratio`` the
    DEM's mean residence of the chain measured at that fill over the steady one
    (``RunStatistics.filling_transport``; a table's runs pooled): rock leaves a
    compartment ``g`` times as often, to the same destinations. The expected-value
    march uses it; the steady solve and the Monte-Carlo solver use ``P``.
    A point with ``ratio <= h`` is left out (with a note): there the mill could
    not fill past ``h`` (its quasi-steady hold-up ``ratio`` times the steady one),
    which the DEM run it was measured in did; without such points every fill
    below 1 has ``ratio > h`` (linear segments up to ``(1, 1)``), so the march
    reaches the steady state. Stage parameters without filling data give
    ``dem_matrix`` (with a note).
    """

    name = "dem_matrix_fill"
    requires = ("transition", "filling_transport")

    def transition(self, params: StageParameters) -> Transition:
        tr = MatrixTransport().transition(params)
        if params.filling_fill is None or params.filling_residence_ratio is None:
            note = "transport: the stage parameters have no filling transport; used the steady matrix throughout"
            return dataclasses.replace(tr, note="; ".join(n for n in (tr.note, note) if n))
        h = np.asarray(params.filling_fill, dtype=float)
        r = np.asarray(params.filling_residence_ratio, dtype=float)
        ok = r > h  # at r <= h the mill could not fill past h: it did in the DEM, so such a point is noise
        note = tr.note
        if not ok.all():
            if r.ndim == 2:
                what = (f"bridged by their neighbours in {int((~ok).any(axis=1).sum())} of {r.shape[0]} size "
                        f"classes (fills {np.round(h[~ok.all(axis=0)], 2).tolist()})")
            else:
                what = f"left out (fills {np.round(h[~ok], 2).tolist()})"
            note = "; ".join(n for n in (note, f"transport: filling points with residence ratio <= fill {what}") if n)
        if r.ndim == 1:
            return dataclasses.replace(tr, note=note, filling=(h[ok], r[ok]) if ok.any() else None)
        # per class: a point left out is bridged by the class's own neighbours (np.interp), or
        # by (1, 1) above its last kept point; a class with none kept runs at the steady speed
        hh = np.append(h, 1.0)
        r = np.array([np.interp(h, hh[np.append(o, True)], np.append(ri, 1.0)[np.append(o, True)])
                      for ri, o in zip(r, ok, strict=True)])
        return dataclasses.replace(tr, note=note, filling=(h, r))

    def streams(self, params: StageParameters) -> np.ndarray:
        """The steady streams (as ``dem_matrix``)."""
        return MatrixTransport().streams(params)

    def __repr__(self) -> str:
        return "FillingMatrixTransport()"


class RegionWeightedTransport:
    """DEM streams; when region data exist, the solid-fraction-weighted average over regions.

    Paper Section 3.1.2: the stage's stream fractions are
    ``sum_r w_r * streams_r`` with ``w_r`` the solid-fraction weights of the 6
    horizontal regions. Without region data the bulk streams are used.
    """

    name = "regions"
    requires = ("streams", "region_weights", "region_streams")

    def streams(self, params: StageParameters) -> np.ndarray:
        if params.region_weights is None or params.region_streams is None:
            return params.streams
        s = np.einsum("snr,snrk->snk", params.region_weights, params.region_streams)
        return s / s.sum(axis=-1, keepdims=True)

    def __repr__(self) -> str:
        return "RegionWeightedTransport()"


class BulkTransport:
    """DEM bulk streams per stage (ignores any region data)."""

    name = "bulk"
    requires = ("streams",)

    def streams(self, params: StageParameters) -> np.ndarray:
        return params.streams

    def __repr__(self) -> str:
        return "BulkTransport()"


class DemImpacts:
    """Impact statistics exactly as measured by the DEM (no speed correction)."""

    name = "dem"
    requires = ("hit_probability", "primary_velocity", "secondary_lambda", "secondary_velocity")

    def impacts(self, params: StageParameters, stage_speeds_rpm: np.ndarray) -> ImpactStatistics:
        return ImpactStatistics(params.hit_probability, params.primary_velocity,
                                params.secondary_lambda, params.secondary_velocity, params.secondary_count)

    def __repr__(self) -> str:
        return "DemImpacts()"


class SpeedScaledImpacts:
    """DEM impact statistics with velocities scaled by the stage speed ratio.

    Primary (flinger) and secondary velocities are multiplied by
    ``speed / design_speed`` of their stage (flinger tip speed is proportional
    to shaft speed); hit probabilities, Poisson means and the transport are
    used as measured. A first-order correction for running off the design
    point; the provider still warns that the statistics were measured elsewhere.

    Parameters whose ``velocities_at_requested_speeds`` is True (a provider
    that predicts at the operating point, e.g. the surrogate) are used as
    given: they are not rescaled a second time.
    """

    name = "speed_scaled"
    requires = ("hit_probability", "primary_velocity", "secondary_lambda", "secondary_velocity",
                "design_stage_speeds_rpm")

    def impacts(self, params: StageParameters, stage_speeds_rpm: np.ndarray) -> ImpactStatistics:
        if getattr(params, "velocities_at_requested_speeds", False):
            return ImpactStatistics(params.hit_probability, params.primary_velocity,
                                    params.secondary_lambda, params.secondary_velocity, params.secondary_count)
        design = params.design_stage_speeds_rpm
        speeds = np.asarray(stage_speeds_rpm, dtype=float) if stage_speeds_rpm is not None else design
        ratio = np.where(design > 0, speeds / np.where(design > 0, design, 1.0), 1.0)
        f = ratio[:, None, None]
        return ImpactStatistics(params.hit_probability, params.primary_velocity.scaled(f),
                                params.secondary_lambda, params.secondary_velocity.scaled(f),
                                params.secondary_count)

    def __repr__(self) -> str:
        return "SpeedScaledImpacts()"


class NoSecondaryImpacts(SpeedScaledImpacts):
    """As ``speed_scaled`` but without secondary impacts (lambda = 0)."""

    name = "primary_only"

    def impacts(self, params: StageParameters, stage_speeds_rpm: np.ndarray) -> ImpactStatistics:
        s = super().impacts(params, stage_speeds_rpm)
        return ImpactStatistics(s.hit_probability, s.primary_velocity,
                                np.zeros_like(s.secondary_lambda), s.secondary_velocity)

    def __repr__(self) -> str:
        return "NoSecondaryImpacts()"


_APPEARANCE_TABLES: dict[tuple, np.ndarray] = {}


class AbT10Breakage:
    """Size-dependent Ab-t10 breakage (paper Eqs. 11-12) with damage.

    ``P_b = 1 - exp(-b E_cs L / (L_ref (1 - D)))``; a broken rock's fragments
    follow the t10-tn appearance function with ``t10 = A P_b``.

    Parameters
    ----------
    ore : BreakageParameters
        ``A_pct``, ``b_t_per_kwh``, ``l_ref_mm`` and the t10-tn constants ``tn``.
    """

    name = "ab_t10"
    requires = ("A_pct", "b_t_per_kwh", "l_ref_mm", "tn")
    #: t10 convention (``msmill.breakage.T10_CONVENTIONS``): broken rock ``t10 = A P_b``.
    t10_convention = "paper"

    #: Breakage probabilities at which appearance columns are tabulated
    #: (``(k / 1024)**2``; the interpolation error in a column is below 5e-4).
    TABLE_NODES = 1025

    def __init__(self, ore: BreakageParameters) -> None:
        self.ore = ore

    def appearance_table(self, edges_mm: np.ndarray) -> np.ndarray:
        """Appearance columns tabulated at ``pb_k = (k / 1024)**2``: shape (1025, N, N).

        Cached per (grid, A, t_n constants) for the whole process.
        """
        edges = np.asarray(edges_mm, dtype=float)
        tn = self.ore.tn
        key = (edges.tobytes(), self.ore.A_pct, None if tn is None else (tuple(tn.k), tuple(tn.s)))
        tab = _APPEARANCE_TABLES.get(key)
        if tab is None:
            u = np.linspace(0.0, 1.0, self.TABLE_NODES) ** 2
            t10 = self.ore.A_pct * u[:, None]  # (nodes, 1): one t10 for every parent
            B = _bk.appearance_matrix(SizeGrid(edges), t10, self.ore.tn)  # (nodes, i, j)
            tab = np.ascontiguousarray(np.swapaxes(B, -1, -2))  # (nodes, parent j, class i)
            if len(_APPEARANCE_TABLES) >= 16:
                _APPEARANCE_TABLES.pop(next(iter(_APPEARANCE_TABLES)))
            _APPEARANCE_TABLES[key] = tab
        return tab

    def probability(self, ecs_kwh_t, size_mm, damage):
        return np.asarray(_bk.breakage_probability(ecs_kwh_t, size_mm, self.ore.b_t_per_kwh,
                                                   self.ore.l_ref_mm, damage))

    def direct_fragments(self, edges_mm: np.ndarray, pb: np.ndarray) -> np.ndarray:
        """Appearance columns ``(parent, class)`` at one ``pb`` per parent class, computed exactly (no table).

        What a fit evaluates at every step (``A`` changes, so the tables would be rebuilt each time);
        equal to :meth:`fragments` to the tabulation error.
        """
        B = _bk.appearance_matrix(SizeGrid(np.asarray(edges_mm, dtype=float)),
                                  self.ore.A_pct * np.asarray(pb, dtype=float), self.ore.tn)  # (class, parent)
        return np.ascontiguousarray(B.T)

    def fragments(self, edges_mm, parent, pb):
        """Appearance columns at ``t10 = A pb``, linear in ``pb`` between tabulated nodes.

        A convex combination of two valid columns, so mass is conserved exactly and
        nothing lands above the parent class.
        """
        tab = self.appearance_table(edges_mm)
        pos = np.sqrt(np.clip(np.asarray(pb, dtype=float), 0.0, 1.0)) * (self.TABLE_NODES - 1)
        j = np.minimum(pos.astype(int), self.TABLE_NODES - 2)
        frac = (pos - j)[..., None]
        parent = np.broadcast_to(np.asarray(parent, dtype=int), pos.shape)
        return (1.0 - frac) * tab[j, parent] + frac * tab[j + 1, parent]

    def expected_fragments(self, edges_mm, pb, weights):
        """``sum_q weights * fragments`` for parents along axis 0 (optional fast path).

        Parameters
        ----------
        edges_mm : ndarray (N+1,)
            Class edges (mm).
        pb : ndarray (N, Q, D)
            Breakage probability setting ``t10`` for parent class ``i`` (axis 0),
            quadrature node ``q`` and damage class ``d``.
        weights : ndarray (N, Q, D)
            Mass weights to sum over ``q``.

        Returns
        -------
        ndarray (N, N, D)
            ``F[k, i, d]``: weighted fragment mass in class ``k``. Equal to
            ``einsum("iqd,iqdk->kid", weights, fragments(edges, i, pb))`` but
            accumulates the weights on the table nodes first (one batched
            matrix product instead of a gather of every column).
        """
        tab = self.appearance_table(edges_mm)  # (nodes, parent, class)
        n_nodes = self.TABLE_NODES
        n, _, nd = pb.shape
        pos = np.sqrt(np.clip(pb, 0.0, 1.0)) * (n_nodes - 1)
        j = np.minimum(pos.astype(int), n_nodes - 2)
        frac = pos - j
        base = (np.arange(n)[:, None, None] * nd + np.arange(nd)[None, None, :]) * n_nodes
        idx = (base + j).ravel()
        size = n * nd * n_nodes
        W = (np.bincount(idx, weights=(weights * (1.0 - frac)).ravel(), minlength=size)
             + np.bincount(idx + 1, weights=(weights * frac).ravel(), minlength=size))
        W = W.reshape(n, nd, n_nodes)
        F = np.matmul(W, self._parent_major(edges_mm, tab))  # (N, nd, N_k)
        return np.transpose(F, (2, 0, 1))

    def _parent_major(self, edges_mm, tab):
        key = ("pm", id(tab))
        pm = _APPEARANCE_TABLES.get(key)
        if pm is None:
            pm = np.ascontiguousarray(np.transpose(tab, (1, 0, 2)))  # (parent, nodes, class)
            _APPEARANCE_TABLES[key] = pm
        return pm

    def __repr__(self) -> str:
        o = self.ore
        return (f"{type(self).__name__}({o.name}: A={o.A_pct:g} %, b={o.b_t_per_kwh:g} t/kWh, "
                f"L_ref={o.l_ref_mm:g} mm)")


class JkT10Breakage(AbT10Breakage):
    """Ab-t10 breakage read in the JK drop-weight convention (the default).

    ``P_b = 1 - exp(-b E_cs L / (L_ref (1 - D)))`` as in :class:`AbT10Breakage`,
    but a broken rock's fragments have ``t10 = A``, so that after one impact the
    t10 of the whole population (broken and unbroken rock) is the JK law
    ``A (1 - exp(-b E_cs L / L_ref))`` in which ``A`` and ``b`` are published and
    fitted (docs/breakage.md, "The t10 convention").
    """

    name = "jk_t10"
    t10_convention = "jk"

    def columns(self, edges_mm: np.ndarray) -> np.ndarray:
        """Appearance columns at ``t10 = A``: ``(parent, class)``, cached per (grid, A, t_n constants)."""
        edges = np.asarray(edges_mm, dtype=float)
        tn = self.ore.tn
        key = ("jk", edges.tobytes(), self.ore.A_pct, None if tn is None else (tuple(tn.k), tuple(tn.s)))
        col = _APPEARANCE_TABLES.get(key)
        if col is None:
            B = _bk.appearance_matrix(SizeGrid(edges), self.ore.A_pct, tn)  # (class i, parent j)
            col = np.ascontiguousarray(B.T)
            if len(_APPEARANCE_TABLES) >= 16:
                _APPEARANCE_TABLES.pop(next(iter(_APPEARANCE_TABLES)))
            _APPEARANCE_TABLES[key] = col
        return col

    def direct_fragments(self, edges_mm: np.ndarray, pb: np.ndarray) -> np.ndarray:
        """Appearance columns ``(parent, class)``: the ``t10 = A`` column of every parent, whatever ``pb``
        (overrides the parent's ``t10 = A P_b`` columns: a fit must use this model's own convention)."""
        return self.columns(edges_mm).copy()

    def fragments(self, edges_mm, parent, pb):
        """The appearance column at ``t10 = A`` for every ``pb``."""
        pb = np.asarray(pb, dtype=float)
        parent = np.broadcast_to(np.asarray(parent, dtype=int), pb.shape)
        return self.columns(edges_mm)[parent]

    def expected_fragments(self, edges_mm, pb, weights):
        """``sum_q weights * fragments`` (parents along axis 0): every column is the ``t10 = A`` one."""
        w = np.asarray(weights, dtype=float).sum(axis=1)  # (N, D)
        return np.einsum("id,ik->kid", w, self.columns(edges_mm))


class EnergyT10Breakage(AbT10Breakage):
    """Ab-t10 selection with fragments that keep getting finer past the energy that breaks every rock.

    ``P_b = 1 - exp(-x)`` with the Eq. 11 exponent ``x = b E_cs L / (L_ref (1 - D))``,
    as in :class:`AbT10Breakage`; a broken rock's fragments have

        ``t10 = A (1 - exp(-c x))``

    driven by the full specific energy through ``x``, which keeps growing once
    ``P_b`` has reached 1. The fineness ratio ``c`` (``fineness_ratio``,
    dimensionless) is the ratio of the energy scales of fragment fineness and
    of first fracture: ``c = 1`` gives ``ab_t10``'s fragments (``t10 = A P_b``),
    ``c -> infinity`` ``jk_t10``'s (``t10 = A`` at any energy), ``c < 1``
    fragments that go on getting finer over ``1/c`` times the energy that
    breaks nearly every rock (the t10-energy law of the JK drop-weight test,
    ``t10 = A (1 - exp(-b' E))`` with its own ``b' = c b``, applied to the
    fragments; Shi and Kojovic, Minerals Engineering 20 (2007) 1454, drive
    t10 by the whole specific energy in the same way). docs/breakage.md
    section 5.2.

    The solvers index the fragments by :meth:`fragment_index`
    (``t10 / A``) instead of ``P_b``, so the tabulated columns of
    :class:`AbT10Breakage` (``t10 = A u`` at node ``u``) serve unchanged.

    Parameters
    ----------
    ore : BreakageParameters
        ``A_pct``, ``b_t_per_kwh``, ``l_ref_mm``, ``tn`` and ``fineness_ratio``
        (None: :data:`DEFAULT_FINENESS_RATIO`, noted in ``ore.notes``).
    fineness_ratio : float, optional
        Overrides the ore's.
    """

    name = "energy_t10"
    requires = ("A_pct", "b_t_per_kwh", "l_ref_mm", "tn")  # fineness_ratio: a default, noted, when the ore has none
    t10_convention = "energy"

    def __init__(self, ore: BreakageParameters, fineness_ratio: float | None = None) -> None:
        c = ore.fineness_ratio if fineness_ratio is None else fineness_ratio
        notes = ore.notes
        if c is None:
            c = DEFAULT_FINENESS_RATIO
            notes = (*notes, f"energy_t10 fineness ratio of {ore.name} is the default {c:g} "
                     "(ab_t10's fragments): fit it to single-impact tests (msmill calibrate)")
        if not (np.isfinite(c) and c > 0):
            raise MsmillInputError("fineness_ratio", c, "a finite number > 0")
        super().__init__(dataclasses.replace(ore, fineness_ratio=float(c), notes=notes))

    def fragment_index(self, ecs_kwh_t, size_mm, damage):
        """``t10 / A = 1 - exp(-c x)`` of the fragments (``x`` the Eq. 11 exponent; no underflow at large x)."""
        o = self.ore
        x = (o.b_t_per_kwh * np.asarray(ecs_kwh_t, dtype=float) * np.asarray(size_mm, dtype=float)
             / (o.l_ref_mm * (1.0 - np.asarray(damage, dtype=float))))
        return -np.expm1(-o.fineness_ratio * np.maximum(x, 0.0))

    def __repr__(self) -> str:
        return f"{super().__repr__()[:-1]}, c={self.ore.fineness_ratio:.4g})"


def fragment_index(breakage: Any, ecs_kwh_t: np.ndarray, size_mm: np.ndarray, damage: np.ndarray,
                   pb: np.ndarray) -> np.ndarray:
    """What indexes ``breakage``'s fragments: its ``fragment_index`` where it has one, else ``pb``."""
    f = getattr(breakage, "fragment_index", None)
    return pb if f is None else np.broadcast_to(f(ecs_kwh_t, size_mm, damage), np.shape(pb))


def simulate_lab_test(breakage: BreakageModel, size_mm: np.ndarray, ecs_kwh_t: np.ndarray) -> np.ndarray:
    """Population t10 (%) of a drop-weight test simulated through a breakage sub-model.

    One impact per rock of size ``size_mm`` at ``ecs_kwh_t`` (intact rock): a
    fraction ``probability`` breaks into ``fragments``, the rest stays whole;
    the result is the % of all the mass passing a tenth of the rock size. The
    fragments are read on a grid (in units of the rock size, the appearance
    function depends only on size ratios) with the parent class centred on the
    rock size and an edge at a tenth of it.
    """
    size = np.asarray(size_mm, dtype=float)
    e = np.asarray(ecs_kwh_t, dtype=float)
    size, e = np.broadcast_arrays(size, e)
    edges = np.concatenate([0.1 * 2.0 ** (np.arange(-20, 7) / 2.0), [1.25]])  # parent class [0.8, 1.25]
    parent = edges.size - 2
    below = int(np.flatnonzero(np.isclose(edges, 0.1))[0])  # classes < below lie under a tenth
    pb = np.asarray(breakage.probability(e, size, np.zeros_like(e)), dtype=float)
    cols = breakage.fragments(edges, np.full(pb.shape, parent),
                              fragment_index(breakage, e, size, np.zeros_like(e), pb))
    return 100.0 * pb * cols[..., :below].sum(axis=-1)


def lab_test(name: str, tn: Any = None):
    """``lab_test(size_mm, ecs_kwh_t, A_pct, b_t_per_kwh, l_ref_mm) -> t10_pct`` for :func:`msmill.calibration.calibrate`.

    Builds the named breakage sub-model at the trial parameters and simulates the
    drop-weight test through it (:func:`simulate_lab_test`).
    """
    factory = SUBMODELS["breakage"].get(name)
    if factory is None:
        raise MsmillInputError("breakage", name, did_you_mean(name, list(SUBMODELS["breakage"])))

    def run(size_mm, ecs_kwh_t, A_pct, b_t_per_kwh, l_ref_mm):
        ore = BreakageParameters("calibration", A_pct=A_pct, b_t_per_kwh=b_t_per_kwh, l_ref_mm=l_ref_mm, tn=tn)
        return simulate_lab_test(factory(ore), size_mm, ecs_kwh_t)

    run.convention = getattr(factory, "t10_convention", name)  # type: ignore[attr-defined]
    return run


class NoBreakage:
    """Rock that never breaks (``P_b = 0``): for transport checks against DEM runs of unbreakable rock."""

    name = "none"
    requires: tuple[str, ...] = ()

    def __init__(self, ore: BreakageParameters | None = None) -> None:
        self.ore = ore

    def probability(self, ecs_kwh_t, size_mm, damage):
        return np.zeros(np.broadcast(ecs_kwh_t, size_mm, damage).shape)

    def fragments(self, edges_mm, parent, pb):
        """The parent's own class (never used with ``P_b = 0``; keeps the protocol's invariants)."""
        n = np.asarray(edges_mm).size - 1
        parent = np.broadcast_to(np.asarray(parent, dtype=int), np.shape(pb))
        return (parent[..., None] == np.arange(n)).astype(float)

    def __repr__(self) -> str:
        return "NoBreakage()"


class TavaresDamage:
    """Tavares damage of surviving rocks, consistent with Eq. 11 (domain notes Sec. 4).

    Eq. 11 is the breakage probability of rocks whose fracture energies are
    exponential with mean ``E_f = L_ref (1 - D) / (b L)`` (kWh/t). A rock that
    survives an impact of energy ``E`` has, by the memoryless property,
    expected fracture energy ``E + E_f``; its damage increment solves
    Tavares' equation at the energy ratio ``r = E / (E + E_f)`` and the
    accumulated damage combines as ``1 - D' = (1 - D)(1 - dD)``. A rock whose
    damage reaches ``threshold`` breaks.

    Parameters
    ----------
    ore : BreakageParameters
        ``b_t_per_kwh``, ``l_ref_mm``, ``gamma`` and ``damage_threshold``.
    """

    name = "tavares"
    requires = ("b_t_per_kwh", "l_ref_mm", "gamma", "damage_threshold")

    def __init__(self, ore: BreakageParameters) -> None:
        self.ore = ore
        self.threshold = float(ore.damage_threshold)
        # damage increment tabulated against the energy ratio (smooth, monotone)
        r = np.linspace(0.0, 1.0, 4097)
        r[-1] = np.nextafter(1.0, 0.0)
        self._r = r
        self._dd = np.asarray(_bk.damage_increment(r, ore.gamma))
        self._slope = np.diff(self._dd) / np.diff(r)

    def after_impact(self, ecs_kwh_t, size_mm, damage):
        d = np.asarray(damage, dtype=float)
        r = np.asarray(_bk.survivor_energy_ratio(ecs_kwh_t, size_mm, self.ore.b_t_per_kwh,
                                                 self.ore.l_ref_mm, d))
        # tabulated damage_increment(r, gamma), linear between nodes: np.interp on the uniform
        # table, its interval found by index arithmetic instead of a binary search
        j = np.minimum((r * (self._r.size - 1)).astype(np.intp), self._r.size - 2)
        dd = self._dd[j] + (r - self._r[j]) * self._slope[j]
        return np.minimum(1.0 - (1.0 - d) * (1.0 - dd), np.nextafter(1.0, 0.0))

    def __repr__(self) -> str:
        return f"TavaresDamage(gamma={self.ore.gamma:g}, threshold={self.threshold:g})"


class NoDamage:
    """Rocks that survive an impact are as strong as before (independent impacts)."""

    name = "none"
    requires: tuple[str, ...] = ()

    def __init__(self, ore: BreakageParameters | None = None) -> None:
        self.threshold = 1.0

    def after_impact(self, ecs_kwh_t, size_mm, damage):
        return np.broadcast_to(np.asarray(damage, dtype=float),
                               np.broadcast(ecs_kwh_t, size_mm, damage).shape).copy()

    def __repr__(self) -> str:
        return "NoDamage()"


# ------------------------------------------------------------------- registry
#: One lookup table per step: name -> factory. Factories of breakage and damage
#: models take the :class:`BreakageParameters`; the others take nothing.
SUBMODELS: dict[str, dict[str, Any]] = {
    "transport": {"dem_matrix": MatrixTransport, "regions": RegionWeightedTransport, "bulk": BulkTransport,
                  "dem_matrix_fill": FillingMatrixTransport},
    "impacts": {"speed_scaled": SpeedScaledImpacts, "dem": DemImpacts,
                "primary_only": NoSecondaryImpacts},
    "breakage": {"jk_t10": JkT10Breakage, "ab_t10": AbT10Breakage, "energy_t10": EnergyT10Breakage,
                 "none": NoBreakage},
    "damage": {"tavares": TavaresDamage, "none": NoDamage},
}
DEFAULTS: dict[str, str] = {"transport": "dem_matrix_fill", "impacts": "speed_scaled",
                            "breakage": "jk_t10", "damage": "tavares"}
_NEEDS_ORE = ("breakage", "damage")
_PROTOCOLS = {"transport": TransportModel, "impacts": ImpactModel,
              "breakage": BreakageModel, "damage": DamageModel}


def did_you_mean(value: str, choices: list[str]) -> str:
    """``"one of a, b (did you mean 'a'?)"`` for error messages."""
    close = difflib.get_close_matches(str(value), choices, n=1, cutoff=0.4)
    hint = f" (did you mean {close[0]!r}?)" if close else ""
    return "one of " + ", ".join(repr(c) for c in choices) + hint


def resolve(step: str, spec: Any, ore: BreakageParameters | None) -> Any:
    """Turn a name, an instance or ``None`` (the default) into a sub-model of ``step``."""
    if step not in SUBMODELS:
        raise MsmillInputError("model step", step, did_you_mean(step, list(SUBMODELS)))
    if spec is None:
        spec = DEFAULTS[step]
    if isinstance(spec, str):
        table = SUBMODELS[step]
        if spec not in table:
            raise MsmillInputError(f"model.{step}", spec, did_you_mean(spec, list(table)))
        factory = table[spec]
        return factory(ore) if step in _NEEDS_ORE else factory()
    if not isinstance(spec, _PROTOCOLS[step]):
        raise MsmillInputError(f"model.{step}", type(spec).__name__,
                               f"a name or an object implementing {_PROTOCOLS[step].__name__}")
    return spec
