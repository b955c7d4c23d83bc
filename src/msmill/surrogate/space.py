"""The 4-D design space of the DEM runs (paper Table 2) and its input scaling.

A design point is ``(size_mm, feed_tph, speed_rpm, gate_deg)``: rock diameter,
feed rate, upper-stage shaft speed (the bottom stage runs at a fixed multiple
of it in the training recipe) and outlet gate angle. The GP sees every input
scaled to ``[0, 1]`` by the design-space bounds, the rock size in ``ln``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from msmill.errors import MsmillInputError
from msmill.stageparams import DESIGN_INPUTS

#: Names of the four inputs, in column order.
INPUTS = DESIGN_INPUTS


@dataclass(frozen=True)
class DesignSpace:
    """Bounds of the design space (paper Table 2 by default).

    Attributes
    ----------
    size_mm, feed_tph, speed_rpm, gate_deg : tuple of float
        ``(low, high)`` of rock size (mm), feed rate (t/h), upper-stage speed
        (rpm) and gate angle (deg).
    """

    size_mm: tuple[float, float] = (2.0, 30.0)
    feed_tph: tuple[float, float] = (10.0, 60.0)
    speed_rpm: tuple[float, float] = (1200.0, 1900.0)
    gate_deg: tuple[float, float] = (0.0, 80.0)

    def __post_init__(self) -> None:
        for name in INPUTS:
            lo, hi = getattr(self, name)
            if not hi > lo or (name == "size_mm" and lo <= 0):
                raise MsmillInputError(f"design_space.{name}", (lo, hi), "low < high (size > 0)")

    @property
    def bounds(self) -> np.ndarray:
        """Bounds as an array of shape (4, 2) in physical units."""
        return np.array([getattr(self, n) for n in INPUTS], dtype=float)

    def _lo_span(self) -> tuple[np.ndarray, np.ndarray]:
        b = self.bounds.copy()
        b[0] = np.log(b[0])
        return b[:, 0], b[:, 1] - b[:, 0]

    def to_unit(self, x: np.ndarray) -> np.ndarray:
        """Physical design points (..., 4) -> unit-cube coordinates (size in ln)."""
        x = np.array(x, dtype=float, copy=True)
        if x.shape[-1] != 4:
            raise MsmillInputError("design points", f"shape {x.shape}", "(..., 4) columns " + ", ".join(INPUTS))
        if np.any(x[..., 0] <= 0):
            raise MsmillInputError("size_mm", float(x[..., 0].min()), "> 0")
        x[..., 0] = np.log(x[..., 0])
        lo, span = self._lo_span()
        return (x - lo) / span

    def from_unit(self, u: np.ndarray) -> np.ndarray:
        """Unit-cube coordinates (..., 4) -> physical design points."""
        lo, span = self._lo_span()
        x = np.asarray(u, dtype=float) * span + lo
        x[..., 0] = np.exp(x[..., 0])
        return x

    def to_dict(self) -> dict[str, list[float]]:
        """Plain dict for JSON."""
        return {n: [float(v) for v in getattr(self, n)] for n in INPUTS}

    @classmethod
    def from_dict(cls, d: dict) -> DesignSpace:
        """Inverse of :meth:`to_dict`."""
        return cls(**{n: tuple(float(v) for v in d[n]) for n in INPUTS})
