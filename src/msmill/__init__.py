"""msmill: semi-analytical model and DEM training pipeline for multi-shaft impact mills.

The top-level namespace is light: heavy sub-packages (``msmill.dem`` with its
numba kernels, ``msmill.surrogate``) are imported only when used.
"""

from msmill._version import __version__

__all__ = ["__version__"]
