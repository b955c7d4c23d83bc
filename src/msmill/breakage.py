"""Impact breakage: paper Eqs. 11-12, the t10-tn appearance function and Tavares damage.

Everything here is a plain, vectorised numpy function (broadcasting over sizes,
energies and batches); see ``docs/breakage.md`` for the reasoning behind each
choice.

* Eq. 11 (with damage ``D``): ``P_b = 1 - exp(-b E_cs L / (L_ref (1 - D)))``,
  ``E_cs`` in kWh/t, ``b`` in t/kWh, ``L`` and ``L_ref`` in mm.
* Eq. 12: ``t10 = A P_b`` (%), ``t_n = k t10**s`` (%), capped at 100 %.
* :func:`appearance_matrix`: the fragment size distribution of a broken parent
  from its ``t_n`` values (domain notes §3) as the columns of ``B[..., i, j]``.
* Tavares damage (domain notes §4): :func:`damage_increment` solves
  ``D = [2γ/(2γ - 5D + 5) · r]**(2γ/5)``, ``r = E_k / E_f``; the coupling with
  Eq. 11 is :func:`survivor_energy_ratio` and :func:`damage_after_impact`.

Units: ``ecs_kwh_t`` specific energy (kWh/t), ``*_j_kg`` (J/kg), sizes in mm,
``A``, ``t10``, ``t_n`` in %.
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Mapping
from functools import lru_cache
from importlib import resources
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import BaseModel, ConfigDict, ValidationError, field_validator

from msmill.errors import MsmillInputError, from_validation_error
from msmill.psd import PSD, SizeGrid

__all__ = [
    "J_KG_PER_KWH_T",
    "T10_CONVENTIONS",
    "TN_SIZES",
    "DamageResult",
    "TnConstants",
    "accumulate_damage",
    "appearance_matrix",
    "breakage_probability",
    "damage_after_impact",
    "damage_increment",
    "default_tn_constants",
    "ecs_kwh_t_to_velocity",
    "fragment_psd",
    "fragment_t10_pct",
    "is_broken",
    "j_kg_to_kwh_t",
    "kwh_t_to_j_kg",
    "mean_fracture_energy_kwh_t",
    "population_t10_pct",
    "survivor_energy_ratio",
    "t10_pct",
    "tn_pct",
    "velocity_to_ecs_j_kg",
    "velocity_to_ecs_kwh_t",
]

#: 1 kWh/t = 3.6e6 J / 1000 kg = 3600 J/kg.
J_KG_PER_KWH_T = 3600.0
#: The JK t_n sizes: t_n is the % of progeny passing parent size / n.
TN_SIZES: tuple[int, ...] = (2, 4, 25, 50, 75)

#: Accepted range of Tavares' gamma (published values are ~3-5.4).
GAMMA_RANGE = (0.5, 50.0)

# --------------------------------------------------------------------------- helpers


def _arr(value: Any, name: str) -> NDArray[np.float64]:
    try:
        a = np.asarray(value, dtype=float)
    except (TypeError, ValueError) as exc:
        raise MsmillInputError(name, value, "a number or array of numbers") from exc
    if not np.all(np.isfinite(a)):
        raise MsmillInputError(name, value, "finite numbers")
    return a


def _ret(a: NDArray[np.float64]) -> NDArray[np.float64] | float:
    return float(a) if a.ndim == 0 else a


def _nonneg(value: Any, name: str, what: str) -> NDArray[np.float64]:
    a = _arr(value, name)
    if np.any(a < 0):
        raise MsmillInputError(name, value, f"{what} >= 0")
    return a


def _pos(value: Any, name: str, what: str) -> NDArray[np.float64]:
    a = _arr(value, name)
    if np.any(a <= 0):
        raise MsmillInputError(name, value, f"{what} > 0")
    return a


def _damage(value: Any, name: str = "damage") -> NDArray[np.float64]:
    a = _arr(value, name)
    if np.any((a < 0) | (a >= 1)):
        raise MsmillInputError(name, value, "damage in [0, 1)")
    return a


# --------------------------------------------------------------------- energy units


def velocity_to_ecs_j_kg(v_m_s: ArrayLike) -> NDArray[np.float64] | float:
    """Specific impact energy ``E_cs = v**2 / 2`` (J/kg) from the normal impact speed (m/s)."""
    v = _arr(v_m_s, "velocity_m_s")
    with np.errstate(over="ignore"):  # |v| > 1e154 m/s gives inf, not numpy's overflow warning
        return _ret(0.5 * v * v)


def j_kg_to_kwh_t(e_j_kg: ArrayLike) -> NDArray[np.float64] | float:
    """Convert specific energy from J/kg to kWh/t (1 kWh/t = 3600 J/kg)."""
    return _ret(_arr(e_j_kg, "ecs_j_kg") / J_KG_PER_KWH_T)


def kwh_t_to_j_kg(e_kwh_t: ArrayLike) -> NDArray[np.float64] | float:
    """Convert specific energy from kWh/t to J/kg (1 kWh/t = 3600 J/kg)."""
    return _ret(_arr(e_kwh_t, "ecs_kwh_t") * J_KG_PER_KWH_T)


def velocity_to_ecs_kwh_t(v_m_s: ArrayLike) -> NDArray[np.float64] | float:
    """Specific impact energy (kWh/t) from the normal impact speed (m/s)."""
    v = _arr(v_m_s, "velocity_m_s")
    return _ret(0.5 * v * v / J_KG_PER_KWH_T)


def ecs_kwh_t_to_velocity(ecs_kwh_t: ArrayLike) -> NDArray[np.float64] | float:
    """Normal impact speed (m/s) carrying the specific energy ``ecs_kwh_t`` (kWh/t)."""
    e = _nonneg(ecs_kwh_t, "ecs_kwh_t", "specific energy (kWh/t)")
    return _ret(np.sqrt(2.0 * e * J_KG_PER_KWH_T))


# ------------------------------------------------------------------ Eq. 11 and 12


def breakage_probability(
    ecs_kwh_t: ArrayLike,
    size_mm: ArrayLike,
    b_t_per_kwh: ArrayLike,
    l_ref_mm: ArrayLike,
    damage: ArrayLike = 0.0,
) -> NDArray[np.float64] | float:
    """Breakage probability of one impact (paper Eq. 11, fracture energy scaled by 1 - D).

    ``P_b = 1 - exp(-b E_cs L / (L_ref (1 - D)))``

    Parameters
    ----------
    ecs_kwh_t : array_like
        Specific impact energy ``E_cs`` (kWh/t), >= 0.
    size_mm : array_like
        Rock size ``L`` (mm), > 0.
    b_t_per_kwh : array_like
        Ore breakability ``b`` (t/kWh), > 0.
    l_ref_mm : array_like
        Reference size ``L_ref`` (mm), > 0.
    damage : array_like, optional
        Accumulated Tavares damage ``D`` in [0, 1) (default 0, an intact rock).

    Returns
    -------
    float or ndarray
        ``P_b`` in [0, 1), broadcast over all inputs.
    """
    e = _nonneg(ecs_kwh_t, "ecs_kwh_t", "specific energy (kWh/t)")
    size = _pos(size_mm, "size_mm", "size (mm)")
    bb = _pos(b_t_per_kwh, "b_t_per_kwh", "breakability (t/kWh)")
    lref = _pos(l_ref_mm, "l_ref_mm", "reference size (mm)")
    d = _damage(damage)
    with np.errstate(over="ignore"):  # a product beyond 1e308 is +inf: P_b = 1, its correct limit
        x = bb * e * size / (lref * (1.0 - d))
    return _ret(-np.expm1(-x))


def t10_pct(pb: ArrayLike, A: ArrayLike) -> NDArray[np.float64] | float:
    """Paper Eq. 12: ``t10 = A P_b`` (%).

    Parameters
    ----------
    pb : array_like
        Breakage probability in [0, 1].
    A : array_like
        Ore parameter ``A`` (%), in (0, 100].
    """
    p = _arr(pb, "pb")
    if np.any((p < 0) | (p > 1)):
        raise MsmillInputError("pb", pb, "probabilities in [0, 1]")
    a = _arr(A, "A")
    if np.any((a <= 0) | (a > 100)):
        raise MsmillInputError("A", A, "A (%) in (0, 100]")
    return _ret(a * p)


#: The two readings of A and b (docs/breakage.md, "The t10 convention"):
#: ``"paper"``: a broken rock's fragments have ``t10 = A P_b`` (paper Eq. 12 read literally), so the
#: population of a drop-weight test (broken and unbroken rock) has ``t10 = A P_b**2``;
#: ``"jk"``: the population t10 after one impact is the JK law ``A P_b = A (1 - exp(-b E L / L_ref))``,
#: a broken rock's fragments have ``t10 = A``.
T10_CONVENTIONS: tuple[str, ...] = ("jk", "paper")


def _convention(convention: str) -> str:
    if convention not in T10_CONVENTIONS:
        raise MsmillInputError("t10 convention", convention, "one of " + ", ".join(map(repr, T10_CONVENTIONS)))
    return convention


def fragment_t10_pct(pb: ArrayLike, A: float, convention: str = "jk") -> NDArray[np.float64] | float:
    """t10 (%) of the fragments of a rock broken by an impact of breakage probability ``pb``.

    ``"paper"``: ``A pb``; ``"jk"``: ``A`` (see :data:`T10_CONVENTIONS`).
    """
    p = np.asarray(pb, dtype=float)
    out = A * p if _convention(convention) == "paper" else np.full(p.shape, float(A))
    return _ret(np.asarray(out, dtype=float))


def population_t10_pct(
    ecs_kwh_t: ArrayLike, size_mm: ArrayLike, A: float, b_t_per_kwh: float, l_ref_mm: float,
    convention: str = "jk",
) -> NDArray[np.float64] | float:
    """t10 (%) of the whole population after one impact per rock (what a drop-weight test measures).

    Unbroken rock adds nothing below a tenth of its size, so the population t10 is
    ``P_b * fragment_t10``: ``A P_b**2`` (``"paper"``) or ``A P_b`` (``"jk"``, the JK law), with
    ``P_b`` from Eq. 11 at zero damage.
    """
    x = b_t_per_kwh * np.asarray(ecs_kwh_t, dtype=float) * np.asarray(size_mm, dtype=float) / l_ref_mm
    pb = -np.expm1(-x)
    return _ret(np.asarray(pb * fragment_t10_pct(pb, A, convention), dtype=float))


def tn_pct(t10: ArrayLike, k: ArrayLike, s: ArrayLike) -> NDArray[np.float64] | float:
    """Paper Eq. 12: ``t_n = k t10**s`` (%), capped at 100 %.

    Parameters
    ----------
    t10 : array_like
        ``t10`` (%), in [0, 100].
    k, s : array_like
        Power-law constants (``k > 0``, ``s > 0``), broadcast against ``t10``.
    """
    t = _arr(t10, "t10_pct")
    if np.any((t < 0) | (t > 100)):
        raise MsmillInputError("t10_pct", t10, "t10 (%) in [0, 100]")
    kk = _pos(k, "k", "power-law constant k")
    ss = _pos(s, "s", "power-law exponent s")
    return _ret(np.minimum(kk * t**ss, 100.0))


# --------------------------------------------------------------------- t_n constants


class TnConstants(BaseModel):
    """Constants of ``t_n = k t10**s`` for ``n`` in :data:`TN_SIZES` (2, 4, 25, 50, 75).

    Attributes
    ----------
    k : tuple of 5 float
        Multipliers (> 0), in the order of :data:`TN_SIZES`.
    s : tuple of 5 float
        Exponents (> 0), same order.
    source : str
        Provenance of the constants.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    k: tuple[float, float, float, float, float]
    s: tuple[float, float, float, float, float]
    source: str = "user"

    @field_validator("k", "s")
    @classmethod
    def _positive(cls, v: tuple[float, ...]) -> tuple[float, ...]:
        if any(not (math.isfinite(x) and x > 0) for x in v):
            raise ValueError("five finite values > 0 (for n = 2, 4, 25, 50, 75)")
        return v

    @classmethod
    def from_mapping(cls, tn: Mapping[Any, Any], source: str = "user") -> TnConstants:
        """Build from ``{n: (k, s)}`` with ``n`` in 2, 4, 25, 50, 75 (keys ``2`` or ``"t2"``)."""
        try:
            norm = {int(str(key).lstrip("t")): tuple(val) for key, val in tn.items()}
        except (TypeError, ValueError) as exc:
            raise MsmillInputError("tn", dict(tn), "a mapping {n: (k, s)} for n in 2, 4, 25, 50, 75") from exc
        if sorted(norm) != list(TN_SIZES) or any(len(v) != 2 for v in norm.values()):
            raise MsmillInputError("tn", dict(tn), "a mapping {n: (k, s)} for n in 2, 4, 25, 50, 75")
        try:
            return cls(
                k=tuple(float(norm[n][0]) for n in TN_SIZES),  # type: ignore[arg-type]
                s=tuple(float(norm[n][1]) for n in TN_SIZES),  # type: ignore[arg-type]
                source=source,
            )
        except ValidationError as exc:
            raise from_validation_error(exc, "tn") from exc

    def as_dict(self) -> dict[int, tuple[float, float]]:
        """``{n: (k, s)}``."""
        return {n: (k, s) for n, k, s in zip(TN_SIZES, self.k, self.s, strict=True)}

    def tn_pct(self, t10: ArrayLike) -> NDArray[np.float64]:
        """``t_n`` (%) for every ``n``: shape ``t10.shape + (5,)``, capped at 100 %."""
        t = np.asarray(t10, dtype=float)[..., None]
        return np.minimum(np.asarray(self.k) * t ** np.asarray(self.s), 100.0)


@lru_cache(maxsize=4)
def default_tn_constants(table: str = "A") -> TnConstants:
    """The packaged ``t_n = k t10**s`` fit (``src/msmill/data/tn_constants.toml``).

    Parameters
    ----------
    table : str, optional
        Which fitted table: ``"A"`` (default) or ``"B"`` (domain notes §3);
        see ``scripts/fit_tn_constants.py``.
    """
    text = resources.files("msmill").joinpath("data/tn_constants.toml").read_text("utf-8")
    data = tomllib.loads(text)
    tables = data.get("tables", {})
    key = str(table).upper()
    if key not in tables:
        raise MsmillInputError("table", table, f"one of {sorted(tables)}")
    t = tables[key]
    prov = data.get("provenance", {})
    src = f"{t.get('source', '')} (fit: {prov.get('command', '?')}, {prov.get('date', '?')})"
    return TnConstants.from_mapping({n: t[f"t{n}"] for n in TN_SIZES}, source=src)


def _as_tn(tn: TnConstants | Mapping[Any, Any] | None) -> TnConstants:
    if tn is None:
        return default_tn_constants()
    if isinstance(tn, TnConstants):
        return tn
    if isinstance(tn, Mapping):
        return TnConstants.from_mapping(tn)
    raise MsmillInputError("tn", tn, "TnConstants, a mapping {n: (k, s)} or None (default)")


# ------------------------------------------------------------------- appearance


# Knots of the t_n curve in u = ln(size / parent): parent/75 ... parent.
_KNOT_N = np.array([75.0, 50.0, 25.0, 10.0, 4.0, 2.0, 1.0])
_KNOT_U = -np.log(_KNOT_N)
#: Floor for % passing before taking logs (a t10 of 0 means "no fragments").
_P_FLOOR = 1e-12


def _pchip_slopes(h: NDArray[np.float64], y: NDArray[np.float64]) -> NDArray[np.float64]:
    """Fritsch-Carlson (PCHIP) slopes along the last axis of ``y`` at fixed knots.

    ``h`` are the knot spacings (shape ``(m-1,)``); ``y`` shape ``(..., m)``.
    Same formulas as scipy's ``PchipInterpolator`` (weighted harmonic mean in the
    interior, shape-preserving three-point ends) but batched over leading axes.
    """
    delta = np.diff(y, axis=-1) / h
    d = np.zeros_like(y)
    h0, h1 = h[:-1], h[1:]
    w1 = 2.0 * h1 + h0
    w2 = h1 + 2.0 * h0
    dl, dr = delta[..., :-1], delta[..., 1:]
    same = (dl * dr) > 0
    with np.errstate(divide="ignore", invalid="ignore"):
        hm = (w1 + w2) / (w1 / dl + w2 / dr)
    d[..., 1:-1] = np.where(same, hm, 0.0)

    def end(hA: float, hB: float, dA: NDArray[np.float64], dB: NDArray[np.float64]) -> NDArray[np.float64]:
        e = ((2.0 * hA + hB) * dA - hA * dB) / (hA + hB)
        e = np.where(np.sign(e) != np.sign(dA), 0.0, e)
        e = np.where((np.sign(dA) != np.sign(dB)) & (np.abs(e) > 3.0 * np.abs(dA)), 3.0 * dA, e)
        return e

    d[..., 0] = end(h[0], h[1], delta[..., 0], delta[..., 1])
    d[..., -1] = end(h[-1], h[-2], delta[..., -1], delta[..., -2])
    return d


def appearance_matrix(
    grid: SizeGrid,
    t10_pct: ArrayLike,
    tn: TnConstants | Mapping[Any, Any] | None = None,
) -> NDArray[np.float64]:
    """Breakage (appearance) matrix from the t10-tn family (domain notes §3).

    For a parent of size ``x_j = grid.mids_mm[j]`` the cumulative % passing of
    its progeny goes through ``(x_j, 100)``, ``(x_j/2, t2)``, ``(x_j/4, t4)``,
    ``(x_j/10, t10)``, ``(x_j/25, t25)``, ``(x_j/50, t50)``, ``(x_j/75, t75)``
    with ``t_n = k t10**s`` (capped at 100 % and made non-increasing in ``n``).
    ``ln(% passing)`` is interpolated against ``ln(size)`` by PCHIP (monotone),
    read at the grid edges, capped at 100 % and differenced into column ``j``.
    Below ``x_j/75`` the curve continues as a power law (a straight line in
    log-log, Gates-Gaudin-Schuhmann-like) with the secant slope between
    ``x_j/75`` and ``x_j/50``, so passing falls to 0 at zero size; everything
    finer than ``edges_mm[1]`` lands in class 0.

    Parameters
    ----------
    grid : SizeGrid
        Size grid (``n`` classes).
    t10_pct : array_like
        ``t10`` (%), in [0, 100]: a scalar or an array whose last axis is the
        parent class (length 1 or ``n``) with any leading batch axes, e.g.
        shape ``(m, 1)`` for ``m`` energies applied to every parent or
        ``(m, n)`` for one ``t10`` per (energy, parent).
    tn : TnConstants or mapping or None, optional
        ``t_n`` constants; ``None`` uses :func:`default_tn_constants`.

    Returns
    -------
    ndarray, shape ``(..., n, n)``
        ``B[..., i, j]``: mass fraction of a broken parent in class ``j`` that
        ends in class ``i``. Every column sums to 1, ``B[..., i, j] = 0`` for
        ``i > j`` and the cumulative sums down each column are monotone. A
        scalar ``t10_pct`` gives shape ``(n, n)``; a column with ``t10 = 0`` is
        the identity (nothing breaks off).
    """
    if not isinstance(grid, SizeGrid):
        raise MsmillInputError("grid", grid, "a msmill.psd.SizeGrid")
    consts = _as_tn(tn)
    n = grid.n_classes
    t10 = _arr(t10_pct, "t10_pct")
    if np.any((t10 < 0) | (t10 > 100)):
        raise MsmillInputError("t10_pct", t10_pct, "t10 (%) in [0, 100]")
    if t10.ndim == 0:
        t10 = t10[None]
    if t10.shape[-1] not in (1, n):
        raise MsmillInputError(
            "t10_pct", f"array of shape {t10.shape}",
            f"a scalar or an array whose last axis (parent class) has length 1 or {n}",
        )
    t10 = np.broadcast_to(t10, (*t10.shape[:-1], n))

    y = _knot_log_passing(consts, t10)
    cum = _passing_at_edges(grid, y)
    return _class_fractions(cum, t10, n)


def _knot_log_passing(consts: Any, t10: np.ndarray) -> np.ndarray:
    """ln(% passing) at the seven knots (t75, t50, t25, t10, t4, t2, 100 %), fine -> coarse, monotone."""
    tn_vals = consts.tn_pct(t10)  # (..., n, 5) for n = 2, 4, 25, 50, 75
    p = np.empty((*t10.shape, 7))
    p[..., 0] = tn_vals[..., 4]  # t75
    p[..., 1] = tn_vals[..., 3]  # t50
    p[..., 2] = tn_vals[..., 2]  # t25
    p[..., 3] = t10
    p[..., 4] = tn_vals[..., 1]  # t4
    p[..., 5] = tn_vals[..., 0]  # t2
    p[..., 6] = 100.0
    np.clip(p, _P_FLOOR, 100.0, out=p)
    # non-decreasing with size: running minimum from the coarse end
    p = np.minimum.accumulate(p[..., ::-1], axis=-1)[..., ::-1]
    return np.log(p)


def _passing_at_edges(grid: SizeGrid, y: np.ndarray) -> np.ndarray:
    """% passing each class edge (rows) of each parent class (columns): the PCHIP through the knots ``y``.

    Below parent/75 a power-law tail with the secant slope of the last segment; 100 % at and
    above the parent size; monotone in size.
    """
    n = grid.n_classes
    h = np.diff(_KNOT_U)
    d = _pchip_slopes(h, y)
    # query points: u[i, j] = ln(edges[i] / mids[j]) for the n+1 edges
    u = np.log(grid.edges_mm)[:, None] - np.log(grid.mids_mm)[None, :]  # (n+1, n)
    k = np.clip(np.searchsorted(_KNOT_U, u, side="right") - 1, 0, _KNOT_U.size - 2)
    cols = np.arange(n)[None, :]
    hk = h[k]
    t = (u - _KNOT_U[k]) / hk
    # gather y and slopes at (..., j, k) and (..., j, k+1) -> (..., n+1, n)
    y0 = y[..., cols, k]
    y1 = y[..., cols, k + 1]
    d0 = d[..., cols, k]
    d1 = d[..., cols, k + 1]
    t2 = t * t
    t3 = t2 * t
    lnp = (
        (2 * t3 - 3 * t2 + 1) * y0
        + (t3 - 2 * t2 + t) * hk * d0
        + (-2 * t3 + 3 * t2) * y1
        + (t3 - t2) * hk * d1
    )
    tail_slope = np.maximum((y[..., 1] - y[..., 0]) / h[0], 0.0)  # (..., n)
    below = u < _KNOT_U[0]
    tail = y[..., 0][..., None, :] + tail_slope[..., None, :] * (u - _KNOT_U[0])
    lnp = np.where(below, tail, lnp)
    cum = np.exp(np.minimum(lnp, math.log(100.0)))
    cum = np.where(u >= 0.0, 100.0, cum)  # at and above the parent size
    # monotone in size (guards round-off)
    return np.maximum.accumulate(cum, axis=-2)


def _class_fractions(cum: np.ndarray, t10: np.ndarray, n: int) -> np.ndarray:
    """The appearance matrix from % passing the edges: exact zeros above the parent, columns summing to 1."""
    # pan below edges[0]: class 0 takes it all
    cum[..., -1, :] = 100.0
    cum[..., 0, :] = 0.0  # cumulative "at edges[0]" is replaced by the pan convention
    # class i gets passing(edges[i+1]) - passing(edges[i]); class 0 includes the pan
    B = np.diff(cum, axis=-2) / 100.0
    B[..., 0, :] = cum[..., 1, :] / 100.0
    # exact zero above the parent's class (cum = 100 there already) and exact column sums
    above = np.arange(n)[:, None] > np.arange(n)[None, :]
    B = np.where(above, 0.0, np.maximum(B, 0.0))
    # put the round-off residual (~1e-16) on each column's largest entry (>= 1/n)
    resid = 1.0 - B.sum(axis=-2, keepdims=True)
    imax = np.argmax(B, axis=-2)[..., None, :]
    np.put_along_axis(B, imax, np.take_along_axis(B, imax, axis=-2) + resid, axis=-2)
    # t10 = 0 means no fragments at all: the column is the identity exactly
    zero = (t10 <= 0.0)[..., None, :]
    if np.any(zero):
        B = np.where(zero, np.eye(n), B)
    return B


def fragment_psd(
    grid: SizeGrid,
    parent_class: int,
    t10_pct: float,
    tn: TnConstants | Mapping[Any, Any] | None = None,
) -> PSD:
    """Fragment size distribution of one broken parent: column ``parent_class`` of the appearance matrix.

    Parameters
    ----------
    grid : SizeGrid
        Size grid; the parent size is ``grid.mids_mm[parent_class]``.
    parent_class : int
        Index of the parent's class (0 ... n-1).
    t10_pct : float
        ``t10`` (%) of the breakage event.
    tn : TnConstants or mapping or None, optional
        As in :func:`appearance_matrix`.
    """
    if not isinstance(grid, SizeGrid):
        raise MsmillInputError("grid", grid, "a msmill.psd.SizeGrid")
    if not isinstance(parent_class, int | np.integer) or not 0 <= int(parent_class) < grid.n_classes:
        raise MsmillInputError("parent_class", parent_class, f"a class index in 0..{grid.n_classes - 1}")
    t = np.zeros(grid.n_classes)
    t[:] = float(np.asarray(_arr(t10_pct, "t10_pct")))
    col = appearance_matrix(grid, t, tn)[:, int(parent_class)]
    return PSD(grid, col, validate=False)


# ------------------------------------------------------------------------ damage


def _check_gamma(gamma: Any) -> NDArray[np.float64]:
    g = _arr(gamma, "gamma")
    lo, hi = GAMMA_RANGE
    if np.any((g < lo) | (g > hi)):
        raise MsmillInputError("gamma", gamma, f"Tavares gamma in [{lo}, {hi}] (published ~3-5.4)")
    return g


def _damage_rhs(d: NDArray[np.float64], r: NDArray[np.float64], g: NDArray[np.float64]) -> NDArray[np.float64]:
    return (2.0 * g * r / (2.0 * g + 5.0 - 5.0 * d)) ** (2.0 * g / 5.0)


def damage_increment(
    energy_ratio: ArrayLike, gamma: ArrayLike, *, tol: float = 1e-14, max_iter: int = 200
) -> NDArray[np.float64] | float:
    """Tavares damage of one non-breaking impact (domain notes §4).

    Solves ``D = [2γ / (2γ - 5D + 5) · r]**(2γ/5)`` for ``D`` in [0, 1) with
    ``r = E_k / E_f`` the ratio of the impact energy to the particle's current
    fracture energy.

    ``f(D) = D - rhs(D)`` is concave on [0, 1] (``rhs`` is convex), negative at
    0 and positive at 1 for ``0 < r < 1``, so there is exactly one root in
    (0, 1): the physical one (``D → 0`` as ``r → 0``, increasing in ``r``).
    Newton's method started at ``D = 0`` approaches it monotonically from below
    on a concave increasing function; a bisection step on the maintained bracket
    is taken whenever a Newton step would leave it. Vectorised over broadcast
    inputs (the loop runs over iterations, not elements).

    Parameters
    ----------
    energy_ratio : array_like
        ``E_k / E_f`` in [0, 1).
    gamma : array_like
        Tavares' damage exponent ``γ`` in [0.5, 50] (published ~3-5.4).
    tol : float, optional
        Absolute tolerance on ``D``.
    max_iter : int, optional
        Iteration cap.

    Returns
    -------
    float or ndarray
        Damage increment ``D`` in [0, 1).
    """
    r = _arr(energy_ratio, "energy_ratio")
    if np.any((r < 0) | (r >= 1)):
        raise MsmillInputError("energy_ratio", energy_ratio, "E_k/E_f in [0, 1)")
    g = _check_gamma(gamma)
    r, g = np.broadcast_arrays(r, g)
    shape = r.shape
    r = r.astype(float).ravel()
    g = g.astype(float).ravel()
    out = np.zeros_like(r)
    # iterate only on the elements not converged yet (r = 0 gives D = 0 exactly)
    idx = np.flatnonzero(r > 0)
    rr, gg = r[idx], g[idx]
    dd = np.zeros_like(rr)
    lo = np.zeros_like(rr)
    hi = np.ones_like(rr)
    for _ in range(max_iter):
        if idx.size == 0:
            break
        rhs = _damage_rhs(dd, rr, gg)
        f = dd - rhs
        lo = np.where(f <= 0, dd, lo)
        hi = np.where(f > 0, dd, hi)
        fp = 1.0 - 2.0 * gg * rhs / (2.0 * gg + 5.0 - 5.0 * dd)
        with np.errstate(divide="ignore", invalid="ignore"):
            newton = dd - f / fp
        ok = np.isfinite(newton) & (newton >= lo) & (newton <= hi)
        new = np.where(ok, newton, 0.5 * (lo + hi))
        done = (np.abs(new - dd) <= tol) | (hi - lo <= tol)
        dd = new
        out[idx[done]] = dd[done]
        keep = ~done
        idx, rr, gg, dd, lo, hi = idx[keep], rr[keep], gg[keep], dd[keep], lo[keep], hi[keep]
    out[idx] = dd  # not converged within max_iter (not expected): best bracketed estimate
    dd = out.reshape(shape)
    return _ret(np.clip(dd, 0.0, np.nextafter(1.0, 0.0)))


def accumulate_damage(d_prev: ArrayLike, d_inc: ArrayLike) -> NDArray[np.float64] | float:
    """Accumulated damage ``1 - (1 - D_prev)(1 - D_inc)`` (fracture energy multiplies by 1 - D)."""
    a = _arr(d_prev, "d_prev")
    b = _arr(d_inc, "d_inc")
    for name, v, raw in (("d_prev", a, d_prev), ("d_inc", b, d_inc)):
        if np.any((v < 0) | (v > 1)):
            raise MsmillInputError(name, raw, "damage in [0, 1]")
    return _ret(1.0 - (1.0 - a) * (1.0 - b))


def is_broken(damage: ArrayLike, threshold: ArrayLike) -> NDArray[np.bool_] | bool:
    """Breakage by accumulated damage: ``damage >= threshold`` (threshold in (0, 1])."""
    d = _arr(damage, "damage")
    th = _arr(threshold, "damage_threshold")
    if np.any((th <= 0) | (th > 1)):
        raise MsmillInputError("damage_threshold", threshold, "a damage threshold in (0, 1]")
    out = d >= th
    return bool(out) if out.ndim == 0 else out


def mean_fracture_energy_kwh_t(
    size_mm: ArrayLike, b_t_per_kwh: ArrayLike, l_ref_mm: ArrayLike, damage: ArrayLike = 0.0
) -> NDArray[np.float64] | float:
    """Mean fracture energy implied by Eq. 11: ``E_m = L_ref (1 - D) / (b L)`` (kWh/t).

    Eq. 11 is the breakage probability of a population whose specific fracture
    energies are exponential with this mean.
    """
    size = _pos(size_mm, "size_mm", "size (mm)")
    bb = _pos(b_t_per_kwh, "b_t_per_kwh", "breakability (t/kWh)")
    lref = _pos(l_ref_mm, "l_ref_mm", "reference size (mm)")
    d = _damage(damage)
    return _ret(lref * (1.0 - d) / (bb * size))


def survivor_energy_ratio(
    ecs_kwh_t: ArrayLike,
    size_mm: ArrayLike,
    b_t_per_kwh: ArrayLike,
    l_ref_mm: ArrayLike,
    damage: ArrayLike = 0.0,
) -> NDArray[np.float64] | float:
    """Ratio ``r = E_k / E_f`` for a rock that survived an impact of energy ``E_k``.

    With exponential fracture energies of mean ``E_m (1 - D)`` (Eq. 11), a
    survivor of an impact of energy ``E`` has (memoryless) expected fracture
    energy ``E + E_m (1 - D)``, so ``r = E / (E + E_m (1 - D))`` in [0, 1).

    Parameters
    ----------
    ecs_kwh_t : array_like
        Impact energy (kWh/t), >= 0.
    size_mm, b_t_per_kwh, l_ref_mm, damage : array_like
        As in :func:`breakage_probability`.
    """
    e = _nonneg(ecs_kwh_t, "ecs_kwh_t", "specific energy (kWh/t)")
    em = np.asarray(mean_fracture_energy_kwh_t(size_mm, b_t_per_kwh, l_ref_mm, damage))
    r = e / (e + em)
    return _ret(np.minimum(r, np.nextafter(1.0, 0.0)))


class DamageResult(NamedTuple):
    """Outcome of one impact on a population of rocks.

    Attributes
    ----------
    pb : ndarray or float
        Probability that the rock breaks in this impact (Eq. 11 with damage,
        plus breakage of survivors whose damage reaches the threshold).
    damage : ndarray or float
        Accumulated damage of the rocks that survive (``D`` in [0, 1)).
    """

    pb: NDArray[np.float64] | float
    damage: NDArray[np.float64] | float


def damage_after_impact(
    ecs_kwh_t: ArrayLike,
    size_mm: ArrayLike,
    b_t_per_kwh: ArrayLike,
    l_ref_mm: ArrayLike,
    gamma: ArrayLike,
    damage: ArrayLike = 0.0,
    damage_threshold: ArrayLike | None = None,
) -> DamageResult:
    """Breakage probability and survivors' new damage for one impact.

    1. ``P_b = 1 - exp(-b E L / (L_ref (1 - D)))`` (:func:`breakage_probability`).
    2. Survivors: ``r = E / (E + E_m (1 - D))`` (:func:`survivor_energy_ratio`),
       increment ``ΔD`` from :func:`damage_increment`, accumulated
       ``D' = 1 - (1 - D)(1 - ΔD)``.
    3. If ``damage_threshold`` is given, survivors with ``D' >= threshold``
       break too: ``P_b`` becomes 1 where that happens.

    Parameters
    ----------
    ecs_kwh_t, size_mm, b_t_per_kwh, l_ref_mm : array_like
        As in :func:`breakage_probability`.
    gamma : array_like
        Tavares' damage exponent.
    damage : array_like, optional
        Accumulated damage before the impact, in [0, 1).
    damage_threshold : array_like, optional
        Damage at which a rock breaks, in (0, 1]; ``None`` = no threshold.

    Returns
    -------
    DamageResult
        ``(pb, damage)`` broadcast over all inputs.
    """
    pb = np.asarray(breakage_probability(ecs_kwh_t, size_mm, b_t_per_kwh, l_ref_mm, damage))
    r = np.asarray(survivor_energy_ratio(ecs_kwh_t, size_mm, b_t_per_kwh, l_ref_mm, damage))
    dinc = np.asarray(damage_increment(r, gamma))
    dnew = np.minimum(np.asarray(accumulate_damage(damage, dinc)), np.nextafter(1.0, 0.0))
    dnew = np.broadcast_to(dnew, np.broadcast_shapes(dnew.shape, pb.shape))
    pb = np.broadcast_to(pb, dnew.shape)
    if damage_threshold is not None:
        pb = np.where(np.asarray(is_broken(dnew, damage_threshold)), 1.0, pb)
    return DamageResult(_ret(np.array(pb, dtype=float)), _ret(np.array(dnew, dtype=float)))

