"""The engine's trajectories are bitwise those of the stored reference runs.

``tests/dem/data/trajectory_reference.json`` holds SHA-256 digests of the final
state and the events of two short runs (a dense frictional gas, threaded and
serial, and the 30 mm mill slice), written by
``scripts/dem_reference_trajectory.py`` from the engine before the force
pass's data were re-laid out (issue 12 item 3). A pure re-layout must leave
every bit unchanged; a change of the physics or of the summation order must
regenerate the file and say so in its commit.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

REF = json.loads((Path(__file__).parent / "data" / "trajectory_reference.json").read_text())


@pytest.fixture(scope="module")
def ref_script():
    """The reference script, on the toolchain and CPU the digests were written with (else skip: numba's
    generated code, and so the last bits of a trajectory, depend on its version, numpy's and the CPU)."""
    import numba
    import numpy as np

    from msmill.dem import reference as mod

    here = {"numba": numba.__version__, "numpy": np.__version__, "host_cpu": mod.host_cpu(),
            "host_cpu_features": mod.host_cpu_features()}
    other = {k: (REF.get(k), v) for k, v in here.items() if REF.get(k) != v}
    if other:
        pytest.skip(f"bitwise reference written with another toolchain or CPU {other}: regenerate it with "
                    "python scripts/dem_reference_trajectory.py")
    return mod


@pytest.mark.parametrize("parallel", [True, False])
def test_dense_gas_is_bitwise_the_reference(ref_script, parallel):
    st = ref_script.run_gas(parallel)
    name = "gas_par" if parallel else "gas_ser"
    assert st["ev_int"].shape[0] == REF["events"][name]
    for k, v in st.items():
        assert ref_script.digest(v) == REF["sha256"][f"{name}/{k}"], k


def test_mill_slice_is_bitwise_the_reference(ref_script):
    import warnings

    warnings.simplefilter("ignore")
    st = ref_script.run_mill()
    assert st["ev_int"].shape[0] == REF["events"]["mill"] > 0
    for k, v in st.items():
        assert ref_script.digest(v) == REF["sha256"][f"mill/{k}"], k
