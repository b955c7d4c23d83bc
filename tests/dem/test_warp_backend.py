"""The Warp backend of the DEM (``Simulation(backend="warp-cpu")``) against the numba engine's checks.

The Warp kernels run here on Warp's CPU device, compiled by Warp's LLVM from the source the GPU
compiles (``msmill.dem.warp_kernels``). What agreement is expected (``docs/dem.md``, "GPU backend"):

* the contact law: the two formulas (numba ``kernels.contact_law``, Warp ``contact_law``) to 1e-12
  relative on random contacts;
* single contacts (Chung & Ooi, the rotating paddle): the published / closed-form checks the numba
  engine passes, and the numba engine's own outcome to 1e-10 relative;
* many-body runs (periodic gas, mill slice) are chaotic, so only what is conserved (momentum to
  round-off, energy between collisions) and statistics within their sampling errors are tested,
  not trajectories. (On Warp's CPU device the step was observed to be bitwise the serial numba
  step: same operations in the same order, no FMA contraction. That is not promised and not
  tested: a GPU's ``sin``/``cos`` differ in the last bit, and chaos does the rest.)

The first test of a fresh machine pays Warp's kernel compile (3 s cold on the 2-core VM; then
cached in ``~/.cache/warp``). The selection and error tests at the top run without Warp.
"""

from __future__ import annotations

import math
import subprocess
import sys
import warnings

import numpy as np
import pytest

from msmill.dem import Rotation, Simulation
from msmill.dem.backend import BACKENDS, check_backend, warp_status
from msmill.errors import MsmillInputError

CUDA_HERE = warp_status()[1] > 0


# --------------------------------------------------------------------------- selection, no Warp needed
def test_default_backend_is_numba_and_warp_is_not_imported():
    code = ("import sys; from msmill.dem import Simulation; s = Simulation(); "
            "assert s.backend == 'cpu'; assert 'warp' not in sys.modules")
    subprocess.run([sys.executable, "-c", code], check=True)


@pytest.mark.parametrize("bad", ["gpu", "CUDA", "", 3, None])
def test_unknown_backend_is_a_one_line_error(bad):
    with pytest.raises(MsmillInputError) as exc:
        Simulation(backend=bad)
    assert exc.value.field == "backend"
    msg = str(exc.value)
    assert "\n" not in msg and "'cpu'" in msg and "'cuda'" in msg and "'warp-cpu'" in msg


@pytest.mark.skipif(CUDA_HERE, reason="this machine has a CUDA device")
def test_cuda_without_a_gpu_is_a_one_line_error(capsys):
    with pytest.raises(MsmillInputError) as exc:
        Simulation(backend="cuda")
    assert exc.value.field == "backend" and exc.value.value == "cuda"
    assert "\n" not in str(exc.value)
    assert "no CUDA device" in str(exc.value) or "not installed" in str(exc.value)
    assert check_backend("cuda", here=False) == "cuda"  # a campaign may run it elsewhere
    from msmill.cli.main import run

    assert run(["dem", "run", "default", "--size-mm", "10", "--out", "/nonexistent/x",
                "--backend", "cuda"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: --backend: got 'cuda'")


def test_run_settings_and_campaign_settings_take_the_backend():
    from msmill.dem.mill.checks import check_run_inputs
    from msmill.dem.mill.run import RunSettings
    from msmill.machine import Machine
    from msmill.pipeline.campaign import run_settings_dict

    assert RunSettings().backend == "cpu"
    check_run_inputs(Machine.default(), RunSettings(backend="cuda"), 10.0)  # the name only
    with pytest.raises(MsmillInputError) as exc:
        check_run_inputs(Machine.default(), RunSettings(backend="tpu"), 10.0)
    assert exc.value.field == "backend"
    assert run_settings_dict({"backend": "cuda"}, defaults={}) == {"backend": "cuda"}
    with pytest.raises(MsmillInputError):
        run_settings_dict({"backend": "tpu"}, defaults={})
    assert BACKENDS[0] == "cpu"


# --------------------------------------------------------------------------- Warp on its CPU device
@pytest.fixture
def warp_default(monkeypatch):
    """Every ``Simulation()`` of the test runs the Warp kernels on Warp's CPU device."""
    pytest.importorskip("warp")
    monkeypatch.setitem(Simulation.__init__.__kwdefaults__, "backend", "warp-cpu")
    assert Simulation().backend == "warp-cpu"
    warnings.simplefilter("ignore")


def _contact_inputs(n: int, seed: int = 5) -> np.ndarray:
    """Random contacts (columns as ``contact_law``'s arguments): sticking, sliding, frictionless."""
    rng = np.random.default_rng(seed)
    nrm = rng.normal(size=(n, 3))
    nrm /= np.linalg.norm(nrm, axis=1)[:, None]
    x = np.empty((n, 18))
    x[:, 0] = rng.uniform(1e-7, 1e-4, n)  # overlap (m)
    x[:, 1:4] = nrm
    x[:, 4:7] = rng.normal(0, 5, (n, 3))  # relative velocity (m/s), approaching or not
    x[:, 7] = rng.uniform(1e-3, 5e-2, n)  # R*
    x[:, 8] = rng.uniform(1e-4, 1.0, n)  # m*
    x[:, 9] = 4 / 3 * rng.uniform(1e9, 2e11, n)
    x[:, 10] = rng.uniform(0, 2, n)  # eta_H
    x[:, 11] = rng.uniform(0, 2, n)  # eta_tau
    x[:, 12] = np.where(rng.random(n) < 0.1, 0.0, rng.uniform(0.05, 0.8, n))  # mu
    x[:, 13] = rng.uniform(0.5, 1.5, n)
    x[:, 14] = rng.uniform(1e-7, 1e-5, n)  # dt
    x[:, 15:18] = rng.normal(0, 1e-5, (n, 3)) * rng.choice([0.0, 1.0, 50.0], (n, 1))  # history
    return x


def _warp_contact_law(x: np.ndarray) -> np.ndarray:
    import warp as wp

    from msmill.dem import warp_kernels as W

    @wp.kernel
    def law(x: wp.array2d(dtype=wp.float64), out: wp.array2d(dtype=wp.float64)):
        i = wp.tid()
        r = W.contact_law(x[i, 0], x[i, 1], x[i, 2], x[i, 3], x[i, 4], x[i, 5], x[i, 6], x[i, 7],
                          x[i, 8], x[i, 9], x[i, 10], x[i, 11], x[i, 12], x[i, 13], x[i, 14],
                          x[i, 15], x[i, 16], x[i, 17])
        for k in range(7):
            out[i, k] = r[k]

    xa = wp.array(x, dtype=wp.float64, device="cpu")
    out = wp.zeros((x.shape[0], 7), dtype=wp.float64, device="cpu")
    wp.launch(law, dim=x.shape[0], inputs=[xa, out], device="cpu")
    return out.numpy()


def test_contact_law_is_the_same_formula_in_both_backends():
    pytest.importorskip("warp")
    from msmill.dem import kernels as K

    x = _contact_inputs(2000)
    ref = np.array([K.contact_law(*row) for row in x])
    got = _warp_contact_law(x)
    scale = np.abs(ref).max(axis=0)  # per output: force, history, F_n
    assert np.all(np.abs(got - ref) <= 1e-12 * scale)
    assert (ref[:, 6] > 0).sum() > 500 and (np.abs(ref[:, 3]) > 0).sum() > 500  # contacts pushed, history


def test_chung_ooi_cases_on_warp(warp_default):
    import test_chung_ooi as co  # tests/dem

    for name, e, nu, rho, table in [("glass", 4.8e10, 0.20, 2800, (274e-6, 10.7e3, 39.3e-6))]:
        co.test_1_elastic_sphere_sphere(name, e, nu, rho, table)
    co.test_2_elastic_sphere_rigid_plane("al_alloy", 7.0e10, 0.30, 2699, (49.7e-6, 11.37e3, 713e-6))
    co.test_3_restitution_output_equals_input(co.AL_OXIDE)
    co.test_4_oblique_impact_gross_sliding_and_shape()
    co.test_6_oblique_impact_with_spin()
    co.test_7_symmetric_spins_give_symmetric_outcome()


def _oblique_impacts(backend: str) -> tuple[np.ndarray, np.ndarray]:
    import test_chung_ooi as co

    mu, e, v, r = 0.4, 0.5, 3.9, 2.5e-3
    cases = [{"e": e, "mu": mu, "v": (v * math.sin(math.radians(a)), 0.3, -v * math.cos(math.radians(a))),
              "w": (0.0, 100.0 - 40 * k, 20.0)} for k, a in enumerate((5, 20, 45, 70))]
    Simulation.__init__.__kwdefaults__["backend"] = backend
    try:
        vel, omg, _ = co._impacts_on_plane(co.CAST_IRON, r, cases, steps=200)
    finally:
        Simulation.__init__.__kwdefaults__["backend"] = "cpu"
    return vel, omg


def test_single_contacts_agree_with_the_numba_engine_to_1e_10():
    pytest.importorskip("warp")
    v0, w0 = _oblique_impacts("cpu")
    v1, w1 = _oblique_impacts("warp-cpu")
    np.testing.assert_allclose(v1, v0, rtol=1e-10, atol=1e-10 * np.abs(v0).max())
    np.testing.assert_allclose(w1, w0, rtol=1e-10, atol=1e-10 * np.abs(w0).max())


def test_periodic_gas_conserves_momentum_and_energy_on_warp(warp_default):
    import test_engine as te  # tests/dem

    te.test_frictionless_elastic_gas_conserves_energy()
    te.test_momentum_conserved_in_periodic_box_with_friction_and_damping()


def test_rotating_paddle_on_warp_matches_the_closed_form_and_the_numba_engine(warp_default):
    import test_engine as te

    te.test_rotating_paddle_hits_resting_sphere_closed_form()
    runs = {}
    for backend in ("cpu", "warp-cpu"):
        sim = Simulation((-0.5, -0.5, -0.5), (0.5, 0.5, 0.5), gravity_m_s2=(0, 0, -9.81),
                         backend=backend)
        sim.add_material("rock", youngs_modulus_pa=1e9, poisson_ratio=0.25, density_kg_m3=2700)
        sim.add_material("steel", youngs_modulus_pa=2e11, poisson_ratio=0.3, density_kg_m3=7800)
        sim.set_interaction("rock", "steel", restitution=0.2, friction=0.3)
        # the paddle of the closed-form test; the rock spins and has weight
        sim.add_box((0.175, 0, 0), (0.125, 0.004, 0.05), material="steel", tag="flinger",
                    group=3, rotation=Rotation((0, 0, 0), (0, 0, 1), 50.0))
        sim.add_particles([[0.1, 0.17, 0.01]], 0.01, [[0.0, 0.0, -0.5]], material="rock",
                          angular_velocities_rad_s=[[5.0, -3.0, 40.0]])
        sim.run(0.03, dt_s=2e-6, progress=False, max_relative_speed_m_s=12)
        runs[backend] = (sim.particle_arrays(), sim.events())
    (a, ea), (b, eb) = runs["cpu"], runs["warp-cpu"]
    assert len(ea) == len(eb) >= 1
    for k in ("pos", "vel", "omg"):
        np.testing.assert_allclose(b[k], a[k], rtol=1e-10, atol=1e-10 * np.abs(a[k]).max())
    cols = ["time_s", "vn_m_s", "vt_m_s", "end_time_s", "peak_overlap_m", "dissipated_j"]
    np.testing.assert_allclose(eb[cols].to_numpy(float), ea[cols].to_numpy(float), rtol=1e-10)


# --------------------------------------------------------------------------- the mill slice
def _slice_statistics(backend: str) -> dict[str, tuple[float, float]]:
    """Statistics of 0.1 s of the 10 mm slice from a table start: ``{name: (value, standard error)}``.

    Impacts are events with ``vn > 0.5`` m/s (as ``dem.mill.stats``): counts per flinger group
    (Poisson errors) and mean ``vn`` per group (errors of independent impacts); rock-rock
    contacts; rocks in the slice at the end.
    """
    from msmill.dem.mill.scene import build_scene
    from msmill.dem.mill.warmstart import place_table_start
    from msmill.machine import Machine, OperatingPoint

    warnings.simplefilter("ignore")
    sc = build_scene(Machine.default(), OperatingPoint(feed_tph=30.0, speed_rpm=1500.0, gate_deg=40.0),
                     size_mm=10.0, backend=backend)
    place_table_start(sc, seed=1)
    sc.sim.run(0.1, max_relative_speed_m_s=sc.max_impact_speed_m_s, progress=False)
    ev = sc.sim.events()
    hits = ev[(ev.vn_m_s > 0.5)]
    fl = hits[hits.partner_tag == "flinger"]
    out = {}
    for g, grp in fl.groupby("partner_group"):
        out[f"flinger{g}_n"] = (len(grp), math.sqrt(len(grp)))
        out[f"flinger{g}_vn"] = (grp.vn_m_s.mean(), grp.vn_m_s.std() / math.sqrt(len(grp)))
    rr = hits[hits.partner_kind == 0]
    out["rock_rock_n"] = (len(rr), math.sqrt(len(rr)))
    out["rocks"] = (sc.sim.n_particles, math.sqrt(sc.sim.n_particles))
    return out


def test_mill_slice_statistics_agree_with_the_numba_engine(warp_default):
    from scipy.stats import norm

    a = _slice_statistics("cpu")
    b = _slice_statistics("warp-cpu")
    assert set(a) == set(b) and len(a) >= 6
    assert a["flinger0_n"][0] > 200  # enough impacts to test anything
    # family-wise: Bonferroni over the statistics at 1e-3 in all
    z_crit = norm.ppf(1 - 0.5e-3 / len(a))
    for k in a:
        z = (b[k][0] - a[k][0]) / math.hypot(a[k][1], b[k][1])
        assert abs(z) < z_crit, (k, a[k], b[k], z)


def test_the_gpu_way_of_stepping_agrees_on_the_cpu_device(warp_default):
    """Copies in and out at each call and a stop flag read every 16 steps (what ``cuda`` does),
    here on Warp's CPU device: the same run as the shared-memory stepper, to 1e-10."""
    import test_engine as te

    from msmill.dem.warp_kernels import WarpStepper

    runs = []
    for gpu_way in (False, True):
        sim = te.gas(5, 0.004, 0.0105, 3.0, e=0.5, mu=0.4)
        sim.add_sink((0.0, 0.0, 0.0), (0.01, 0.01, 0.01), tag="corner")  # flags: a stop mid-batch
        sim._on_device = False  # numba rebuilds, the step through _step_fn
        if gpu_way:
            sim._step_fn = WarpStepper("cpu", share=False, steps_per_check=16).advance
        sim.run(2e-3, dt_s=1e-6, progress=False)
        runs.append((sim.particle_arrays(), sim.events(), sim.removed(), sim.stats["steps"]))
    (a, ea, ra, na), (b, eb, rb, nb) = runs
    assert na == nb == 2000 and len(ea) == len(eb) > 20 and len(ra) == len(rb) > 0
    for k in ("pid", "pos", "vel", "omg"):
        np.testing.assert_allclose(b[k], a[k], rtol=1e-10, atol=1e-10 * np.abs(a[k]).max())
    np.testing.assert_allclose(eb[["time_s", "vn_m_s", "dissipated_j"]].to_numpy(float),
                               ea[["time_s", "vn_m_s", "dissipated_j"]].to_numpy(float), rtol=1e-10)
    np.testing.assert_array_equal(rb.time_s, ra.time_s)


def test_a_pickled_warp_simulation_continues_as_the_uninterrupted_one(warp_default):
    """Checkpoints pickle the Simulation: the Warp stepper is left out and made again on load."""
    import pickle

    import test_engine as te

    whole = te.gas(4, 0.004, 0.0105, 3.0, e=0.5, mu=0.4)
    whole.run(1e-3, dt_s=1e-6, progress=False)
    part = te.gas(4, 0.004, 0.0105, 3.0, e=0.5, mu=0.4)
    part.run(4e-4, dt_s=1e-6, progress=False)
    part = pickle.loads(pickle.dumps(part))
    assert part.backend == "warp-cpu" and part._step_fn is None
    part.run(6e-4, dt_s=1e-6, progress=False)
    a, b = whole.particle_arrays(), part.particle_arrays()
    for k in ("pos", "vel", "omg"):
        np.testing.assert_allclose(b[k], a[k], rtol=1e-10, atol=1e-10 * np.abs(a[k]).max())
    assert len(whole.events()) == len(part.events()) > 5
