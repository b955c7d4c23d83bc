"""Contact-law parameters: material-pair tables and the restitution calibration.

Normal force (paper Eqs. 4-9)::

    F_n = K_H s^{3/2} + C_H s^{1/4} ds/dt,   K_H = 4/3 E* sqrt(R*),
    C_H = 2 eta_H sqrt(m* K_H),              F_n >= 0 (clipped).

Tangential force (paper Eq. 10, Mindlin-Deresiewicz) with
``s_tmax = mu s_n E*/(4 G*)``, which for equal Poisson ratios is exactly
``mu s_n (2 - nu) / (2 (1 - nu))`` (domain notes Section 5) and generalises it
to unlike materials (``1/G* = (2 - nu1)/G1 + (2 - nu2)/G2``).

Restitution calibration
-----------------------
In nondimensional form (overlap scaled by ``s0 = (m* v0^2 / K_H)^{2/5}``,
time by ``s0 / v0``) one contact obeys ``S'' = -max(0, S^{3/2} + 2 eta_H
S^{1/4} S')`` with ``S(0) = 0, S'(0) = 1``: the coefficient of restitution
depends on ``eta_H`` only. :func:`restitution_of_eta` integrates it once (RK4,
fine step) on a grid of ``eta_H``; :func:`eta_of_restitution` inverts the
table by monotone interpolation. The clipping ``F_n >= 0`` is the engine's.
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
from numba import njit

from msmill.errors import MsmillInputError

# Number of entries of the per-pair parameter vector (see :func:`pair_table`).
N_PAIR = 6
P_KFAC, P_ETAH, P_ETAT, P_MU, P_STRATIO, P_ESTAR = range(N_PAIR)


@njit(cache=True, fastmath=False)
def _rebound(eta: float, dtau: float) -> tuple[float, float, float]:
    """Integrate one nondimensional contact; return (e, duration, peak overlap)."""
    s = 0.0
    v = 1.0
    tau = 0.0
    peak = 0.0

    def acc(s: float, v: float, eta: float) -> float:
        if s <= 0.0:
            return 0.0
        f = s**1.5 + 2.0 * eta * s**0.25 * v
        return -f if f > 0.0 else 0.0

    while True:
        k1s = v
        k1v = acc(s, v, eta)
        k2s = v + 0.5 * dtau * k1v
        k2v = acc(s + 0.5 * dtau * k1s, k2s, eta)
        k3s = v + 0.5 * dtau * k2v
        k3v = acc(s + 0.5 * dtau * k2s, k3s, eta)
        k4s = v + dtau * k3v
        k4v = acc(s + dtau * k3s, k4s, eta)
        s_new = s + dtau / 6.0 * (k1s + 2 * k2s + 2 * k3s + k4s)
        v_new = v + dtau / 6.0 * (k1v + 2 * k2v + 2 * k3v + k4v)
        if s_new <= 0.0 and tau > 0.0:
            # linear interpolation of the exit (force is ~0 there)
            frac = s / (s - s_new)
            tau += frac * dtau
            return -v_new, tau, peak
        s, v = s_new, v_new
        tau += dtau
        if s > peak:
            peak = s
        if tau > 1.0e4:
            return 0.0, tau, peak


@lru_cache(maxsize=1)
def _table() -> tuple[np.ndarray, np.ndarray]:
    """Tabulate restitution against eta_H (cached per process)."""
    etas = np.concatenate([[0.0], np.geomspace(1e-4, 50.0, 400)])
    es = np.empty_like(etas)
    for k, eta in enumerate(etas):  # 401 small scalar integrations, ~0.2 s total
        es[k] = _rebound(float(eta), 2e-4)[0]
    return etas, es


def restitution_of_eta(eta_h: float) -> float:
    """Coefficient of restitution produced by damping ratio ``eta_H`` (clipped law).

    Parameters
    ----------
    eta_h : float
        Normal damping ratio of paper Eq. 8 (dimensionless, >= 0).

    Returns
    -------
    float
        Restitution coefficient (velocity-independent).
    """
    return float(_rebound(float(eta_h), 2e-4)[0])


def eta_of_restitution(e: float) -> float:
    """Damping ratio ``eta_H`` that gives restitution ``e`` with ``F_n >= 0`` clipping.

    Parameters
    ----------
    e : float
        Requested coefficient of restitution, ``0 < e <= 1``.

    Returns
    -------
    float
        ``eta_H`` (dimensionless).
    """
    if not (0.0 < e <= 1.0):
        raise MsmillInputError("restitution", e, "a number in (0, 1]")
    if e == 1.0:
        return 0.0
    etas, es = _table()
    if e < es[-1]:
        raise MsmillInputError("restitution", e, f"a number in [{es[-1]:.3g}, 1]")
    # es decreases with eta: interpolate in (e, log eta) on the reversed table
    x = es[::-1]
    y = np.log(np.maximum(etas[::-1], 1e-12))
    k = int(np.searchsorted(x, e))
    k = min(max(k, 1), len(x) - 1)
    if etas[::-1][k - 1] == 0.0 or etas[::-1][k] == 0.0:
        return float(np.interp(e, x, etas[::-1]))
    eta = float(np.exp(np.interp(e, x, y)))
    # one Newton-secant polish on the exact integrator
    for _ in range(3):
        f0 = restitution_of_eta(eta) - e
        h = 1e-3 * eta
        f1 = restitution_of_eta(eta + h) - e
        if f1 == f0:
            break
        eta = max(eta - f0 * h / (f1 - f0), 1e-12)
    return eta


def hertz_contact_time(m_eff_kg: float, r_eff_m: float, e_eff_pa: float, v_m_s: float) -> float:
    """Hertz contact duration ``t_c = 2.87 (m*^2 / (R* E*^2 v))^{1/5}`` (s).

    Parameters
    ----------
    m_eff_kg, r_eff_m, e_eff_pa : float
        Effective mass (kg), radius (m) and Young's modulus (Pa).
    v_m_s : float
        Relative normal impact speed (m/s).
    """
    return 2.87 * (m_eff_kg**2 / (r_eff_m * e_eff_pa**2 * v_m_s)) ** 0.2


def effective_moduli(e1: float, nu1: float, e2: float, nu2: float) -> tuple[float, float]:
    """Effective Young's and shear moduli ``(E*, G*)`` of a pair (Pa); ``E = inf`` is rigid."""
    inv_e = (1 - nu1**2) / e1 + (1 - nu2**2) / e2
    g1 = e1 / (2 * (1 + nu1))
    g2 = e2 / (2 * (1 + nu2))
    inv_g = (2 - nu1) / g1 + (2 - nu2) / g2
    if inv_e <= 0 or inv_g <= 0:
        raise MsmillInputError("youngs_modulus_pa", (e1, e2), "at least one finite modulus per pair")
    return 1.0 / inv_e, 1.0 / inv_g


def pair_table(
    materials: list[dict], interactions: dict[tuple[int, int], dict]
) -> np.ndarray:
    """Pack per-pair contact parameters into an ``(M, M, N_PAIR)`` float array.

    Entries: ``4/3 E*`` (Pa), ``eta_H``, ``eta_tau``, ``mu``, ``E*/(4 G*)``, ``E*`` (Pa).
    A pair without :meth:`Simulation.set_interaction` gets e = 1 and mu = 0 and
    is reported by the caller.
    """
    m = len(materials)
    tab = np.zeros((m, m, N_PAIR))
    for a in range(m):
        for b in range(m):
            ma, mb = materials[a], materials[b]
            if math.isinf(ma["E"]) and math.isinf(mb["E"]):
                continue  # two rigid (wall) materials never touch
            estar, gstar = effective_moduli(ma["E"], ma["nu"], mb["E"], mb["nu"])
            key = (min(a, b), max(a, b))
            inter = interactions.get(key, {"restitution": 1.0, "friction": 0.0,
                                           "tangential_damping": None})
            eta_h = eta_of_restitution(inter["restitution"])
            eta_t = inter["tangential_damping"]
            tab[a, b, P_KFAC] = 4.0 / 3.0 * estar
            tab[a, b, P_ETAH] = eta_h
            tab[a, b, P_ETAT] = eta_h if eta_t is None else eta_t
            tab[a, b, P_MU] = inter["friction"]
            tab[a, b, P_STRATIO] = estar / (4.0 * gstar)
            tab[a, b, P_ESTAR] = estar
    return tab
