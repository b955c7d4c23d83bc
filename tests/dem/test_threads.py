"""numba threading layer of the DEM kernels and fork safety (msmill.dem.threads).

Each case runs in a fresh interpreter, because the layer is fixed when
numba first launches its threads.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import pytest

SCENE = """
import numpy as np
from msmill.dem import Simulation

def gas_sim(parallel):
    rng = np.random.default_rng(3)
    side = 0.2
    g = (np.arange(8) + 0.5) * side / 8
    pos = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    sim = Simulation((0, 0, 0), (side,) * 3, periodic=(True,) * 3, gravity_m_s2=(0, 0, 0),
                     parallel=parallel, parallel_min_particles=1)
    sim.add_material("rock", youngs_modulus_pa=2e10, poisson_ratio=0.25, density_kg_m3=2700)
    sim.set_interaction("rock", "rock", restitution=0.5, friction=0.4)
    sim.add_particles(pos, 0.006, rng.normal(0, 10, pos.shape), material="rock")
    sim.run(2e-4, dt_s=1e-6, progress=False)
    return sim

def gas(parallel):
    return gas_sim(parallel).particle_arrays()["pos"]
"""


def _run(code: str, env_extra: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if not k.startswith("NUMBA_THREADING_LAYER")}
    env.update(env_extra or {})
    return subprocess.run([sys.executable, "-c", SCENE + textwrap.dedent(code)], env=env,
                          capture_output=True, text=True, timeout=600)


def _omp_available() -> bool:
    try:
        import numba.np.ufunc.omppool  # noqa: F401
    except ImportError:
        return False
    return True


needs_omp = pytest.mark.skipif(not _omp_available(), reason="numba's OpenMP layer is not installed")


@needs_omp
def test_openmp_is_preferred_unless_the_user_chooses():
    code = """
    import numba
    gas(True)
    print(numba.threading_layer())
    """
    out = _run(code)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split()[-1] == "omp"
    out = _run(code, {"NUMBA_THREADING_LAYER": "workqueue"})
    assert out.returncode == 0, out.stderr
    assert out.stdout.split()[-1] == "workqueue"


@needs_omp
def test_a_child_forked_from_an_openmp_process_runs_serial_kernels():
    # numba terminates a forked child that opens an OpenMP parallel region; the engine
    # must fall back to its serial kernels there, with the same result and a warning
    code = """
    import os, warnings
    import numpy as np
    sim = gas_sim(True)
    ref = sim.particle_arrays()["pos"].copy()
    pid = os.fork()
    if pid == 0:
        with warnings.catch_warnings(record=True) as w:
            warnings.simplefilter("always")
            got = gas(True)  # a new simulation in the child
            sim.add_particles([(0.1, 0.1, 0.1)], 0.006, material="rock")  # forces a rebuild
            sim.run(1e-4, dt_s=1e-6, progress=False)  # and the parent's, continued
        ok = np.array_equal(got, ref) and any("forked" in str(x.message) for x in w)
        os._exit(0 if ok else 3)
    _, status = os.waitpid(pid, 0)
    print("child", os.waitstatus_to_exitcode(status))
    """
    out = _run(code, {"NUMBA_THREADING_LAYER": "omp"})
    assert out.returncode == 0, out.stderr
    assert out.stdout.split()[-1] == "0", out.stdout + out.stderr
