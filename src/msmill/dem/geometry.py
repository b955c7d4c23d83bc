"""Analytic geometry primitives packed into flat arrays for the kernels.

Kinds and the layout of one row of ``gref`` (reference pose, time 0)::

    PLANE (0): point(0:3), unit normal(3:6) pointing to the particle side
    BOX   (1): centre(0:3), local axes as rows ex(3:6) ey(6:9) ez(9:12),
               half extents(12:15); a half extent of 0 makes a finite plate
    CYL   (2): p0(0:3), unit axis u(3:6), length(6), radius(7), inside flag(8)

``grot`` rows hold the rotation: axis point(0:3), unit axis(3:6), omega (rad/s,
right-handed about the axis) (6), rotating flag (7). A rotating primitive at
time ``t`` is its reference pose turned by ``omega t`` about the axis.
``gbound`` rows hold the rotation-invariant extent used by the candidate
search: for a rotating primitive ``(r_min, r_max, a_min, a_max)`` in
cylindrical coordinates about its rotation axis; for a static one an
axis-aligned box ``(lo(0:3), hi(3:6))`` (planes: infinite).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from msmill.errors import MsmillInputError

PLANE, BOX, CYL = 0, 1, 2
KIND_NAMES = {PLANE: "plane", BOX: "box", CYL: "cylinder"}
NG = 16


def vec3(name: str, value, *, unit: bool = False) -> np.ndarray:
    """Validate a finite 3-vector (optionally normalised)."""
    try:
        v = np.asarray(value, dtype=float).reshape(3)
    except (TypeError, ValueError):
        raise MsmillInputError(name, value, "a sequence of 3 finite numbers") from None
    if not np.all(np.isfinite(v)):
        raise MsmillInputError(name, value, "a sequence of 3 finite numbers")
    if unit:
        nrm = float(np.linalg.norm(v))
        if nrm == 0.0:
            raise MsmillInputError(name, value, "a non-zero 3-vector")
        v = v / nrm
    return v


@dataclass(frozen=True)
class Rotation:
    """Constant-speed rotation of a primitive about a fixed axis.

    Parameters
    ----------
    axis_point_m : sequence of 3 float
        A point on the axis (m).
    axis_dir : sequence of 3 float
        Axis direction (normalised internally); rotation is right-handed.
    omega_rad_s : float
        Angular speed (rad/s); negative turns the other way.
    """

    axis_point_m: tuple[float, float, float]
    axis_dir: tuple[float, float, float]
    omega_rad_s: float

    def __post_init__(self) -> None:
        vec3("axis_point_m", self.axis_point_m)
        vec3("axis_dir", self.axis_dir, unit=True)
        if not np.isfinite(self.omega_rad_s):
            raise MsmillInputError("omega_rad_s", self.omega_rad_s, "a finite number (rad/s)")

    def row(self) -> np.ndarray:
        """The packed ``grot`` row."""
        out = np.zeros(8)
        out[0:3] = vec3("axis_point_m", self.axis_point_m)
        out[3:6] = vec3("axis_dir", self.axis_dir, unit=True)
        out[6] = float(self.omega_rad_s)
        out[7] = 1.0
        return out


def _cyl_extent(points: np.ndarray, rot: np.ndarray) -> np.ndarray:
    """Rotation-invariant (r_min, r_max, a_min, a_max) of a point cloud (r_min = 0)."""
    a0 = rot[0:3]
    u = rot[3:6]
    rel = points - a0
    ax = rel @ u
    rad = np.linalg.norm(rel - np.outer(ax, u), axis=1)
    return np.array([0.0, rad.max(), ax.min(), ax.max()])


def box_corners(c: np.ndarray, axes: np.ndarray, h: np.ndarray) -> np.ndarray:
    """The 8 corners of an oriented box (m)."""
    s = np.array([[i, j, k] for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)], float)
    return c + (s * h) @ axes


def cylinder_points(p0: np.ndarray, u: np.ndarray, length: float, radius: float) -> np.ndarray:
    """Points whose hull bounds a cylinder (rim samples, for extents)."""
    tmp = np.array([1.0, 0, 0]) if abs(u[0]) < 0.9 else np.array([0, 1.0, 0])
    e1 = np.cross(u, tmp)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(u, e1)
    ang = np.linspace(0, 2 * np.pi, 72, endpoint=False)
    ring = radius / np.cos(np.pi / 72) * (np.outer(np.cos(ang), e1) + np.outer(np.sin(ang), e2))
    return np.concatenate([p0 + ring, p0 + length * u + ring])


def bound_row(kind: int, ref: np.ndarray, rot: np.ndarray) -> np.ndarray:
    """The ``gbound`` row of a primitive (see module docstring)."""
    if kind == PLANE:
        if rot[7] > 0:
            return np.array([0.0, np.inf, -np.inf, np.inf, 0, 0])
        return np.array([-np.inf, -np.inf, -np.inf, np.inf, np.inf, np.inf])
    if kind == BOX:
        pts = box_corners(ref[0:3], ref[3:12].reshape(3, 3), ref[12:15])
    else:
        pts = cylinder_points(ref[0:3], ref[3:6], ref[6], ref[7])
    if rot[7] > 0:
        return np.concatenate([_cyl_extent(pts, rot), [0.0, 0.0]])
    return np.concatenate([pts.min(axis=0), pts.max(axis=0)])


def spans_axis(kind: int, ref: np.ndarray, rot: np.ndarray, axis: int, period_m: float) -> bool:
    """True if a primitive is unchanged by sliding along ``axis`` over one period.

    Such a primitive (a plane parallel to the axis, a box or cylinder lying
    along it and at least one period long; if rotating, only about an axis
    parallel to it) is taken as continuous along a periodic axis; any other is
    met through its periodic images.
    """
    tol = 1e-9
    if rot[7] > 0 and abs(rot[3 + axis]) < 1.0 - tol:
        return False
    if kind == PLANE:
        return abs(ref[3 + axis]) < tol
    if kind == BOX:
        axes = ref[3:12].reshape(3, 3)
        return any(abs(axes[k, axis]) > 1.0 - tol and 2.0 * ref[12 + k] >= period_m for k in range(3))
    return abs(ref[3 + axis]) > 1.0 - tol and ref[6] >= period_m


def orthonormal_axes(name: str, axes) -> np.ndarray:
    """Validate a proper 3x3 rotation (rows are the box's local axes)."""
    if axes is None:
        return np.eye(3)
    try:
        a = np.asarray(axes, dtype=float).reshape(3, 3)
    except (TypeError, ValueError):
        raise MsmillInputError(name, axes, "a 3x3 orthonormal matrix (rows = local axes)") from None
    if not np.all(np.isfinite(a)) or not np.allclose(a @ a.T, np.eye(3), atol=1e-6):
        raise MsmillInputError(name, axes, "a 3x3 orthonormal matrix (rows = local axes)")
    return a
