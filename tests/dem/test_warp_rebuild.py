"""The neighbour-list rebuild on the Warp device (``msmill.dem.warp_rebuild``) against the numba rebuild.

The device rebuild keeps the numba rebuild's list order (the step sums forces in list order), so
its lists are compared exactly: from one state, the two rebuilds give the same half list, shifts,
reverse list, geometry candidates, work flags and, after the sort, the same particle order with
the history slots carried with their particles. Then the data path: a run that keeps its state on
the device (``Simulation._on_device``, what ``cuda`` does; here on Warp's CPU device, copies in
and out at the host's reads) is bitwise the run with numba rebuilds and the same step kernels,
through sinks, sources, event-buffer flushes, callbacks and a checkpoint.
"""

from __future__ import annotations

import pickle
import warnings

import numpy as np
import pandas as pd
import pytest

pytest.importorskip("warp")

from msmill.dem import Simulation

LIST_ITEMS = {"_nb": 5, "_gc": 2, "_pair": 4}


def _gas(spacing: float = 0.0105, **kw):
    import test_engine as te  # tests/dem

    warnings.simplefilter("ignore")
    return te.gas(5, 0.004, spacing, 3.0, e=0.5, mu=0.4, **kw)


def _slice():
    from msmill.dem.mill.scene import build_scene
    from msmill.dem.mill.warmstart import place_table_start
    from msmill.machine import Machine, OperatingPoint

    warnings.simplefilter("ignore")
    sc = build_scene(Machine.default(), OperatingPoint(feed_tph=30.0, speed_rpm=1500.0, gate_deg=40.0),
                     size_mm=10.0)
    place_table_start(sc, seed=1)
    return sc


def _both_rebuilds(sim: Simulation, sort: bool) -> tuple[Simulation, Simulation]:
    """The numba rebuild of ``sim`` and the device rebuild of a copy, from the same state."""
    dev = pickle.loads(pickle.dumps(sim))
    dev._backend, dev._on_device = "warp-cpu", True
    for s in (sim, dev):
        s._n_rebuilds = 0 if sort else 1
        s._rebuild()
    dev._host_view(lists=True)
    return sim, dev


def _assert_same_rebuild(a: Simulation, b: Simulation) -> None:
    for attr, k in LIST_ITEMS.items():
        for x, y in zip(getattr(a, attr)[:k], getattr(b, attr)[:k], strict=True):
            np.testing.assert_array_equal(y, x, err_msg=attr)
    np.testing.assert_array_equal(b._kind, a._kind)
    np.testing.assert_array_equal(b._work[0], a._work[0])
    pa, pb = a._host_view(), b._host_view()
    for k in ("pid", "pos", "vel", "omg", "h_n", "g_n"):
        np.testing.assert_array_equal(pb[k], pa[k], err_msg=k)
    for pre, key in (("h", "h_pid"), ("g", "g_gid")):  # used history slots, keys and values
        used = np.arange(pa[key].shape[1])[None, :] < pa[f"{pre}_n"][:, None]
        for f in (key, f"{pre}_st", f"{pre}_ev", f"{pre}_pk", f"{pre}_ds"):
            np.testing.assert_array_equal(pb[f][used], pa[f][used], err_msg=f)


@pytest.mark.parametrize("sort", [True, False])
def test_device_rebuild_of_a_frictional_periodic_gas_is_the_numba_rebuild(sort):
    sim = _gas(0.0082)  # dense: many contacts with history
    sim.run(4e-4, dt_s=1e-6, progress=False)
    p = sim._p
    p["pos"][::7, 0] += sim._box_len[0]  # some particles outside the periodic box: wrapped
    p["pos"][1::7, 2] -= sim._box_len[2]
    a, b = _both_rebuilds(sim, sort)
    assert a._nb[1].size > 100 and np.abs(a._nb[2]).sum() > 0 and (a._p["h_n"] > 0).sum() > 10
    _assert_same_rebuild(a, b)


def test_device_rebuild_of_the_mill_slice_is_the_numba_rebuild():
    """Rotating plates, periodic images of the plates, geometry history keys moved by the wrap."""
    sc = _slice()
    sim = sc.sim
    sim.run(0.01, max_relative_speed_m_s=sc.max_impact_speed_m_s, progress=False)
    p = sim._p
    per = int(np.nonzero(sim._periodic)[0][0])
    near = np.nonzero((np.diff(sim._gc[0]) > 0) | (p["g_n"] > 0))[0]
    assert near.size > 5
    p["pos"][near[::2], per] += sim._box_len[per]  # across the periodic boundary, near plates
    p["g_n"][near[::2]] = 1  # a geometry history slot each, with an image key the wrap moves
    g = int(np.nonzero(sim._gspan[:, per] == 0)[0][0])  # a primitive met through its images
    p["g_gid"][near[::2], 0] = 4096 * g
    a, b = _both_rebuilds(sim, sort=True)
    assert a._gc[1].size > 100 and (a._gc[1] % 4096 != 0).any()  # some image keys
    _assert_same_rebuild(a, b)


def _run_gas(on_device: bool) -> tuple:
    Simulation.__init__.__kwdefaults__["backend"] = "warp-cpu"
    try:
        sim = _gas(event_buffer_rows=8)  # event buffers flushed every few contacts
    finally:
        Simulation.__init__.__kwdefaults__["backend"] = "cpu"
    sim._on_device = on_device
    sim.add_sink((0.0, 0.0, 0.0), (0.01, 0.01, 0.01), tag="corner")
    sim.add_source((0.02, 0.02, 0.02), (0.05, 0.05, 0.05), 5.0, radii_m=0.002, material="rock",
                   insert_interval_s=2e-4, velocity_m_s=(1.0, 0.0, 0.0))
    seen = []
    sim.run(1e-3, dt_s=1e-6, progress=False, callback=lambda s: seen.append(s.kinetic_energy_j()),
            callback_every=100)
    sim = pickle.loads(pickle.dumps(sim))  # a checkpoint mid-run
    sim.run(1e-3, dt_s=1e-6, progress=False)
    return sim, seen


def test_a_run_kept_on_the_device_is_bitwise_the_run_with_numba_rebuilds():
    (a, ka), (b, kb) = _run_gas(False), _run_gas(True)
    assert b._dev is not None and a._dev is None
    assert a.stats["steps"] == b.stats["steps"] == 2000 and a.stats["rebuilds"] == b.stats["rebuilds"]
    pa, pb = a.particle_arrays(), b.particle_arrays()
    assert pa["pid"].max() > 124  # the source inserted
    for k in pa:
        np.testing.assert_array_equal(pb[k], pa[k], err_msg=k)
    assert ka == kb and len(ka) == 10
    ea, eb = a.events(), b.events()
    assert len(ea) > 50
    pd.testing.assert_frame_equal(eb, ea, check_exact=True)
    pd.testing.assert_frame_equal(b.removed(), a.removed(), check_exact=True)
    assert len(a.removed()) > 0
    assert b.contact_energy_j() == a.contact_energy_j()
