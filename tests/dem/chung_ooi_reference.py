"""Independent reference for one DEM contact: scipy ``solve_ivp`` of the contact ODE.

Written apart from ``msmill.dem`` (no import from it) so that the Chung & Ooi
tests compare the engine with a second implementation of the same law
(docs/dem.md, paper Eqs. 4-10), integrated with an adaptive high-order
scheme at tight tolerance instead of the engine's fixed symplectic step:

- normal: ``F_n = max(0, K_H s^{3/2} + C_H s^{1/4} ds/dt)``, ``K_H = 4/3 E* sqrt(R*)``,
  ``C_H = 2 eta_H sqrt(m* K_H)``;
- tangential (Mindlin-Deresiewicz, partial slip): history ``xi`` with
  ``xi_max = mu s strat``, ``zeta = 1 - |xi| / xi_max``,
  ``F_t = -mu F_n (1 - zeta^{3/2}) sign(xi) - eta_t sqrt(6 mu m* F_n / xi_max) zeta^{1/4} v_t``;
  the history grows with the contact-point slip ``v_t`` and is held at the
  bound while the contact slides, i.e. at ``|xi| = xi_max`` it moves at
  ``sign(xi) min(sign(xi) v_t, mu strat ds/dt)``;
- ``eta_H`` is found here from the requested restitution by root-finding on
  the same nondimensional normal ODE (``eta_t = eta_H``).

Motion is planar and the normal fixed (a sphere on a plane, or two spheres
colliding head on with spin about the common normal's perpendicular): one
tangential direction suffices. Spin coordinates ``q`` are defined so that the
contact-point slip is ``v_t = u + l_a q_a + l_b q_b`` and a tangential force
``F`` (on body a) gives ``du/dt = F (1/m_a + 1/m_b)``, ``dq/dt = l F / I``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from scipy.integrate import solve_ivp
from scipy.optimize import brentq


def mindlin_ratio(nu: float) -> float:
    """``xi_max / (mu s) = (2 - nu) / (2 (1 - nu))`` for like Poisson ratios (a rigid partner too)."""
    return (2.0 - nu) / (2.0 * (1.0 - nu))


def _restitution(eta: float) -> float:
    """Restitution of the clipped nondimensional law ``S'' = -max(0, S^1.5 + 2 eta S^0.25 S')``."""
    def rhs(_t, y):
        s = max(y[0], 0.0)
        f = s**1.5 + 2.0 * eta * s**0.25 * y[1]
        return [y[1], -max(f, 0.0)]

    def out(_t, y):
        return y[0]
    out.terminal, out.direction = True, -1
    sol = solve_ivp(rhs, (0.0, 50.0), [0.0, 1.0], method="DOP853", rtol=1e-11, atol=1e-13,
                    events=out, max_step=0.01)
    return float(-sol.y_events[0][0][1])


@lru_cache(maxsize=32)
def eta_of_e(e: float) -> float:
    """Normal damping ratio ``eta_H`` giving restitution ``e`` (independent root-find)."""
    if e >= 1.0:
        return 0.0
    return float(brentq(lambda eta: _restitution(eta) - e, 1e-6, 5.0, xtol=1e-12))


@dataclass(frozen=True)
class Contact:
    """A binary contact: body a, body b (``m_b = inf`` for a rigid plane).

    ``lever(s)`` returns ``(l_a, l_b)`` (m) at overlap ``s``; ``i_a``, ``i_b`` are
    moments of inertia (kg m^2, ``inf`` for a plane).
    """

    m_a: float
    m_b: float
    i_a: float
    i_b: float
    r_eff: float
    e_star: float
    strat: float
    mu: float
    restitution: float
    plane: bool

    @property
    def m_eff(self) -> float:
        return 1.0 / (1.0 / self.m_a + 1.0 / self.m_b)

    def lever(self, s: float) -> tuple[float, float]:
        if self.plane:
            return self.r_a - s, 0.0
        return self.r_a - 0.5 * s, self.r_b - 0.5 * s

    @property
    def r_a(self) -> float:
        return self.r_eff if self.plane else 2.0 * self.r_eff  # equal spheres: R* = R/2

    @property
    def r_b(self) -> float:
        return 0.0 if self.plane else 2.0 * self.r_eff


def sphere_on_plane(m: float, r: float, e_star: float, nu: float, mu: float, e: float) -> Contact:
    """Sphere (mass ``m``, radius ``r``) on a rigid plane."""
    return Contact(m, math.inf, 0.4 * m * r * r, math.inf, r, e_star, mindlin_ratio(nu), mu, e, True)


def equal_spheres(m: float, r: float, e_star: float, nu: float, mu: float, e: float) -> Contact:
    """Two equal spheres (each mass ``m``, radius ``r``)."""
    i = 0.4 * m * r * r
    return Contact(m, m, i, i, 0.5 * r, e_star, mindlin_ratio(nu), mu, e, False)


def impact(c: Contact, vn: float, u: float, q_a: float, q_b: float = 0.0) -> dict:
    """Integrate one contact from first touch to separation.

    Parameters
    ----------
    vn : float
        Approach speed (m/s, > 0).
    u, q_a, q_b : float
        Initial relative tangential velocity of the centres (m/s) and spin
        coordinates (rad/s) as defined in the module docstring.

    Returns
    -------
    dict
        ``vn, u, q_a, q_b`` at separation (``vn`` > 0 receding) and ``duration_s``.
    """
    k_h = 4.0 / 3.0 * c.e_star * math.sqrt(c.r_eff)
    m = c.m_eff
    eta = eta_of_e(c.restitution)
    c_h = 2.0 * eta * math.sqrt(m * k_h)
    inv_m = 1.0 / c.m_a + 1.0 / c.m_b
    inv_ia = 1.0 / c.i_a
    inv_ib = 0.0 if math.isinf(c.i_b) else 1.0 / c.i_b

    def forces(y):
        s, v, xi, uu, qa, qb = y
        s = max(s, 0.0)
        la, lb = c.lever(s)
        fn = max(k_h * s**1.5 + c_h * s**0.25 * v, 0.0)
        vt = uu + la * qa + lb * qb
        xmax = c.mu * s * c.strat
        if xmax <= 0.0:
            return fn, 0.0, vt, xmax, la, lb
        ratio = min(abs(xi) / xmax, 1.0)
        zeta = 1.0 - ratio
        ft = -c.mu * fn * (1.0 - zeta**1.5) * math.copysign(1.0, xi) if xi != 0.0 else 0.0
        if zeta > 0.0 and fn > 0.0:
            ft -= eta * math.sqrt(6.0 * c.mu * m * fn / xmax) * zeta**0.25 * vt
        return fn, ft, vt, xmax, la, lb

    def rhs(_t, y):
        fn, ft, vt, xmax, la, lb = forces(y)
        xi = y[2]
        if xmax > 0.0 and abs(xi) >= xmax:
            sg = math.copysign(1.0, xi)
            dxi = sg * min(sg * vt, c.mu * c.strat * y[1])
        else:
            dxi = vt
        return [y[1], -fn * inv_m, dxi, ft * inv_m, la * ft * inv_ia, lb * ft * inv_ib]

    def out(_t, y):
        return y[0]
    out.terminal, out.direction = True, -1
    tc = 3.21807 * (m / k_h) ** 0.4 * vn**-0.2
    sol = solve_ivp(rhs, (0.0, 5.0 * tc), [0.0, vn, 0.0, u, q_a, q_b], method="DOP853",
                    rtol=1e-10, atol=1e-14, events=out, max_step=tc / 400)
    y = sol.y_events[0][0]
    return {"vn": float(-y[1]), "u": float(y[3]), "q_a": float(y[4]), "q_b": float(y[5]),
            "duration_s": float(sol.t_events[0][0])}


def impacts(c: Contact, vn, u, q_a, q_b=0.0) -> dict[str, np.ndarray]:
    """:func:`impact` over arrays of initial conditions (broadcast)."""
    vn, u, q_a, q_b = np.broadcast_arrays(*(np.asarray(x, dtype=float) for x in (vn, u, q_a, q_b)))
    rows = [impact(c, *args) for args in zip(vn.ravel(), u.ravel(), q_a.ravel(), q_b.ravel(), strict=True)]
    return {k: np.array([r[k] for r in rows]).reshape(vn.shape) for k in rows[0]}
