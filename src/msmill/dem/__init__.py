"""DEM engine of msmill: spheres, Hertz-Mindlin contacts (paper Section 2), analytic geometry.

Importing this package loads numba; ``import msmill`` does not.

>>> from msmill.dem import Simulation, Rotation
"""

from msmill.dem.geometry import Rotation
from msmill.dem.simulation import DemRuntimeError, DemRuntimeWarning, Simulation

__all__ = ["DemRuntimeError", "DemRuntimeWarning", "Rotation", "Simulation"]
