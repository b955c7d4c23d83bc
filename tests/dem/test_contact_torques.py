"""Contact torques: angular momentum of a pair contact, and the wall lever at large overlap.

Two checks independent of the Chung & Ooi tables:

- a frictional pair contact exerts equal and opposite forces at one contact
  point, so the total angular momentum ``sum(m x cross v + I omega)`` about any
  fixed point is conserved (an oblique, spinning, three-dimensional impact, so
  every torque component matters);
- against a rigid plane the tangential force acts on the plane, at ``R - s``
  from the centre. A soft sphere (overlap up to ~8 % of its radius) makes the
  lever visible: the engine's spin-up against the independent fine
  integration of the same law (``chung_ooi_reference``, lever ``R - s``).
"""

from __future__ import annotations

import math

import chung_ooi_reference as cref
import numpy as np
from test_chung_ooi import _estar, _impacts_on_plane, hertz, sphere_mass

from msmill.dem import Simulation

COPPER = {"youngs_modulus_pa": 1.2e11, "poisson_ratio": 0.35, "density_kg_m3": 8900}
SOFT = {"youngs_modulus_pa": 1.0e7, "poisson_ratio": 0.3, "density_kg_m3": 1000}


def _angular_momentum(a: dict, m: float, r: float) -> np.ndarray:
    return (m * np.cross(a["pos"], a["vel"])).sum(axis=0) + 0.4 * m * r * r * a["omg"].sum(axis=0)


def test_oblique_spinning_pair_conserves_angular_momentum():
    r, v = 0.1, 0.2
    n = np.array([1.0, 2.0, 2.0]) / 3  # line of centres
    e = np.array([1.0, 0.3, -0.2])
    e /= np.linalg.norm(e)  # approach direction, oblique to n (e . n = 0.53)
    sim = Simulation((-1, -1, -1), (1, 1, 1), gravity_m_s2=(0, 0, 0))
    sim.add_material("cu", **COPPER)
    sim.set_interaction("cu", "cu", restitution=0.5, friction=0.4)
    sim.add_particles([-(r + 1e-7) * n, (r + 1e-7) * n], r, [v * e, -v * e], material="cu",
                      angular_velocities_rad_s=[[3.0, -2.0, 1.0], [-1.0, 2.0, 4.0]])
    m = sphere_mass(COPPER["density_kg_m3"], r)
    before = _angular_momentum(sim.particle_arrays(), m, r)
    tc = hertz(m / 2, r / 2, COPPER["youngs_modulus_pa"] / (2 * (1 - 0.35**2)), 2 * v * (e @ n))[2]
    sim.run(1.5 * tc, dt_s=tc / 1000, progress=False)
    a = sim.particle_arrays()
    assert len(sim.events()) == 1
    after = _angular_momentum(a, m, r)
    spin_change = 0.4 * m * r * r * np.abs(a["omg"] - [[3.0, -2.0, 1.0], [-1.0, 2.0, 4.0]]).max()
    assert spin_change > 0.02 * m * v * r  # friction changed the spins noticeably
    np.testing.assert_allclose(after, before, rtol=0, atol=1e-9 * m * v * r)  # measured 2e-14
    # and linear momentum, trivially
    np.testing.assert_allclose(a["vel"].sum(axis=0), 0.0, atol=1e-12)


def test_wall_lever_is_radius_minus_overlap():
    mu, e, vn, r = 0.3, 0.7, 2.0, 0.05
    vt = np.array([2.0 * vn, 0.5 * vn])  # gross sliding (tan 63 deg > 3.5 mu (1 + e)) and partial slip
    m = sphere_mass(SOFT["density_kg_m3"], r)
    dmax = hertz(m, r, _estar(SOFT), vn)[0]
    assert 0.05 < dmax / r < 0.12  # the lever R - s differs from R by up to ~8 %
    cases = [{"e": e, "mu": mu, "v": (u, 0, -vn)} for u in vt]
    vel, omg, _ = _impacts_on_plane(SOFT, r, cases, steps=2000)
    ref = cref.impacts(cref.sphere_on_plane(m, r, _estar(SOFT), SOFT["poisson_ratio"], mu, e), vn, vt, 0.0)
    spin = omg[:, 1] * r
    np.testing.assert_allclose(spin / vt, -ref["q_a"] * r / vt, rtol=0, atol=1e-3)
    np.testing.assert_allclose(vel[:, 0] / vt, ref["u"] / vt, rtol=0, atol=1e-3)
    # gross sliding: the spin-up falls short of the rigid-lever value 2.5 mu (1 + e) vn
    # by the lever's mean shortening, a visible fraction
    rigid = 2.5 * mu * (1 + e) * vn
    assert spin[0] < rigid * (1 - 0.01)
    assert math.isclose(spin[0], rigid, rel_tol=0.1)
