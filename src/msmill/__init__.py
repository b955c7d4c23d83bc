"""msmill: semi-analytical model and DEM training pipeline for multi-shaft impact mills.

The top-level namespace is light: heavy sub-packages (``msmill.dem`` with its
numba kernels, ``msmill.surrogate``) are imported only when used.
"""

from msmill._version import __version__

__all__ = ["Mill", "__version__", "simulate"]

_LAZY = {"Mill": "msmill.model", "simulate": "msmill.model"}


def __getattr__(name: str):
    """Lazy exports: ``msmill.simulate`` and ``msmill.Mill`` import the model on first use."""
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'msmill' has no attribute {name!r}")
