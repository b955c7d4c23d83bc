"""Engine tests: conservation, rotating paddle, sources, sinks, events, outputs."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest

from msmill.dem import Rotation, Simulation
from msmill.errors import MsmillInputError


def gas(n_side: int, r: float, spacing: float, speed: float, *, e=1.0, mu=0.0, seed=3, **kw):
    side = n_side * spacing
    sim = Simulation((0, 0, 0), (side, side, side), periodic=(True, True, True),
                     gravity_m_s2=(0, 0, 0), **kw)
    sim.add_material("rock", youngs_modulus_pa=2e10, poisson_ratio=0.25, density_kg_m3=2700)
    sim.set_interaction("rock", "rock", restitution=e, friction=mu)
    g = (np.stack(np.meshgrid(*[np.arange(n_side)] * 3, indexing="ij"), -1).reshape(-1, 3)
         + 0.5) * spacing
    rng = np.random.default_rng(seed)
    g += rng.uniform(-1, 1, g.shape) * 0.4 * (spacing - 2 * r)
    v = rng.normal(0, speed, g.shape)
    v -= v.mean(axis=0)
    w = rng.normal(0, speed / r, g.shape) if mu > 0 else None
    sim.add_particles(g, r, v, material="rock", angular_velocities_rad_s=w)
    return sim


def test_frictionless_elastic_gas_conserves_energy():
    """Energy between collisions (no contact open, so the leapfrog velocity is exact)."""
    sim = gas(4, 0.005, 0.0125, 5.0)
    sim._pack()
    dt = sim.contact_time_s(10.0) / 200
    e0 = sim.kinetic_energy_j()
    free = []

    def cb(s):
        if s.contact_energy_j() == 0.0:
            free.append(s.kinetic_energy_j())

    sim.run(10_000 * dt, dt_s=dt, progress=False, callback=cb, callback_every=50)
    assert sim.stats["steps"] == 10_000
    assert len(sim.events()) >= 10  # collisions happened
    assert len(free) >= 10
    assert np.max(np.abs(np.array(free) - e0)) / e0 < 1e-6


def test_momentum_conserved_in_periodic_box_with_friction_and_damping():
    sim = gas(6, 0.005, 0.0115, 5.0, e=0.5, mu=0.4)
    p0 = sim.momentum_kg_m_s()
    scale = float(np.sum(sim.particle_arrays()["mass"]) * 5.0)
    ke0 = sim.kinetic_energy_j()
    sim.run(3e-3, dt_s=2e-7, progress=False)
    assert np.all(np.abs(sim.momentum_kg_m_s() - p0) < 1e-12 * scale)
    assert sim.kinetic_energy_j() < 0.9 * ke0
    ev = sim.events()
    assert len(ev) > 50
    # energy book-keeping: closed events dissipated what the particles lost
    assert (ev.dissipated_j.dropna() > -1e-12).all()



@pytest.mark.parametrize("parallel", [False, True])
def test_momentum_conserved_in_dilute_gas_on_the_sparse_integration_path(parallel):
    """Solid fraction ~0.02, no gravity: most particles have no candidates, so the integration
    visits only the others (the two-loop form of ``_integrate_chunk``); the partner shares must
    reach the particles there as they do on the dense path (the test above)."""
    sim = gas(8, 0.005, 0.03, 8.0, e=0.5, mu=0.4, parallel=parallel, parallel_min_particles=1)
    p0 = sim.momentum_kg_m_s()
    scale = float(np.sum(sim.particle_arrays()["mass"]) * 8.0)
    idle = []
    sim.run(6e-3, dt_s=1e-6, progress=False, callback_every=200,
            callback=lambda s: idle.append(float(np.mean(s._kind == 0))))
    assert min(idle) > 0.5  # the sparse form was taken at every sampled step
    assert len(sim.events()) > 100
    assert np.all(np.abs(sim.momentum_kg_m_s() - p0) < 1e-12 * scale)

def test_rotating_paddle_hits_resting_sphere_closed_form():
    om, h, r = 50.0, 0.004, 0.01  # rad/s, plate half thickness (m), sphere radius (m)
    rho_s, phi0 = 0.2, math.radians(60.0)  # sphere at 0.2 m from the axis, 60 deg
    sim = Simulation((-0.5, -0.5, -0.5), (0.5, 0.5, 0.5), gravity_m_s2=(0, 0, 0))
    sim.add_material("rock", youngs_modulus_pa=1e9, poisson_ratio=0.25, density_kg_m3=2700)
    sim.add_material("steel", youngs_modulus_pa=2e11, poisson_ratio=0.3, density_kg_m3=7800)
    sim.set_interaction("rock", "steel", restitution=0.2, friction=0.3)
    rot = Rotation((0, 0, 0), (0, 0, 1), om)
    # paddle along +x at t = 0, 0.05-0.3 m from the axis, turning towards +y
    gid = sim.add_box((0.175, 0, 0), (0.125, h, 0.05), material="steel", tag="flinger",
                      group=3, rotation=rot)
    sim.add_particles([[rho_s * math.cos(phi0), rho_s * math.sin(phi0), 0]], r,
                      material="rock")
    t_hit = (phi0 - math.asin((r + h) / rho_s)) / om
    vn = om * math.sqrt(rho_s**2 - (r + h) ** 2)
    sim.run(t_hit * 1.02, dt_s=2e-6, progress=False, max_relative_speed_m_s=12)
    ev = sim.events()
    assert len(ev) == 1
    row = ev.iloc[0]
    assert row.partner_kind == 1 and row.partner_id == gid
    assert row.partner_tag == "flinger" and row.partner_group == 3
    assert row.time_s == pytest.approx(t_hit, rel=0.005)
    assert row.vn_m_s == pytest.approx(vn, rel=0.005)
    # contact point on the paddle face, at the predicted radius
    assert math.hypot(row.x_m, row.y_m) == pytest.approx(math.hypot(
        math.sqrt(rho_s**2 - (r + h) ** 2), h), rel=0.005)
    g = sim.geometry()
    assert list(g.columns[:4]) == ["geom_id", "kind", "tag", "group"]
    assert g.kind.iloc[0] == "box" and g.rotating.iloc[0]


def test_source_mass_flow_and_no_overlap():
    sim = Simulation((0, 0, 0), (0.3, 0.3, 0.3), gravity_m_s2=(0, 0, 0))
    sim.add_material("rock", youngs_modulus_pa=1e8, poisson_ratio=0.25, density_kg_m3=2700)
    sim.set_interaction("rock", "rock", restitution=0.5, friction=0.4)
    rate = 2.0
    sim.add_source((0.05, 0.05, 0.05), (0.25, 0.25, 0.25), rate,
                   radii_m=([0.004, 0.006], [0.7, 0.3]), material="rock", seed=4,
                   insert_interval_s=1e-3)
    sim.run(0.02, dt_s=1e-5, progress=False)
    a = sim.particle_arrays()
    mass = a["mass"].sum()
    # mass owed at the last insertion (t = 0.02 s) minus less than one particle
    m_big = 2700 * 4 / 3 * math.pi * 0.006**3
    assert rate * 0.02 - m_big <= mass <= rate * 0.02
    d = np.linalg.norm(a["pos"][:, None] - a["pos"][None], axis=-1)
    rr = a["rad"][:, None] + a["rad"][None]
    np.fill_diagonal(d, np.inf)
    assert np.all(d >= rr)
    assert len(sim.events()) == 0  # nothing moves, nothing touches
    assert set(np.round(a["rad"], 6)) == {0.004, 0.006}
    ts = sim.timeseries()
    assert ts.mass_kg.is_monotonic_increasing
    # nothing leaves: the mass the source placed is the mass in the box at every record
    np.testing.assert_allclose(ts.mass_in_kg, ts.mass_kg, rtol=1e-12)


def test_sink_removal_times_and_lost_particles():
    sim = Simulation((0, 0, 0), (1, 1, 1), gravity_m_s2=(0, 0, 0))
    sim.add_material("rock", youngs_modulus_pa=1e8, poisson_ratio=0.25, density_kg_m3=2700)
    sim.add_sink((0, 0, 0), (1, 1, 0.1), tag="outlet")
    v = np.array([1.0, 2.0, 4.0])
    ids = sim.add_particles([[0.5, 0.2, 0.5], [0.5, 0.5, 0.5], [0.5, 0.8, 0.5]], 0.01,
                            np.outer(v, [0, 0, -1]), material="rock")
    ids_lost = sim.add_particles([[0.95, 0.5, 0.5]], 0.01, [[2.0, 0, 0]], material="rock")
    dt = 1e-4
    with pytest.warns(UserWarning, match="lost"):
        sim.run(0.3, dt_s=dt, progress=False)
    rem = sim.removed().set_index("particle_id")
    assert set(rem.index) == {*ids[1:], *ids_lost}  # the slow one has not arrived
    for k in (1, 2):
        assert rem.loc[ids[k], "time_s"] == pytest.approx(0.4 / v[k], abs=1.01 * dt)
        assert rem.loc[ids[k], "tag"] == "outlet"
    assert rem.loc[ids_lost[0], "tag"] == "lost"
    assert rem.loc[ids_lost[0], "time_s"] == pytest.approx(0.025, abs=1.01 * dt)
    ts = sim.timeseries()
    m = 2700 * 4 / 3 * math.pi * 0.01**3
    assert ts.mass_out_kg.iloc[-1] == pytest.approx(2 * m)
    assert ts.n_lost.iloc[-1] == 1 and sim.n_particles == 1


def test_events_once_per_contact_with_onset_vn_and_repeated_runs():
    sim = Simulation((-0.5, -0.5, -0.5), (0.5, 0.5, 0.5), gravity_m_s2=(0, 0, -9.81))
    sim.add_material("rock", youngs_modulus_pa=1e8, poisson_ratio=0.25, density_kg_m3=2700)
    sim.add_material("steel", youngs_modulus_pa=2e11, poisson_ratio=0.3, density_kg_m3=7800)
    sim.set_interaction("rock", "steel", restitution=0.5, friction=0.3)
    sim.set_interaction("rock", "rock", restitution=0.5, friction=0.4)
    sim.add_plane((0, 0, -0.4), (0, 0, 1), material="steel", tag="floor")
    h = 0.2
    (drop,) = sim.add_particles([[0, 0, -0.4 + 0.01 + h]], 0.01, material="rock")
    # a pair colliding head-on at 3 m/s, far from the floor in time
    pair = sim.add_particles([[0.2, 0.3, 0.3], [0.3, 0.3, 0.3]], 0.01, [[1.5, 0, 0], [-1.5, 0, 0]],
                             material="rock")
    calls = []
    sim.run(0.1, progress=False, max_relative_speed_m_s=5, callback=lambda s: calls.append(
        s.time_s), callback_every=100)
    t1 = sim.time_s
    sim.run(0.35, progress=False, max_relative_speed_m_s=5, safety=0.02)  # continues
    assert sim.time_s == pytest.approx(t1 + 0.35, abs=sim.dt_s)
    assert len(calls) >= 5
    ev = sim.events()
    pp = ev[(ev.partner_kind == 0) & ev.particle_id.isin(pair) & ev.partner_id.isin(pair)]
    assert len(pp) == 1
    assert pp.vn_m_s.iloc[0] == pytest.approx(3.0, rel=1e-3)  # gravity adds nothing along x
    fl = ev[(ev.partner_tag == "floor") & (ev.particle_id == drop)]
    first = fl.iloc[0]
    assert first.vn_m_s == pytest.approx(math.sqrt(2 * 9.81 * h), rel=5e-3)
    # bounces: each onset once, strictly ordered, each ended before the next began
    assert (fl.time_s.diff().dropna() > 0).all()
    assert (fl.end_time_s.iloc[:-1].to_numpy() <= fl.time_s.iloc[1:].to_numpy()).all()
    assert fl.vn_m_s.iloc[1] == pytest.approx(0.5 * first.vn_m_s, rel=0.02)
    # early stop through the callback
    n = sim.run(0.1, progress=False, max_relative_speed_m_s=5, callback=lambda s: True,
                callback_every=10)
    assert n == 10


def test_geometry_box_cylinder_contacts_and_rotation():
    from msmill.dem import kernels as K

    g = np.zeros((1, 16))
    # box of half extents (0.1, 0.2, 0.3) centred at origin, axes = identity
    g[0, 3:12] = np.eye(3).ravel()
    g[0, 12:15] = (0.1, 0.2, 0.3)
    ok, s, nx, ny, nz, cx, cy, cz = K.geom_contact(K.BOX, g, 0, 0.105, 0.0, 0.0, 0.01)
    assert ok and s == pytest.approx(0.005) and (nx, ny, nz) == (-1.0, 0.0, 0.0)
    assert (cx, cy, cz) == pytest.approx((0.1, 0, 0))
    # edge: nearest point on the edge x = 0.1, y = 0.2
    ok, s, nx, ny, nz, cx, cy, cz = K.geom_contact(K.BOX, g, 0, 0.105, 0.205, 0.0, 0.01)
    assert ok and s == pytest.approx(0.01 - 0.005 * math.sqrt(2))
    assert (nx, ny) == pytest.approx((-1 / math.sqrt(2), -1 / math.sqrt(2)))
    assert not K.geom_contact(K.BOX, g, 0, 0.12, 0.0, 0.0, 0.01)[0]
    # centre inside: pushed out through the nearest face
    ok, s, nx, ny, nz, *_ = K.geom_contact(K.BOX, g, 0, 0.0, 0.0, 0.29, 0.01)
    assert ok and s == pytest.approx(0.02) and nz == -1.0
    # rotating the box by 90 deg about z moves its x-face to y
    rot = np.zeros((1, 8))
    rot[0, 3:8] = (0, 0, 1, math.pi / 2, 1)
    cur = np.zeros_like(g)
    g2 = g.copy()
    g2[0, 0:3] = (0.5, 0, 0)
    K.update_geometry(g2, rot, np.array([K.BOX], np.int32), 1.0, cur)
    assert cur[0, 0:3] == pytest.approx((0, 0.5, 0), abs=1e-12)
    ok, s, nx, ny, *_ = K.geom_contact(K.BOX, cur, 0, 0.0, 0.5 + 0.105, 0.0, 0.01)
    assert ok and s == pytest.approx(0.005) and ny == pytest.approx(-1.0)
    # cylinders: solid (outside) and tube (inside)
    c = np.zeros((1, 16))
    c[0, 3:9] = (0, 0, 1, 1.0, 0.1, 0.0)  # axis +z, length 1, radius 0.1
    ok, s, nx, ny, nz, cx, cy, cz = K.geom_contact(K.CYL, c, 0, 0.105, 0.0, 0.5, 0.01)
    assert ok and s == pytest.approx(0.005) and nx == pytest.approx(-1.0)
    ok, s, nx, ny, nz, *_ = K.geom_contact(K.CYL, c, 0, 0.0, 0.05, -0.005, 0.01)
    assert ok and s == pytest.approx(0.005) and nz == pytest.approx(1.0)
    c[0, 8] = 1.0
    ok, s, nx, ny, nz, cx, cy, cz = K.geom_contact(K.CYL, c, 0, 0.0, 0.095, 0.5, 0.01)
    assert ok and s == pytest.approx(0.005) and ny == pytest.approx(1.0)
    assert (cx, cy, cz) == pytest.approx((0, 0.1, 0.5))
    assert not K.geom_contact(K.CYL, c, 0, 0.0, 0.05, 0.5, 0.01)[0]


def test_sphere_rolls_inside_rotating_drum_and_outputs(tmp_path):
    sim = Simulation((-0.3, -0.1, -0.3), (0.3, 0.1, 0.3), periodic=(False, True, False),
                     gravity_m_s2=(0, 0, -9.81))
    sim.add_material("rock", youngs_modulus_pa=1e8, poisson_ratio=0.25, density_kg_m3=2700)
    sim.add_material("steel", youngs_modulus_pa=2e11, poisson_ratio=0.3, density_kg_m3=7800)
    sim.set_interaction("rock", "steel", restitution=0.2, friction=0.3)
    sim.set_interaction("rock", "rock", restitution=0.5, friction=0.4)
    drum = Rotation((0, 0, 0), (0, 1, 0), 3.0)
    sim.add_cylinder((0, -0.2, 0), (0, 0.2, 0), 0.25, material="steel", tag="liner",
                     rotation=drum, inside=True)
    sim.add_particles([[0, 0, -0.24]], 0.01, material="rock")
    sim.run(0.5, progress=True, max_relative_speed_m_s=2, snapshot_every_s=0.1,
            snapshot_times_s=[0.123, 0.31])
    ev = sim.events()
    assert (ev.partner_tag == "liner").all() and len(ev) >= 1
    a = sim.particle_arrays()
    r = np.hypot(a["pos"][0, 0], a["pos"][0, 2])
    assert 0.235 < r < 0.2405  # resting on the liner (small overlap)
    assert np.linalg.norm(a["vel"][0]) > 0.1  # dragged along by the rotating wall
    snaps = sim.snapshots()
    assert len(snaps) == 7 and snaps[0][1].shape[0] == 1
    times = sorted(t for t, _ in snaps)
    assert any(abs(t - 0.123) <= sim.dt_s for t in times)
    assert any(abs(t - 0.31) <= sim.dt_s for t in times)
    assert isinstance(sim.snapshot(), pd.DataFrame)
    p = sim.write_events_parquet(tmp_path / "ev.parquet")
    back = pd.read_parquet(p)
    assert list(back.columns[:14]) == [
        "time_s", "particle_id", "partner_kind", "partner_id", "radius_m", "partner_radius_m",
        "x_m", "y_m", "z_m", "vn_m_s", "vt_m_s", "end_time_s", "peak_overlap_m", "dissipated_j"]
    vtu = sim.write_vtu(tmp_path / "p.vtu")
    meshio = pytest.importorskip("meshio")  # reader only; the writer has no dependency
    m = meshio.read(vtu)
    assert m.points.shape == (1, 3) and "radius_m" in m.point_data


def test_event_buffer_flushes_keep_every_event():
    frames = []
    for rows in (8, 100_000):
        sim = gas(6, 0.005, 0.0115, 5.0, e=0.5, mu=0.4, event_buffer_rows=rows, n_chunks=4)
        sim.run(2e-3, dt_s=2e-7, progress=False)
        frames.append(sim.events())
    small, big = frames
    assert len(big) > 100
    pd.testing.assert_frame_equal(small, big)
    closed = big.dropna(subset=["end_time_s"])
    assert (closed.end_time_s > closed.time_s).all()
    assert (closed.peak_overlap_m > 0).all()


def test_sparse_domain_gets_a_small_cell_grid_and_still_finds_contacts():
    """A few rocks in a large periodic domain: the grid follows the particle count
    (every rebuild sweeps it), periodic axes keep >= 3 cells, contacts are found."""
    sim = Simulation((0, 0, 0), (2.0, 0.1, 3.0), periodic=(False, True, False), gravity_m_s2=(0, 0, 0))
    sim.add_material("rock", youngs_modulus_pa=2e10, poisson_ratio=0.25, density_kg_m3=2700)
    sim.set_interaction("rock", "rock", restitution=0.5, friction=0.4)
    # two head-on pairs, one of them across the periodic boundary along y
    pos = [(1.0, 0.05, 1.5), (1.03, 0.05, 1.5), (0.5, 0.006, 0.5), (0.5, 0.094, 0.5)]
    vel = [(1.0, 0, 0), (-1.0, 0, 0), (0, -1.0, 0), (0, 1.0, 0)]
    sim.add_particles(np.array(pos), 0.005, np.array(vel), material="rock")
    sim.run(0.02, progress=False)
    assert np.prod(sim._ncell) <= 4096
    assert sim._ncell[1] >= 3
    ev = sim.events()
    pairs = {tuple(sorted((int(a), int(b)))) for a, b in zip(ev.particle_id, ev.partner_id, strict=True)}
    assert len(pairs) == 2, pairs
    assert np.allclose(np.sort(ev.vn_m_s.to_numpy()), 2.0, rtol=1e-3)


def _plate_kick(safety: float) -> tuple[float, float]:
    """A frictionless rotating plate hits a resting rock; return (onset vn, rebound speed)."""
    omega, rc = 157.08, 0.15
    sim = Simulation((-0.5, -0.2, -0.5), (0.5, 0.2, 0.5), gravity_m_s2=(0, 0, 0))
    sim.add_material("rock", youngs_modulus_pa=5e10, poisson_ratio=0.25, density_kg_m3=2700)
    sim.add_material("steel", youngs_modulus_pa=2.1e11, poisson_ratio=0.3, density_kg_m3=7800)
    sim.set_interaction("rock", "steel", restitution=0.2, friction=0.0)
    rot = Rotation(axis_point_m=(0, 0, 0), axis_dir=(0, 1, 0), omega_rad_s=omega)
    sim.add_box((0.12, 0.0, 0.0), (0.07, 0.04, 0.006), axes=np.eye(3), material="steel",
                tag="flinger", group=0, rotation=rot)
    a = math.radians(30)
    sim.add_particles(np.array([[rc * math.cos(a), 0.0, -rc * math.sin(a)]]), 0.005,
                      np.zeros((1, 3)), material="rock")
    sim.run(0.006, max_relative_speed_m_s=omega * 0.19 + 5, safety=safety, progress=False)
    s = sim.snapshot()
    return float(sim.events().vn_m_s.iloc[0]), float(np.sqrt(s.vx_m_s**2 + s.vy_m_s**2 + s.vz_m_s**2).iloc[0])


def test_rotating_plate_kick_returns_one_plus_e_times_the_plate_speed():
    """Against a plate of infinite mass the rock leaves at (1 + e) times the normal
    plate speed at the contact point; larger time steps than the cap gain energy."""
    vn, v = _plate_kick(0.2)
    assert vn == pytest.approx(157.08 * 0.15, rel=0.01)
    assert v == pytest.approx(1.2 * vn, rel=0.02)
    from msmill.errors import MsmillInputError

    with pytest.raises(MsmillInputError, match="safety"):
        _plate_kick(0.3)


def test_geometry_candidates_do_not_depend_on_the_row_width_guess():
    # candidates are swept into padded rows of a guessed width; a row that overflows
    # makes the sweep run again wider, and the result must be the same list, which
    # must equal a brute-force test of every primitive
    from msmill.dem import kernels as K

    sim = Simulation((0, 0, 0), (0.2, 0.2, 0.2), gravity_m_s2=(0, 0, 0))
    sim.add_material("rock", youngs_modulus_pa=1e9, poisson_ratio=0.25, density_kg_m3=2700)
    sim.add_material("steel", youngs_modulus_pa=2e11, poisson_ratio=0.3, density_kg_m3=7800)
    sim.set_interaction("rock", "steel", restitution=0.5, friction=0.3)
    sim.set_interaction("rock", "rock", restitution=0.5, friction=0.3)
    for k in range(6):  # a fan of plates through one corner: every particle there sees several
        a = k * math.pi / 12
        sim.add_box((0.05, 0.05, 0.1), (0.04, 0.002, 0.09),
                    axes=((math.cos(a), math.sin(a), 0), (-math.sin(a), math.cos(a), 0), (0, 0, 1)),
                    material="steel")
    sim.add_plane((0, 0, 0), (0, 0, 1), material="steel")
    rng = np.random.default_rng(5)
    sim.add_particles(rng.uniform(0.01, 0.09, (40, 3)), 0.004, material="rock")
    sim.run(1e-6, dt_s=1e-7, progress=False)
    p = sim._p
    args = (p["pos"], p["rad"], sim._skin, sim._gcur, sim._grot, sim._gkind, sim._gbound, sim._gspan,
            sim._periodic, sim._box_len, sim._img_box, sim._lo, sim._gcl, sim._gnc, sim._ggrid[0],
            sim._ggrid[1], False)
    narrow = K.build_geom_candidates(*args, 1)
    wide = K.build_geom_candidates(*args, 64)
    assert narrow[2] == wide[2] >= 3
    np.testing.assert_array_equal(narrow[0], wide[0])
    np.testing.assert_array_equal(narrow[1], wide[1])
    for i in range(p["pos"].shape[0]):
        x, y, z = p["pos"][i]
        brute = [g for g in range(len(sim._geoms))
                 if K._geom_candidate(g, x, y, z, p["rad"][i], sim._skin, sim._gcur, sim._grot,
                                      sim._gkind, sim._gbound)]
        assert sorted(wide[1][wide[0][i]:wide[0][i + 1]] // K.KEY_STRIDE) == brute


def test_skin_set_between_runs_regrids_the_cells_and_misses_no_contact():
    """A wider Verlet skin set between runs: fewer rebuilds, cells re-sized to the new cut-off, energy
    conserved as with the default skin."""
    sim = gas(8, 0.005, 0.0125, 5.0)
    sim._pack()
    dt = sim.contact_time_s(10.0) / 200
    sim.run(2000 * dt, dt_s=dt, progress=False)
    assert sim.neighbor_skin_m == pytest.approx(0.0025)  # the engine default: half the smallest radius
    per_rebuild = sim.stats["steps"] / sim.stats["rebuilds"]
    e0 = sim.kinetic_energy_j() + sim.contact_energy_j()
    n_events = len(sim.events())
    total = []

    def cb(s):
        total.append(s.kinetic_energy_j() + s.contact_energy_j())

    sim.neighbor_skin_m = 0.015  # cut-off 0.025 m: twice the old cells
    assert np.all(sim._cell_len >= 2 * 0.005 + 0.015)  # the cells hold the new cut-off
    s0, r0 = sim.stats["steps"], sim.stats["rebuilds"]
    sim.run(8000 * dt, dt_s=dt, progress=False, callback=cb, callback_every=50)
    assert (sim.stats["steps"] - s0) / (sim.stats["rebuilds"] - r0) > 3 * per_rebuild
    assert len(sim.events()) - n_events >= 20  # collisions happened under the new lists
    # kinetic + elastic contact energy: 2.9e-4 at most, as with the default skin (the leapfrog's error in
    # contacts); a missed contact would jump it by the pair's overlap energy
    assert np.max(np.abs(np.array(total) - e0)) / e0 < 1e-3
    with pytest.raises(MsmillInputError, match="neighbor_skin_m"):
        sim.neighbor_skin_m = -1.0
