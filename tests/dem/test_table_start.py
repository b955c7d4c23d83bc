"""Warm start from the stage table's expected hold-up: clear of the geometry, no overlaps, mass per compartment."""

import warnings

import numpy as np
import pytest

import msmill.dem.mill.run as run_mod
from msmill.dem.mill.run import RunSettings, run_mill
from msmill.dem.mill.scene import build_scene
from msmill.dem.mill.stats import stage_of_z
from msmill.dem.mill.warmstart import place_table_start, table_residence_s
from msmill.errors import MsmillInputError, OutOfDomainWarning
from msmill.machine import Machine, OperatingPoint
from msmill.stageparams import StageParameterTable, default_stage_table

M = Machine.default()
RHO = 2700.0
SLAB = 0.05  # half thickness of the roof and chute slabs (msmill.dem.mill.scene)
CHUTE_H = 0.4


def _scene(size=30.0, feed=30.0, gate=40.0, rpm=1500.0):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", OutOfDomainWarning)
        return build_scene(M, OperatingPoint(feed_tph=feed, speed_rpm=rpm, gate_deg=gate), size_mm=size,
                           mode="slice")


def _rocks(sc):
    s = sc.sim.snapshot()
    return s[["x_m", "y_m", "z_m"]].to_numpy(), s["radius_m"].to_numpy()


def _dist_to_rect(x, z, x0, x1, z0, z1):
    """Distance in the x-z plane from points to an axis-aligned rectangle (0 inside)."""
    dx = np.maximum(np.maximum(x0 - x, x - x1), 0.0)
    dz = np.maximum(np.maximum(z0 - z, z - z1), 0.0)
    return np.hypot(dx, dz)


def _dist_to_segment(x, z, a, b):
    ax, az = a
    bx, bz = b
    t = np.clip(((x - ax) * (bx - ax) + (z - az) * (bz - az)) / ((bx - ax) ** 2 + (bz - az) ** 2), 0.0, 1.0)
    return np.hypot(x - ax - t * (bx - ax), z - az - t * (bz - az))


def assert_clear_of_geometry(sc, pos, rad):
    """Independent x-z check against every part of the mill (all but the flingers are extruded along y)."""
    x, z = pos[:, 0], pos[:, 2]
    hw, cw, roof = M.half_width_m, M.chute_width_m / 2, M.roof_z_m
    tol = 1e-9
    assert np.all(np.abs(x) <= hw - rad + tol), "rock in a liner"
    for stage in range(1, M.n_stages + 1):  # the swept circles hold the hubs and every flinger phase
        for side in (0, 1):
            d = np.hypot(x - M.rotor_x_m(side), z - M.stage_axis_z_m(stage))
            assert np.all(d >= M.tip_radius_m + rad - tol), f"rock in the swept circle of stage {stage}"
    for side, sgn in ((0, -1), (1, 1)):
        hinge = (sgn * hw, M.gate_hinge_z_m)
        tip = M.gate_tip_m(sc.op.gate_deg, side)
        assert np.all(_dist_to_segment(x, z, hinge, tip) >= rad - tol), "rock in a gate"
        reach = hw - abs(tip[0])
        if reach > 1e-12:  # nor under the gate, between it and the liner (rock there falls straight out)
            ax = sgn * x
            z_gate = hinge[1] + (tip[1] - hinge[1]) * (hw - ax) / reach
            assert not np.any((ax >= abs(tip[0])) & (z < z_gate)), "rock under a gate"
        roof_box = (cw, hw, roof, roof + 2 * SLAB) if sgn > 0 else (-hw, -cw, roof, roof + 2 * SLAB)
        assert np.all(_dist_to_rect(x, z, *roof_box) >= rad - tol), "rock in the roof"
        wall = (cw, cw + 2 * SLAB) if sgn > 0 else (-cw - 2 * SLAB, -cw)
        assert np.all(_dist_to_rect(x, z, *wall, roof, roof + CHUTE_H) >= rad - tol), "rock in a chute wall"
    assert np.all((z <= roof) | (np.abs(x) < cw)), "rock above the roof outside the chute"
    assert np.all(z < roof + CHUTE_H - rad) and np.all(z > 0), "rock above the chute lid or below the outlet"


def assert_no_overlap(sc, pos, rad):
    """Every pair of rocks apart (nearest periodic image along the slice)."""
    length = sc.length_m
    d = pos[:, None, :] - pos[None, :, :]
    d[..., 1] -= length * np.round(d[..., 1] / length)
    dist = np.sqrt((d**2).sum(-1))
    np.fill_diagonal(dist, np.inf)
    assert np.all(dist >= rad[:, None] + rad[None, :] - 1e-12), "overlapping rocks"


def chain_holdup_kg(run, feed_kg_s, n_steps=20000):
    """Steady hold-up per compartment by iterating the one-lag chain (independent of the linear solve)."""
    n = run.n_stages
    q = np.array([run.inlet_destinations[: n + 1]] + [st.destinations[: n + 1] for st in run.stages])
    h = np.zeros(n + 1)
    feed = np.zeros(n + 1)
    feed[0] = feed_kg_s * run.characteristic_time_s
    for _ in range(n_steps):
        h = h @ q + feed
    return h


@pytest.mark.parametrize(("size", "feed", "gate"), [(30.0, 30.0, 5.0), (30.0, 60.0, 40.0), (30.0, 30.0, 80.0),
                                                    (20.0, 30.0, 40.0), (10.0, 30.0, 15.0)])
def test_table_start_is_clear_of_the_geometry_and_of_itself(size, feed, gate):
    sc = _scene(size, feed, gate)
    rep = place_table_start(sc, seed=3)
    pos, rad = _rocks(sc)
    assert rep["n_placed"] == len(rad) > 0 and rep["kind"] == "table"
    assert_clear_of_geometry(sc, pos, rad)
    assert_no_overlap(sc, pos, rad)


def test_the_engine_sees_no_contact_at_the_start():
    """Placed at rest, rock that touched a plate, a flinger, a periodic image or another rock would record a contact."""
    sc = _scene(30.0, 30.0, 40.0)
    place_table_start(sc, seed=5, speed_m_s=0.0)
    sc.sim.run(2e-5, max_relative_speed_m_s=sc.max_impact_speed_m_s, safety=0.2, progress=False)
    assert len(sc.sim.events()) == 0


@pytest.mark.parametrize(("size", "feed"), [(30.0, 30.0), (20.0, 45.0), (10.0, 30.0)])
def test_mass_per_compartment_matches_the_chain_within_one_rock(size, feed):
    sc = _scene(size, feed)
    rep = place_table_start(sc, seed=1)
    pos, rad = _rocks(sc)
    placed = np.bincount(stage_of_z(M, pos[:, 2]), weights=RHO * 4 / 3 * np.pi * rad**3, minlength=M.n_stages + 2)
    assert placed[-1] == 0.0  # nothing below the outlet
    rock_kg = RHO * np.pi / 6 * (size / 1000) ** 3
    target = np.array(rep["compartment_target_kg"])
    assert np.all(np.abs(placed[:-1] - target) <= rock_kg)
    assert np.allclose(rep["compartment_placed_kg"], placed[:-1])
    # at a size of the table the target is that run's chain at this feed
    table = default_stage_table()
    [run] = [r for r in table.runs if abs(r.design.size_mm - size) < 1e-6]
    assert np.allclose(target, chain_holdup_kg(run, sc.feed_kg_s), rtol=1e-6)
    assert rep["placed_kg"] == pytest.approx(rep["target_kg"], abs=0.5 * len(target) * rock_kg)  # half a rock each


def test_residence_interpolates_in_log_size_and_scales_with_feed():
    table = default_stage_table()
    r14, _ = table_residence_s(14.0, 5)
    r20, _ = table_residence_s(20.0, 5)
    r17, src = table_residence_s(17.0, 5)
    w = np.log(17 / 14) / np.log(20 / 14)
    assert src["table_sizes_mm"] == pytest.approx([14.0, 20.0]) and src["table_weights"][1] == pytest.approx(w)
    assert np.allclose(r17, (1 - w) * r14 + w * r20)
    assert np.allclose(table_residence_s(40.0, 5)[0], table_residence_s(30.0, 5)[0])  # the end run outside
    a, b = place_table_start(_scene(30.0, 20.0), seed=0), place_table_start(_scene(30.0, 40.0), seed=0)
    assert np.allclose(np.array(b["compartment_target_kg"]), 2 * np.array(a["compartment_target_kg"]))
    # a table without destinations cannot give a start
    bare = StageParameterTable.model_validate(table.model_dump() | {"runs": [
        r.model_copy(update={"inlet_destinations": None}) for r in table.runs]})
    with pytest.raises(MsmillInputError, match="destinations"):
        table_residence_s(20.0, 5, bare)


def test_a_given_residence_replaces_the_tables():
    """``residence_s`` (a finished run's steady residence per compartment) sets the targets: feed x residence."""
    sc = _scene(10.0, 30.0)
    res = [0.28, 0.32, 0.11, 0.09, 0.06, 0.05]
    rep = place_table_start(sc, seed=2, residence_s=res)
    target = np.array(rep["compartment_target_kg"])
    assert np.allclose(target, sc.feed_kg_s * np.array(res))
    assert not np.allclose(target, sc.feed_kg_s * table_residence_s(10.0, M.n_stages)[0])
    pos, rad = _rocks(sc)
    placed = np.bincount(stage_of_z(M, pos[:, 2]), weights=RHO * 4 / 3 * np.pi * rad**3, minlength=M.n_stages + 2)
    assert np.all(np.abs(placed[:-1] - target) <= RHO * np.pi / 6 * 0.010**3)  # within one rock
    assert "given residence" in rep["source"] and "table_sizes_mm" not in rep
    for bad in ([0.3] * M.n_stages, [0.3] * M.n_stages + [-0.1], [0.3] * M.n_stages + [float("nan")], "fast"):
        with pytest.raises(MsmillInputError, match="residence_s"):
            place_table_start(_scene(10.0, 30.0), residence_s=bad)
    with pytest.raises(MsmillInputError, match=r"settings\.start_residence_s"):
        run_mill(M, OperatingPoint(feed_tph=30, speed_rpm=1500), size_mm=30.0,
                 settings=RunSettings(start="table", start_residence_s=[0.3, 0.3]))


def test_a_runs_compartment_residence_adds_up_to_its_residence_time():
    """The start a finished run offers (hold-up / rate per compartment) sums to its measured residence time."""
    run = default_stage_table().runs[0]
    res = run.compartment_residence_s()
    assert res is not None and len(res) == run.n_stages + 1 and min(res) > 0
    hold = run.inlet_holdup_kg + sum(st.mean_holdup_kg for st in run.stages)
    assert sum(res) == pytest.approx(hold / run.mass_out_rate_kg_s, rel=1e-12)
    assert sum(res) == pytest.approx(run.residence_time_s, rel=0.02)
    assert run.model_copy(update={"mass_out_rate_kg_s": None}).compartment_residence_s() is None


def test_refuses_a_used_scene_and_bad_inputs():
    sc = _scene()
    place_table_start(sc)
    with pytest.raises(MsmillInputError, match="fresh"):
        place_table_start(sc)
    with pytest.raises(MsmillInputError, match="speed"):
        place_table_start(_scene(), speed_m_s=-1.0)
    with pytest.raises(MsmillInputError, match="start"):
        run_mill(M, OperatingPoint(feed_tph=30, speed_rpm=1500), size_mm=30.0, settings=RunSettings(start="hot"))


def test_run_mill_starts_from_the_table_and_records_it(monkeypatch):
    """``RunSettings(start="table")`` fills the mill at t = 0 and the report goes into the provenance."""
    seen, stats_settings = [], []
    real = run_mod.place_table_start
    monkeypatch.setattr(run_mod, "place_table_start", lambda scene, **kw: seen.append(kw) or real(scene, **kw))
    real_stats = run_mod.compute_statistics
    monkeypatch.setattr(run_mod, "compute_statistics",
                        lambda *a, **kw: stats_settings.append(kw["settings"]) or real_stats(*a, **kw))
    # declare steady state at once and measure 0.2 ms: only the start and the bookkeeping are under test
    monkeypatch.setattr(run_mod, "_first_steady", lambda ts, feed, crit: (0.0, float(ts["time_s"].iloc[-1])))
    rs = RunSettings(chunk_s=1e-4, measure_s=2e-4, snapshot_every_s=1e-4, start="table", seed=7)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        run = run_mill(M, OperatingPoint(feed_tph=30, speed_rpm=1500, gate_deg=40), size_mm=30.0, settings=rs)
    assert seen == [{"seed": 7, "residence_s": None}]
    assert run.timeseries["mass_kg"].iloc[0] == pytest.approx(run.extra["warm_start"]["placed_kg"])
    prov = run.stats.run.provenance
    assert prov["warm_start"]["kind"] == "table" and prov["run_settings"]["start"] == "table"
    assert prov["warm_start"]["placed_fraction"] > 0.95
    # the mill never filled: no filling transport from the placed rock settling
    assert stats_settings and not any(ss.with_filling_transport for ss in stats_settings)
    assert run.stats.run.filling_transport is None
