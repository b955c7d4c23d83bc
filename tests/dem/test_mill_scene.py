"""Small, fast mill scenes through the real engine: mass balance, impact-speed bounds, streams."""

import warnings

import numpy as np
import pytest

from msmill.dem.mill.run import RunSettings, run_mill
from msmill.dem.mill.scene import (
    SKIN_RADII,
    build_scene,
    mill_skin_m,
    peak_overlap_fraction,
    scene_extent,
    softened_youngs_modulus,
)
from msmill.dem.mill.stats import RunStatistics, identify_impacts
from msmill.errors import OutOfDomainWarning
from msmill.machine import Machine, OperatingPoint

# two stages, slow shafts, big rocks: a coarse time step keeps this fast
MACHINE = Machine.default().model_copy(update={"n_stages": 2})
with warnings.catch_warnings():
    warnings.simplefilter("ignore", OutOfDomainWarning)
    OP = OperatingPoint(feed_tph=40, speed_rpm=600, bottom_speed_factor=1.0, gate_deg=40)


#: short runs: the steady-state test is relaxed, these tests check book-keeping, not convergence
SHORT = RunSettings(max_time_s=0.6, chunk_s=0.1, steady_window_s=0.1, rel_tol=0.5, trend_tol=5.0, balance_tol=5.0,
                    measure_s=0.3, snapshot_every_s=0.005)


def test_slice_rows_do_not_follow_the_engine_skin_and_the_skin_fits_the_slice():
    """A slice is sized with 1.5 radii of skin (17-19 mm rock keeps one row, 20 mm has two), and the
    engine's skin is 2.0 radii where the slice holds three cells of ``2 r_max + skin``, else what fits."""
    m = Machine.default()
    rows = {d: len(scene_extent(m, np.array([d]), "slice")[2]) for d in (6.0, 17.0, 19.0, 20.0, 30.0, 34.0)}
    assert rows == {6.0: 1, 17.0: 1, 19.0: 1, 20.0: 2, 30.0: 2, 34.0: 2}
    for d in np.arange(2.0, 60.0, 0.5):
        y0, y1, _rows, _scale = scene_extent(m, np.array([d]), "slice")
        skin_m = mill_skin_m(np.array([d]), y1 - y0)
        assert 0 < skin_m <= SKIN_RADII * d / 2000 + 1e-15
        assert y1 - y0 >= 3 * (d / 1000 + skin_m) * (1 - 1e-12)
    assert mill_skin_m(np.array([10.0])) == pytest.approx(0.010)  # 2.0 radii, nothing periodic
    assert mill_skin_m(np.array([17.0]), 0.1) == pytest.approx(0.1 / 3.003 - 0.017)  # the slice limits it
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", OutOfDomainWarning)
        sc = build_scene(MACHINE, OP, size_mm=18.0, mode="slice")
    assert sc.info["slice_rows"] == 1 and sc.sim._skin == pytest.approx(mill_skin_m(np.array([18.0]), 0.1))


@pytest.fixture(scope="module")
def small_run():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", OutOfDomainWarning)
        return run_mill(MACHINE, OP, size_mm=20.0, mode="slice", settings=SHORT)


def test_softened_modulus_respects_overlap_limit():
    from msmill.dem.mill.scene import RockMaterial

    rock = RockMaterial()
    e = softened_youngs_modulus(rock, 20.0, 0.05)
    assert e < rock.youngs_modulus_pa
    soft = RockMaterial(e, rock.poisson_ratio, rock.density_kg_m3)
    assert peak_overlap_fraction(soft, 20.0) == pytest.approx(0.05, rel=1e-6)
    # at 65 m/s real rock already exceeds 5 %: no softening
    assert softened_youngs_modulus(rock, 65.0, 0.05) == rock.youngs_modulus_pa


def test_scene_tags_groups_and_feed_scaling():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", OutOfDomainWarning)
        sc = build_scene(MACHINE, OP, size_mm=10.0, mode="slice")
    geo = sc.sim.geometry()
    fl = geo[geo["tag"] == "flinger"]
    assert sorted(fl["group"].unique()) == [0, 1, 2, 3]
    assert (fl.groupby("group").size() == MACHINE.flingers_per_row).all()
    assert {"liner", "hub", "gate", "chute", "flinger"} <= set(geo["tag"])
    assert sc.feed_kg_s == pytest.approx(40 / 3.6 * 0.1 / 0.6)
    # left rotors turn at +omega (sweeping down in the centre), right rotors at -omega
    om = fl.groupby("group")["omega_rad_s"].first()
    assert om[0] > 0 > om[1]
    big = build_scene(MACHINE, OP, size_mm=30.0, mode="slice")
    assert big.info["slice_rows"] == 2 and big.feed_kg_s == pytest.approx(40 / 3.6 * 0.2 / 0.6)


@pytest.fixture(scope="module")
def full_mixed_run():
    """Full mill (end walls, all six rows) fed a two-size PSD."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", OutOfDomainWarning)
        return run_mill(MACHINE, OP, feed_psd=([20.0, 30.0], [0.4, 0.6]), mode="full", settings=SHORT)


def _check_mass_balance(run, r_max_m: float) -> None:
    sim = run.scene.sim
    now = sim.snapshot()
    rem = run.removed
    ever = set(run.snapshots["particle_id"]) | set(run.events["particle_id"]) | set(rem["particle_id"])
    ids_now, ids_out = set(now["particle_id"]), set(rem["particle_id"])
    assert not ids_now & ids_out
    assert len(rem["particle_id"]) == len(ids_out)  # removed once
    assert ever <= ids_now | ids_out
    assert set(rem["tag"]) <= {"outlet"}  # nothing lost through the domain walls
    rho = run.scene.rock.density_kg_m3
    fed = rho * 4 / 3 * np.pi * (np.sum(now["radius_m"] ** 3) + np.sum(rem["radius_m"] ** 3))
    in_mill = run.timeseries["mass_kg"].iloc[-1]
    out = run.timeseries["mass_out_kg"].iloc[-1]
    assert fed == pytest.approx(in_mill + out, rel=1e-12)
    assert len(rem) > 0  # rock did leave through the outlet
    # the source delivered the requested feed (to within one particle)
    m1 = rho * 4 / 3 * np.pi * r_max_m**3
    assert abs(fed - run.scene.feed_kg_s * sim.time_s) < 2 * m1


def test_mass_balance_exact_per_particle(small_run):
    _check_mass_balance(small_run, 0.01)


def test_full_mill_mixed_feed_mass_balance_and_size_mix(full_mixed_run):
    _check_mass_balance(full_mixed_run, 0.015)
    sim = full_mixed_run.scene.sim
    assert full_mixed_run.scene.info["mode"] == "full"
    assert sim.geometry().query("tag == 'flinger'").shape[0] == 4 * 6 * MACHINE.flingers_per_row
    # fed mass fractions of the two sizes follow the PSD (0.4 / 0.6) to within sampling noise
    now, rem = sim.snapshot(), full_mixed_run.removed
    r = np.concatenate([now["radius_m"].to_numpy(), rem["radius_m"].to_numpy()])
    m = r**3
    assert set(np.round(r * 2000, 6)) == {20.0, 30.0}
    assert m[np.isclose(r, 0.01)].sum() / m.sum() == pytest.approx(0.4, abs=0.12)


def test_full_mill_statistics_regions_and_streams_by_size(full_mixed_run):
    st = full_mixed_run.stats.run
    assert st.mode == "full"
    # (the values of region weights and streams are checked by hand in test_mill_stats.py)
    for s in st.stages:
        # six horizontal regions along the shafts (full mode only), each region's rock counted
        assert len(s.region_weights) == 6 and len(s.region_streams) == 6
        assert s.n_transport_samples > 0
    by_size = full_mixed_run.stats.streams_by_size
    assert set(by_size["size_class"]) == {0, 1}
    # tagged mass per (stage, size) is the mass of whole rocks: a multiple of one rock's mass
    rho = full_mixed_run.scene.rock.density_kg_m3
    m_rock = rho * 4 / 3 * np.pi * np.array([0.01, 0.015]) ** 3
    n_tags = by_size["mass_kg"].to_numpy() / m_rock[by_size["size_class"].to_numpy()]
    np.testing.assert_allclose(n_tags, np.round(n_tags), atol=1e-6)
    # each stage's overall streams are the mass-weighted mean of its per-size streams
    for stage, grp in by_size.groupby("stage_from"):
        if stage < 1 or stage > MACHINE.n_stages:
            continue
        mean_pt = np.average(grp["pass_through"], weights=grp["mass_kg"])
        assert st.stages[stage - 1].pass_through == pytest.approx(mean_pt, abs=1e-9)


def test_primary_impacts_bounded_by_tip_speed_plus_rock_speed(small_run):
    ev = identify_impacts(MACHINE, small_run.events, small_run.snapshots)
    prim = ev[ev["is_primary"]]
    assert len(prim) > 10
    snaps = small_run.snapshots
    v_rock = float(np.sqrt(snaps["vx_m_s"] ** 2 + snaps["vy_m_s"] ** 2 + snaps["vz_m_s"] ** 2).max())
    speeds = OP.stage_speeds(MACHINE.n_stages)
    # no energy gain: a rock driven by the flingers cannot outrun (1 + e) x the fastest tip much,
    # plus what it gains falling through the mill (~8 m/s)
    tip_max = max(MACHINE.tip_speed_m_s(s) for s in speeds)
    assert v_rock <= 1.2 * tip_max + 10.0
    tip = np.array([MACHINE.tip_speed_m_s(speeds[s - 1]) for s in prim["stage"]])
    assert np.all(prim["vn_m_s"].to_numpy() <= tip + v_rock + 1e-9)
    # contact points lie inside the tip circle of their rotor
    raw = small_run.events.set_index(["time_s", "particle_id"])
    pts = raw.loc[list(zip(prim["time_s"], prim["particle_id"], strict=True)), ["x_m", "z_m"]].to_numpy()
    rot = prim["rotor"].to_numpy()
    ax = np.array([MACHINE.rotor_x_m(r % 2) for r in rot])
    az = np.array([MACHINE.stage_axis_z_m(r // 2 + 1) for r in rot])
    r_contact = np.hypot(pts[:, 0] - ax, pts[:, 1] - az)
    assert np.all(r_contact <= MACHINE.tip_radius_m + 0.002)


def test_statistics_valid_and_streams_sum_to_one(small_run):
    st = small_run.stats.run
    again = RunStatistics.from_json(st.to_json())
    assert again.n_stages == 2
    for s in st.stages:
        assert s.kickback + s.refeed + s.pass_through == pytest.approx(1.0)
        assert 0 <= s.primary_hit_probability <= 1
    assert st.characteristic_time_s > 0
    assert st.provenance["scene"]["rock_youngs_modulus_used_pa"] <= 50e9


def test_saved_run_recomputes_same_statistics(small_run, tmp_path):
    from msmill.cli.main import run as cli
    from msmill.dem.mill.run import save_run, stats_from_dir
    from msmill.plots.dem import plot_run

    save_run(small_run, tmp_path)
    assert [f.name for f in plot_run(small_run, tmp_path)] == ["particles_in_mill.png", "stage_impacts.png"]
    again = stats_from_dir(tmp_path).run
    first = small_run.stats.run
    for a, b in zip(first.stages, again.stages, strict=True):
        assert a.kickback == pytest.approx(b.kickback)
        assert a.secondary_lambda == pytest.approx(b.secondary_lambda)
        assert a.n_primary_impacts == b.n_primary_impacts
    assert again.characteristic_time_s == pytest.approx(first.characteristic_time_s)
    assert cli(["dem", "stats", str(tmp_path)]) == 0
    assert (tmp_path / "statistics.json").exists()
    assert cli(["dem", "stats", str(tmp_path / "missing")]) == 2
    # another window inside the record (the stop replay): its own impacts, the saved window's when it is the same
    t0, t1 = small_run.window_s
    same = stats_from_dir(tmp_path, window_s=(t0, t1)).run
    assert [s.n_primary_impacts for s in same.stages] == [s.n_primary_impacts for s in first.stages]
    half = stats_from_dir(tmp_path, window_s=(t0, 0.5 * (t0 + t1))).run
    assert sum(s.n_primary_impacts for s in half.stages) < sum(s.n_primary_impacts for s in first.stages)
    from msmill.errors import MsmillInputError

    with pytest.raises(MsmillInputError, match="window_s"):
        stats_from_dir(tmp_path, window_s=(t0, t1 + 1.0))


def test_feed_speed_sets_the_source_velocity_and_reaches_the_scene(monkeypatch):
    """``RunSettings.feed_speed_m_s`` is the source's downward speed (capacity probes feed faster)."""
    import msmill.dem.mill.run as run_module

    sc = build_scene(MACHINE, OP, size_mm=20.0, mode="slice", feed_speed_m_s=6.0)
    assert np.allclose(sc.sim._sources[0]["vel"], (0.0, 0.0, -6.0))
    seen = {}

    class Stop(Exception):
        pass

    def spy(*args, **kwargs):
        seen.update(kwargs)
        raise Stop

    monkeypatch.setattr(run_module, "build_scene", spy)
    with pytest.raises(Stop):
        run_mill(MACHINE, OP, size_mm=20.0, mode="slice", settings=RunSettings(feed_speed_m_s=7.5))
    assert seen["feed_speed_m_s"] == 7.5
    assert RunSettings().feed_speed_m_s == 2.0  # the default every training run used
