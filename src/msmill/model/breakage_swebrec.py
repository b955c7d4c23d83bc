"""Alternative breakage sub-model: Vogel-Peukert selection with a threshold + Swebrec appearance.

Selection (breakage probability of one impact; Vogel & Peukert, Powder
Technol. 129 (2003) 101-110 and Chem. Eng. Sci. 58 (2003) 2127; their
``S = 1 - exp(-f_Mat x k (W_m,kin - W_m,min))`` with ``x W_m,min = const``)::

    P_b = 1 - exp(-b_t_per_kwh (L / L_ref) max(E / (1 - D) - E_min L_ref / L, 0))

with ``E`` the specific impact energy (kWh/t), ``L`` the rock size (mm),
``b_t_per_kwh`` the slope at ``L_ref`` (t/kWh; ``f_Mat x`` of Vogel-Peukert in
these units), ``E_min`` the threshold energy at ``L_ref`` (kWh/t; it scales as
``1/L``) and ``D`` the accumulated damage (fracture energies scale by
``1 - D``, as in ``docs/breakage.md``). With ``E_min = 0`` this is Eq. 11 and
``b_t_per_kwh`` is the ore's ``b``.

Appearance (Swebrec function, Ouchterlony, Fragblast 9 (2005) 1-25): the
cumulative passing of the fragments of a parent of size ``x`` is::

    P(y) = 1 / (1 + (ln(x / y) / ln(x / x50)) ** beta)     (y < x; 100 % at y >= x)

with the undulation exponent ``beta`` (``swebrec_b``) and the median ``x50``
set by ``t10 = A P_b`` through ``P(x / 10) = t10``:
``ln(x / x50) = ln(10) / (100 / t10 - 1) ** (1 / beta)``. So one shape
parameter replaces the five t10-tn power laws, and the whole curve (fines
included) follows from ``t10`` and ``beta``.

Defaults from an ore (:meth:`VogelSwebrecBreakage.from_ore`): ``k = b``,
``E_min = 0`` (no threshold until fitted), ``A`` the ore's, ``beta`` the
least-squares fit of the Swebrec curve to the ore's t10-tn knots at
``t10 = A / 2`` (log passing). These are starting points to be fitted to
laboratory single-impact tests (``msmill.model.fitting``), not measured values.

Damage: the shipped Tavares damage sub-model computes the survivor's energy
ratio from Eq. 11 (``b``, ``L_ref``), not from this selection function; with
this sub-model prefer ``damage = "none"`` or read the damage as approximate.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import lru_cache

import numpy as np

from msmill import breakage as _bk
from msmill.model.submodels import _APPEARANCE_TABLES, SUBMODELS, AbT10Breakage, BreakageParameters

__all__ = ["SwebrecParameters", "VogelSwebrecBreakage", "swebrec_passing"]

T10_CAP_PCT = 99.0


def swebrec_passing(rel_size: np.ndarray, t10_pct: np.ndarray, beta: float) -> np.ndarray:
    """Swebrec cumulative passing (%) at ``y / x`` (< 1) for ``t10`` (%) and exponent ``beta``."""
    r = np.asarray(rel_size, dtype=float)
    t10 = np.clip(np.asarray(t10_pct, dtype=float), 0.0, T10_CAP_PCT)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        lnx50 = np.log(10.0) / (100.0 / t10 - 1.0) ** (1.0 / beta)  # ln(x / x50); 0 when t10 = 0
        q = np.log(1.0 / r) / lnx50
        p = 100.0 / (1.0 + q ** beta)
    p = np.where(t10 <= 0.0, 0.0, p)
    return np.where(r >= 1.0, 100.0, np.nan_to_num(p, nan=0.0))


@dataclass(frozen=True)
class SwebrecParameters:
    """Parameters of :class:`VogelSwebrecBreakage` (units in the names).

    Attributes
    ----------
    A_pct : float
        Largest ``t10`` (%), ``t10 = A P_b``.
    b_t_per_kwh : float
        Selection slope at ``L_ref`` (t/kWh).
    e_min_kwh_t : float
        Threshold specific energy at ``L_ref`` (kWh/t), scaling as ``1/L``.
    swebrec_b : float
        Swebrec undulation exponent ``beta`` (dimensionless).
    l_ref_mm : float
        Reference size (mm).
    name : str
        Ore name.
    """

    A_pct: float
    b_t_per_kwh: float
    e_min_kwh_t: float
    swebrec_b: float
    l_ref_mm: float
    name: str = "ore"


@lru_cache(maxsize=32)
def _beta_from_tn(A_pct: float, tn_k: tuple, tn_s: tuple) -> float:
    """Least-squares Swebrec ``beta`` matching the t10-tn knots at ``t10 = A / 2`` (log passing)."""
    from scipy.optimize import minimize_scalar

    t10 = 0.5 * A_pct
    target = np.minimum(np.asarray(tn_k) * t10 ** np.asarray(tn_s), 100.0)
    rel = 1.0 / np.asarray(_bk.TN_SIZES, dtype=float)

    def loss(beta: float) -> float:
        p = swebrec_passing(rel, t10, beta)
        return float(np.sum((np.log(np.maximum(p, 1e-9)) - np.log(target)) ** 2))

    return float(minimize_scalar(loss, bounds=(0.2, 10.0), method="bounded").x)


class VogelSwebrecBreakage(AbT10Breakage):
    """Vogel-Peukert selection with a size-scaled threshold and Swebrec fragments (module docstring)."""

    name = "vogel_swebrec"
    requires = ("A_pct", "b_t_per_kwh", "e_min_kwh_t", "swebrec_b", "l_ref_mm")

    def __init__(self, params: SwebrecParameters) -> None:
        self.params = params
        # the tabulation machinery of AbT10Breakage reads ``self.ore.A_pct``
        self.ore = BreakageParameters(name=params.name, A_pct=params.A_pct, b_t_per_kwh=params.b_t_per_kwh,
                                      l_ref_mm=params.l_ref_mm)

    @classmethod
    def from_ore(cls, ore: BreakageParameters, **overrides: float) -> VogelSwebrecBreakage:
        """Defaults from an ore (module docstring); keyword arguments override fields."""
        tn = ore.tn if ore.tn is not None else _bk.default_tn_constants()
        beta = _beta_from_tn(float(ore.A_pct), tuple(tn.k), tuple(tn.s))
        p = SwebrecParameters(A_pct=ore.A_pct, b_t_per_kwh=ore.b_t_per_kwh, e_min_kwh_t=0.0, swebrec_b=beta,
                              l_ref_mm=ore.l_ref_mm, name=ore.name)
        return cls(replace(p, **overrides))

    def probability(self, ecs_kwh_t, size_mm, damage):
        p = self.params
        L = np.asarray(size_mm, dtype=float)
        e = np.asarray(ecs_kwh_t, dtype=float) / (1.0 - np.asarray(damage, dtype=float))
        excess = np.maximum(e - p.e_min_kwh_t * p.l_ref_mm / L, 0.0)
        return -np.expm1(-p.b_t_per_kwh * (L / p.l_ref_mm) * excess)

    def appearance_table(self, edges_mm: np.ndarray) -> np.ndarray:
        """Swebrec columns tabulated at ``pb_k = (k / 1024)**2``: shape (1025, N, N), cached."""
        edges = np.asarray(edges_mm, dtype=float)
        p = self.params
        key = ("swebrec", edges.tobytes(), p.A_pct, p.swebrec_b)
        tab = _APPEARANCE_TABLES.get(key)
        if tab is None:
            t10 = p.A_pct * np.linspace(0.0, 1.0, self.TABLE_NODES) ** 2  # (nodes,)
            tab = swebrec_columns(edges, t10, p.swebrec_b)
            if len(_APPEARANCE_TABLES) >= 16:
                _APPEARANCE_TABLES.pop(next(iter(_APPEARANCE_TABLES)))
            _APPEARANCE_TABLES[key] = tab
        return tab

    def direct_fragments(self, edges_mm: np.ndarray, pb: np.ndarray) -> np.ndarray:
        """Exact Swebrec columns ``[parent, class]`` at one ``pb`` per parent (no table)."""
        return swebrec_columns_per_parent(edges_mm, self.params.A_pct * np.asarray(pb), self.params.swebrec_b)

    def __repr__(self) -> str:
        p = self.params
        return (f"VogelSwebrecBreakage({p.name}: A={p.A_pct:.4g} %, k={p.b_t_per_kwh:.4g} t/kWh, "
                f"E_min={p.e_min_kwh_t:.4g} kWh/t at L_ref={p.l_ref_mm:.4g} mm, beta={p.swebrec_b:.4g})")


def swebrec_columns_per_parent(edges_mm: np.ndarray, t10_pct: np.ndarray, beta: float) -> np.ndarray:
    """Fragment mass fractions ``[parent j, class i]`` with one ``t10`` per parent class."""
    edges = np.asarray(edges_mm, dtype=float)
    mids = np.sqrt(edges[:-1] * edges[1:])
    rel = edges[None, 1:] / mids[:, None]
    cum = swebrec_passing(rel, np.asarray(t10_pct, dtype=float)[:, None], beta) / 100.0
    cum[..., -1] = 1.0
    cum = np.maximum.accumulate(cum, axis=-1)
    frac = np.clip(np.diff(np.concatenate([np.zeros((cum.shape[0], 1)), cum], axis=-1), axis=-1), 0.0, None)
    return frac / frac.sum(axis=-1, keepdims=True)


def swebrec_columns(edges_mm: np.ndarray, t10_pct: np.ndarray, beta: float) -> np.ndarray:
    """Fragment mass fractions ``[node, parent j, class i]`` of Swebrec curves (columns sum to 1).

    Parent size is the class mid; the cumulative curve is 100 % at edges at or
    above it (nothing coarser than the parent class) and class 0 takes all mass
    below ``edges_mm[1]``.
    """
    edges = np.asarray(edges_mm, dtype=float)
    mids = np.sqrt(edges[:-1] * edges[1:])
    rel = edges[None, 1:] / mids[:, None]  # (parent, edge k+1)
    cum = swebrec_passing(rel[None], np.asarray(t10_pct, dtype=float)[:, None, None], beta) / 100.0
    cum[..., -1] = 1.0
    cum = np.maximum.accumulate(cum, axis=-1)
    frac = np.diff(np.concatenate([np.zeros((*cum.shape[:-1], 1)), cum], axis=-1), axis=-1)
    frac = np.clip(frac, 0.0, None)
    return frac / frac.sum(axis=-1, keepdims=True)


# registration by name (``Mill(..., breakage="vogel_swebrec")``); imported by msmill.model
SUBMODELS["breakage"].setdefault("vogel_swebrec", VogelSwebrecBreakage.from_ore)
