"""numba threading layer of the DEM kernels, and fork safety.

The step kernels open two parallel regions per time step, a few hundred
microseconds of work each. The cost of opening one differs by an order of
magnitude between numba's layers (measured on the 2-core benchmark machine,
``docs/dem.md``, Performance): OpenMP about 3 us (its workers spin briefly
before sleeping), TBB about 27 us, numba's own workqueue about 95 us. With
TBB, the second thread often woke too late to take its share, and the
threaded force pass was no faster than the serial one.

:func:`prefer_openmp` therefore puts OpenMP first in numba's layer priority,
unless the user chose a layer (``NUMBA_THREADING_LAYER`` or
``NUMBA_THREADING_LAYER_PRIORITY``). numba falls back to TBB or workqueue
where OpenMP is not installed.

GNU OpenMP is not fork-safe: a child forked from a process whose OpenMP
threads are running is terminated by numba if it opens a parallel region.
:func:`threads_usable` is False in such a child, and the engine then runs its
serial kernels (same results). Processes started with ``spawn`` or
``forkserver`` (Dask's default) are unaffected.
"""

from __future__ import annotations

import os

#: layer order used when the user has not chosen one
LAYER_PRIORITY = ("omp", "tbb", "workqueue")

_fork_unsafe = False


def prefer_openmp() -> bool:
    """Put OpenMP first in numba's threading-layer priority; False if the user chose a layer.

    Sets both ``NUMBA_THREADING_LAYER_PRIORITY`` (so that numba's
    configuration reloads, and child processes, keep it) and the loaded
    configuration. Has no effect once numba's threads are running.
    """
    if os.environ.get("NUMBA_THREADING_LAYER") or os.environ.get("NUMBA_THREADING_LAYER_PRIORITY"):
        return False
    from numba.core import config

    if config.THREADING_LAYER != "default":
        return False
    os.environ["NUMBA_THREADING_LAYER_PRIORITY"] = " ".join(LAYER_PRIORITY)
    config.THREADING_LAYER_PRIORITY = list(LAYER_PRIORITY)
    return True


def _after_fork_in_child() -> None:
    global _fork_unsafe
    import numba

    try:
        _fork_unsafe = _fork_unsafe or numba.threading_layer() == "omp"
    except ValueError:  # no threads launched before the fork: the child may launch its own
        pass


os.register_at_fork(after_in_child=_after_fork_in_child)


def threads_usable() -> bool:
    """False in a process forked from one whose GNU OpenMP threads were running."""
    return not _fork_unsafe
