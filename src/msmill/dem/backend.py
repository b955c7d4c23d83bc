"""Step backends of the DEM engine: the numba kernels (default) or NVIDIA Warp on CPU or CUDA.

``Simulation(backend=...)`` and ``RunSettings.backend`` (``msmill dem run --backend``) take one of
:data:`BACKENDS`. ``"cpu"`` is the numba engine (:func:`msmill.dem.kernels.advance`);
``"warp-cpu"`` and ``"cuda"`` run the same step with the Warp kernels of
:mod:`msmill.dem.warp_kernels` on Warp's CPU device or the first CUDA GPU. Warp is imported
only here, and only when a Warp backend is asked for: the package installs and runs without it.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from functools import lru_cache
from typing import Any

from msmill.errors import MsmillInputError

#: backend names: numba engine (default), Warp kernels on Warp's CPU device, Warp kernels on CUDA
BACKENDS = ("cpu", "warp-cpu", "cuda")
_WARP_DEVICE = {"warp-cpu": "cpu", "cuda": "cuda:0"}
_ALLOWED = "'cpu' (numba, the default), 'warp-cpu' or 'cuda' (NVIDIA Warp)"


@lru_cache(maxsize=1)
def warp_status() -> tuple[bool, int]:
    """``(warp importable, number of CUDA devices)``; Warp's start-up messages are silenced."""
    try:
        import warp as wp
    except ImportError:
        return False, 0
    wp.config.log_level = wp.LOG_WARNING
    fd = os.dup(2)  # the native library prints a missing CUDA driver on stderr
    nul = os.open(os.devnull, os.O_WRONLY)
    os.dup2(nul, 2)
    try:
        wp.init()
        n = int(wp.get_cuda_device_count())
    finally:
        os.dup2(fd, 2)
        os.close(fd)
        os.close(nul)
    return True, n


def check_backend(value: Any, field: str = "backend", *, here: bool = True) -> str:
    """Return ``value`` if it names a backend (usable here), else raise a one-line :class:`MsmillInputError`.

    Parameters
    ----------
    value : Any
        The requested backend.
    field : str
        Field name for the error (``--backend`` on the command line).
    here : bool
        Also require it to run on this machine (Warp installed; for ``"cuda"`` a GPU). A campaign
        checks the name only: its runs may execute on other machines, where the engine checks again.
    """
    if not isinstance(value, str) or value not in BACKENDS:
        raise MsmillInputError(field, value, _ALLOWED)
    if value == "cpu" or not here:
        return value
    has_warp, n_cuda = warp_status()
    if not has_warp:
        raise MsmillInputError(field, value, "'cpu' here (NVIDIA Warp is not installed: "
                                             "pip install 'msmill[gpu]')")
    if value == "cuda" and n_cuda == 0:
        raise MsmillInputError(field, value, "'cpu' or 'warp-cpu' here (no CUDA device found)")
    return value


def stepper(backend: str) -> Callable[..., tuple[int, int]]:
    """The step loop of ``backend``: a callable with the arguments of :func:`msmill.dem.kernels.advance`."""
    if backend == "cpu":
        from msmill.dem import kernels

        return kernels.advance
    check_backend(backend)
    from msmill.dem.warp_kernels import WarpStepper

    return WarpStepper(_WARP_DEVICE[backend]).advance


def device_engine(backend: str) -> Any:
    """A :class:`msmill.dem.warp_rebuild.DeviceEngine` on ``backend``'s Warp device (``"warp-cpu"``, ``"cuda"``)."""
    check_backend(backend)
    from msmill.dem.warp_rebuild import DeviceEngine

    return DeviceEngine(_WARP_DEVICE[backend])
