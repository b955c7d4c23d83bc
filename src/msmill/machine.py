"""Geometry of a multi-shaft vertical impact mill and its operating point.

:class:`Machine` describes the mill (stages, rotors, flingers, casing, inlet
chute, outlet gates, deflector plates); :class:`OperatingPoint` the way it is
run (feed rate, shaft speeds, gate angle). Both are validated pydantic models;
invalid input raises a one-line :class:`msmill.errors.MsmillInputError`.

Coordinate frame (used by the DEM scene and by every ``*_m`` field)
-------------------------------------------------------------------
* ``x`` runs horizontally **across** the shafts, from liner to liner; ``x = 0``
  is the vertical centre plane of the casing. The left rotor of every pair is
  at ``x = -rotor_axis_offset_m``, the right one at ``+rotor_axis_offset_m``.
* ``y`` runs **along** the shafts, from ``0`` to ``casing_length_m``.
* ``z`` points up. ``z = 0`` is the outlet plane below the gates (rock whose
  centre falls below it has left the mill). Stage ``n`` (bottom) has its rotor
  axes at ``bottom_axis_height_m``; stage ``s`` at
  ``bottom_axis_height_m + (n - s) * stage_spacing_m``.

Stage bands (how rock is assigned to a stage)
---------------------------------------------
Stage ``s`` is the horizontal band ``stage_axis_z_m(s) +- stage_spacing_m / 2``,
except that the bottom stage extends down to the outlet plane (so its
pass-through is exactly the rock that left through the outlet) and everything
above the top of stage 1 is the *inlet zone* (so stage 1's kickback is rock
moved into the inlet zone).

Rotation sense
--------------
Each rotor's sense is given by the direction its flingers move when they pass
through the central gap between the two rotors of the pair: ``"down"`` or
``"up"``. ``("down", "down")`` is a counter-rotating pair whose flingers sweep
rock down through the centre (and rise along the liners);
``("down", "up")`` is a co-rotating pair. In right-hand terms about ``+y``
the angular velocity of a rotor is ``+omega`` for a left rotor sweeping down
and ``-omega`` for a right rotor sweeping down.

Gate angle
----------
Each of the two outlet gates is a flat plate ``gate_length_m`` long (and as
long as the casing along ``y``), hinged on its side wall (``x = +-casing
half-width``) at ``gate_hinge_drop_m`` below the bottom-stage axes. The gate
angle is measured **from the horizontal, downwards**: at ``0 deg`` both gates
stick straight out from the walls as horizontal shelves and the free opening
between their tips is narrowest (``casing_width_m - 2 gate_length_m``); at
``90 deg`` they would hang vertically against the walls (fully open). The
design space is 0-80 deg, where 80 deg is nearly fully open. Both gates always
share one angle (paper Section 3.3.2).
"""

from __future__ import annotations

import math
import tomllib
import warnings
from pathlib import Path
from typing import Any, Literal

import tomli_w
from pydantic import ConfigDict, Field, ValidationError, model_validator

from msmill.errors import MsmillInputError, OutOfDomainWarning, from_validation_error
from msmill.validate import InputModel

__all__ = ["DESIGN_SPACE", "Deflector", "Machine", "OperatingPoint"]

Sweep = Literal["down", "up"]
#: the rotation sense of ``Machine.default()``: counter-rotating pairs sweeping down through the centre
DEFAULT_ROTATION_SENSE = "down_down"

#: Design space of the surrogate (paper Table 2, domain-notes Section 1).
DESIGN_SPACE: dict[str, tuple[float, float]] = {
    "size_mm": (2.0, 30.0),
    "feed_tph": (10.0, 60.0),
    "speed_rpm": (1200.0, 1900.0),
    "gate_deg": (0.0, 80.0),
}


#: Smallest and largest length a machine field may have (m): below 1 mm a plate or
#: clearance is numerically meaningless for the DEM, above 100 m it is a typo.
LENGTH_RANGE_M = (1e-3, 100.0)


#: Largest shaft speed accepted (rpm): a 0.19 m flinger tip then moves at 200 m/s,
#: far past any impact mill (the design space ends at 1900 rpm upper, 3800 rpm bottom).
MAX_SPEED_RPM = 10_000.0
#: Largest feed rate accepted (t/h).
MAX_FEED_TPH = 10_000.0


class _Model(InputModel):
    """Frozen, strict-keyed pydantic base: the constructor raises one-line ``MsmillInputError``."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)


class Deflector(_Model):
    """A flat deflector plate fixed to both side liners above one stage.

    The plate spans the whole casing length along ``y``. It starts at the
    liner (``x = +-casing half-width``) at height ``height_above_axis_m``
    above the rotor axes of ``stage`` and runs towards the centre at
    ``angle_deg`` below the horizontal (negative: rising towards the centre),
    ``length_m`` along its slope. Two plates are made, one per liner, mirror
    images of each other. A plate rising from the liner to the roof at the
    chute edge makes a hipped roof whose underside turns rock thrown up along
    the liners back towards the centre.

    Parameters
    ----------
    stage : int
        Stage (1 = top) above whose rotors the plates sit.
    height_above_axis_m : float
        Height of the plates' liner edge above the stage's rotor axes (m).
    length_m : float
        Plate length along its slope (m).
    angle_deg : float
        Slope below the horizontal towards the centre (deg, -90 to 90;
        negative rises towards the centre).
    """

    stage: int = Field(ge=1)
    height_above_axis_m: float = Field(gt=0)
    length_m: float = Field(gt=0)
    angle_deg: float = Field(ge=-90, le=90)

    def inner_edge_offset_m(self) -> float:
        """Horizontal reach of the plate from the liner (m)."""
        return self.length_m * math.cos(math.radians(self.angle_deg))

    def drop_m(self) -> float:
        """Height of the liner edge minus that of the inner edge (m; negative if rising inwards)."""
        return self.length_m * math.sin(math.radians(self.angle_deg))


class Machine(_Model):
    """Validated geometry of a multi-shaft vertical impact mill.

    All lengths in metres, angles in degrees. See the module docstring for the
    coordinate frame, stage bands, rotation sense and gate-angle conventions.

    Parameters
    ----------
    name : str
        Label of the machine description.
    n_stages : int
        Number of rotor stages (pairs of horizontal shafts), stacked vertically.
    stage_spacing_m : float
        Vertical distance between the rotor axes of consecutive stages (m).
    bottom_axis_height_m : float
        Height of the bottom-stage rotor axes above the outlet plane ``z = 0`` (m).
    rotor_axis_offset_m : float
        Horizontal distance of each rotor axis from the casing centre plane (m).
    hub_radius_m : float
        Radius of the shaft hub that carries the flingers (m).
    tip_radius_m : float
        Radius of the flinger tips (m).
    flinger_rows : int
        Rows of flingers along each shaft.
    flingers_per_row : int
        Flingers in one row, equally spaced in angle (``360 / flingers_per_row``).
    row_pitch_m : float
        Distance between consecutive rows along the shaft (m).
    row_stagger_deg : float
        Angular offset of each row relative to the previous one (deg).
    flinger_thickness_m, flinger_width_m : float
        Flinger plate thickness (in the direction of motion) and width (along
        the shaft) (m). A plate spans radially from hub to tip.
    casing_width_m : float
        Inside width of the casing across the shafts, liner to liner (m).
    casing_length_m : float
        Inside length of the casing along the shafts (m).
    headroom_m : float
        Height of the casing roof above the top-stage rotor axes (m).
    chute_width_m : float
        Width (across the shafts) of the central feed chute in the roof (m); it
        runs the full casing length along the shafts.
    gate_length_m : float
        Length of each outlet gate plate from hinge to tip (m).
    gate_hinge_drop_m : float
        Height of the gate hinges below the bottom-stage rotor axes (m).
    central_sweep : list of (str, str) or None
        Per stage, the direction ("down" or "up") the left and right rotor's
        flingers move when passing the central gap. ``None`` means
        ``("down", "down")`` for every stage (counter-rotating, sweeping down
        in the centre).
    deflectors : list of Deflector
        Deflector plates fixed to the liners.
    description : str
        Free-text provenance of the description.
    """

    name: str = "machine"
    n_stages: int = Field(default=5, ge=1, le=20)
    # flinger counts are bounded: each flinger is a DEM primitive
    stage_spacing_m: float = Field(default=0.45, gt=0)
    bottom_axis_height_m: float = Field(default=0.60, gt=0)
    rotor_axis_offset_m: float = Field(default=0.215, gt=0)
    hub_radius_m: float = Field(default=0.05, gt=0)
    tip_radius_m: float = Field(default=0.19, gt=0)
    flinger_rows: int = Field(default=6, ge=1, le=100)
    flingers_per_row: int = Field(default=3, ge=1, le=36)
    row_pitch_m: float = Field(default=0.10, gt=0)
    row_stagger_deg: float = Field(default=20.0, ge=-360, le=360)
    flinger_thickness_m: float = Field(default=0.012, gt=0)
    flinger_width_m: float = Field(default=0.08, gt=0)
    casing_width_m: float = Field(default=0.96, gt=0)
    casing_length_m: float = Field(default=0.60, gt=0)
    headroom_m: float = Field(default=0.24, gt=0)
    chute_width_m: float = Field(default=0.16, gt=0)
    gate_length_m: float = Field(default=0.30, gt=0)
    gate_hinge_drop_m: float = Field(default=0.25, gt=0)
    central_sweep: list[tuple[Sweep, Sweep]] | None = None
    deflectors: list[Deflector] = Field(default_factory=list)
    description: str = ""

    @model_validator(mode="after")
    def _check(self) -> Machine:
        lo_m, hi_m = LENGTH_RANGE_M
        for key in type(self).model_fields:
            v = getattr(self, key)
            if key.endswith("_m") and not lo_m <= v <= hi_m:
                raise ValueError(f"{key} = {v:g} m is outside {lo_m:g}-{hi_m:g} m")
        half_w = self.casing_width_m / 2
        if self.tip_radius_m <= self.hub_radius_m:
            raise ValueError(f"tip_radius_m ({self.tip_radius_m}) must exceed hub_radius_m ({self.hub_radius_m})")
        if self.rotor_axis_offset_m + self.tip_radius_m >= half_w:
            raise ValueError("flinger tips must clear the liners: rotor_axis_offset_m + tip_radius_m < casing_width_m / 2")
        if self.rotor_axis_offset_m < self.tip_radius_m:
            raise ValueError("flinger tips of a pair must not overlap: rotor_axis_offset_m >= tip_radius_m")
        if self.n_stages > 1 and 2 * self.tip_radius_m >= self.stage_spacing_m:
            raise ValueError("flinger circles of consecutive stages must clear: 2 tip_radius_m < stage_spacing_m")
        if self.flinger_width_m > self.row_pitch_m:
            raise ValueError("flinger_width_m must not exceed row_pitch_m")
        if self.flinger_rows * self.row_pitch_m > self.casing_length_m + 1e-9:
            raise ValueError("flinger_rows * row_pitch_m must fit in casing_length_m")
        if self.flinger_thickness_m >= self.tip_radius_m - self.hub_radius_m:
            raise ValueError("flinger_thickness_m must be smaller than the flinger length")
        if self.chute_width_m >= self.casing_width_m:
            raise ValueError("chute_width_m must be smaller than casing_width_m")
        if self.headroom_m <= self.tip_radius_m:
            raise ValueError("headroom_m must exceed tip_radius_m (roof above the top flingers)")
        if 2 * self.gate_length_m >= self.casing_width_m:
            raise ValueError("the two gates must not touch when horizontal: 2 gate_length_m < casing_width_m")
        if self.gate_hinge_drop_m <= self.tip_radius_m:
            raise ValueError("gate hinges must sit below the bottom flingers: gate_hinge_drop_m > tip_radius_m")
        if self.gate_hinge_drop_m + self.gate_length_m >= self.bottom_axis_height_m:
            raise ValueError(
                "gates hanging vertically must end above the outlet plane: "
                "gate_hinge_drop_m + gate_length_m < bottom_axis_height_m"
            )
        if self.central_sweep is not None and len(self.central_sweep) != self.n_stages:
            raise ValueError(f"central_sweep needs one (left, right) pair per stage ({self.n_stages})")
        for d in self.deflectors:
            if d.stage > self.n_stages:
                raise ValueError(f"deflector stage {d.stage} exceeds n_stages {self.n_stages}")
            if d.inner_edge_offset_m() >= half_w:
                raise ValueError("deflector plates must not reach the centre plane")
            if d.stage == 1 and max(d.height_above_axis_m, d.height_above_axis_m - d.drop_m()) > self.headroom_m + 1e-9:
                raise ValueError("stage-1 deflector plates must stay below the roof")
            if self._deflector_clearance(d) <= 0:
                raise ValueError(f"deflector plates above stage {d.stage} cut the flinger circles")
        return self

    def _deflector_clearance(self, d: Deflector) -> float:
        """Smallest distance from a deflector plate to a flinger tip circle of its stage (m)."""
        hw = self.casing_width_m / 2
        p0 = (-hw, d.height_above_axis_m)
        p1 = (-hw + d.inner_edge_offset_m(), d.height_above_axis_m - d.drop_m())
        best = math.inf
        for ax in (-self.rotor_axis_offset_m, self.rotor_axis_offset_m):
            dx, dz = p1[0] - p0[0], p1[1] - p0[1]
            t = max(0.0, min(1.0, ((ax - p0[0]) * dx + (0.0 - p0[1]) * dz) / (dx * dx + dz * dz)))
            best = min(best, math.hypot(p0[0] + t * dx - ax, p0[1] + t * dz) - self.tip_radius_m)
        return best

    # ------------------------------------------------------------------ I/O
    @classmethod
    def default(cls) -> Machine:
        """The documented representative 5-stage mill (``data/machines/default.toml``)."""
        return cls.from_toml(Path(__file__).parent / "data" / "machines" / "default.toml")

    @classmethod
    def from_dict(cls, data: dict[str, Any], source: str = "machine") -> Machine:
        """Validate a plain dict (e.g. a parsed TOML table); errors are one line."""
        try:
            return cls.model_validate(data)
        except ValidationError as exc:
            raise from_validation_error(exc, prefix=source) from None

    @classmethod
    def from_toml(cls, path_or_text: str | Path) -> Machine:
        """Read a machine from a TOML file (or TOML text containing a newline).

        The file holds the fields at top level or under a ``[machine]`` table;
        deflectors are ``[[deflectors]]`` (or ``[[machine.deflectors]]``) tables.
        """
        from msmill.validate import read_text

        is_text = isinstance(path_or_text, str) and "\n" in path_or_text
        if not is_text and not isinstance(path_or_text, str | Path):
            raise MsmillInputError("machine file", type(path_or_text).__name__, "a path of a machine TOML file")
        source = "machine" if is_text else Path(path_or_text).name
        text = path_or_text if is_text else read_text(path_or_text, "machine file", "machine TOML file")
        try:
            data = tomllib.loads(str(text))
        except tomllib.TOMLDecodeError as exc:
            raise MsmillInputError(source, str(exc).split("\n")[0], "valid TOML") from None
        if "machine" in data and isinstance(data["machine"], dict):
            data = data["machine"]
        if not data:
            raise MsmillInputError(source, "an empty file", "machine fields (an empty file is not the "
                                   "default machine; use 'default' or Machine.default())")
        return cls.from_dict(data, source=source)

    def to_toml(self, path: str | Path | None = None) -> str:
        """Serialise as TOML text under a ``[machine]`` table (and write to ``path``)."""
        data = self.model_dump(exclude_none=True)
        if data.get("central_sweep") is not None:
            data["central_sweep"] = [list(p) for p in data["central_sweep"]]
        if not data["deflectors"]:
            data.pop("deflectors")
        text = tomli_w.dumps({"machine": data})
        if path is not None:
            Path(path).write_text(text, encoding="utf-8")
        return text

    # ------------------------------------------------------------ identity
    def geometry_hash(self) -> str:
        """SHA-256 (16 hex digits) of what the DEM sees: every field but ``name`` and ``description``,
        the rotation sense written out (``central_sweep`` None and all ``("down", "down")`` hash alike).

        Two machines with equal geometry hashes give the same DEM runs; a surrogate records the hash of
        the machine it was trained on, so a prediction for another machine can say so.
        """
        import hashlib
        import json

        d = self.model_dump(mode="json", exclude={"name", "description"})
        d["central_sweep"] = [list(self.sweep(s)) for s in range(1, self.n_stages + 1)]
        text = json.dumps(d, sort_keys=True, separators=(",", ":"))
        return hashlib.sha256(text.encode()).hexdigest()[:16]

    @property
    def rotation_sense(self) -> str:
        """Name of the rotation-sense configuration (:func:`rotation_senses`) this machine's sweeps match,
        ``"custom"`` for any other pattern."""
        mine = [self.sweep(s) for s in range(1, self.n_stages + 1)]
        for name, sweeps in rotation_senses().items():
            if _sense_pattern(sweeps, self.n_stages) == mine:
                return name
        return "custom"

    def with_rotation_sense(self, sense: str, field: str = "rotation_sense") -> Machine:
        """This machine with the rotors turning as configuration ``sense`` (:func:`rotation_senses`)."""
        senses = rotation_senses()
        if sense not in senses:
            raise MsmillInputError(field, sense, ", ".join(senses))
        sweeps = _sense_pattern(senses[sense], self.n_stages)
        return self.model_copy(update={"central_sweep": None if sense == DEFAULT_ROTATION_SENSE else sweeps})

    # ------------------------------------------------------------ geometry
    @property
    def half_width_m(self) -> float:
        """Half the casing width: the liners are at ``x = +-half_width_m`` (m)."""
        return self.casing_width_m / 2

    @property
    def n_rotors(self) -> int:
        """Number of rotors (two per stage)."""
        return 2 * self.n_stages

    @property
    def flingers_per_rotor(self) -> int:
        """Flingers on one rotor (rows x flingers per row)."""
        return self.flinger_rows * self.flingers_per_row

    @property
    def liner_clearance_m(self) -> float:
        """Gap between the flinger tip circle and the side liner (m)."""
        return self.half_width_m - self.rotor_axis_offset_m - self.tip_radius_m

    @property
    def central_gap_m(self) -> float:
        """Gap between the tip circles of the two rotors of a pair (m)."""
        return 2 * (self.rotor_axis_offset_m - self.tip_radius_m)

    @property
    def stage_clearance_m(self) -> float:
        """Vertical gap between tip circles of consecutive stages (m)."""
        return self.stage_spacing_m - 2 * self.tip_radius_m

    @property
    def roof_z_m(self) -> float:
        """Height of the casing roof (m)."""
        return self.stage_axis_z_m(1) + self.headroom_m

    @property
    def gate_hinge_z_m(self) -> float:
        """Height of the gate hinges (m)."""
        return self.bottom_axis_height_m - self.gate_hinge_drop_m

    @property
    def inlet_zone_bottom_z_m(self) -> float:
        """Lower boundary of the inlet zone = top of stage 1's band (m)."""
        return self.stage_band_m(1)[1]

    def stage_axis_z_m(self, stage: int) -> float:
        """Height of the rotor axes of ``stage`` (1 = top) (m)."""
        self._check_stage(stage)
        return self.bottom_axis_height_m + (self.n_stages - stage) * self.stage_spacing_m

    def stage_band_m(self, stage: int) -> tuple[float, float]:
        """``(z_low, z_high)`` of the band that defines ``stage`` (m).

        Bands are ``axis +- stage_spacing_m / 2``; the bottom band extends down
        to the outlet plane ``z = 0``.
        """
        z = self.stage_axis_z_m(stage)
        lo = 0.0 if stage == self.n_stages else z - self.stage_spacing_m / 2
        return lo, z + self.stage_spacing_m / 2

    def stage_edges_z_m(self) -> list[float]:
        """Band boundaries from the outlet plane up to the inlet zone: ``n + 1`` heights, ascending (m)."""
        return [0.0] + [self.stage_band_m(s)[1] for s in range(self.n_stages, 0, -1)]

    def rotor_x_m(self, side: int) -> float:
        """Horizontal position of the left (``side = 0``) or right (``1``) rotor axis (m)."""
        return -self.rotor_axis_offset_m if side == 0 else self.rotor_axis_offset_m

    def rotor_index(self, stage: int, side: int) -> int:
        """Index of a rotor: ``2 (stage - 1) + side`` (0-based, left = 0, right = 1)."""
        self._check_stage(stage)
        return 2 * (stage - 1) + side

    def sweep(self, stage: int) -> tuple[Sweep, Sweep]:
        """Central-gap sweep direction of the (left, right) rotor of ``stage``."""
        self._check_stage(stage)
        if self.central_sweep is None:
            return ("down", "down")
        return self.central_sweep[stage - 1]

    def omega_sign(self, stage: int, side: int) -> int:
        """Sign of the angular velocity about ``+y`` of a rotor (right-hand rule).

        A left rotor sweeping down through the centre turns at ``+omega``; a
        right rotor sweeping down at ``-omega``.
        """
        down = self.sweep(stage)[side] == "down"
        sign = 1 if down else -1
        return sign if side == 0 else -sign

    def flinger_phase_deg(self, row: int, k: int) -> float:
        """Initial angle of flinger ``k`` of ``row`` (deg).

        Measured in the x-z plane from ``+x`` towards ``+z``:
        ``row * row_stagger_deg + k * 360 / flingers_per_row``. Rows are
        numbered from ``y = 0``; row ``j`` is centred at
        ``(j + 0.5) * row_pitch_m + (casing_length_m - flinger_rows * row_pitch_m) / 2``.
        """
        return (row * self.row_stagger_deg + k * 360.0 / self.flingers_per_row) % 360.0

    def row_y_m(self, row: int) -> float:
        """Centre of flinger row ``row`` along the shaft (m)."""
        margin = (self.casing_length_m - self.flinger_rows * self.row_pitch_m) / 2
        return margin + (row + 0.5) * self.row_pitch_m

    def gate_tip_m(self, gate_deg: float, side: int) -> tuple[float, float]:
        """``(x, z)`` of the free tip of the left (``side = 0``) or right gate (m)."""
        a = math.radians(gate_deg)
        dx = self.gate_length_m * math.cos(a)
        x = -self.half_width_m + dx if side == 0 else self.half_width_m - dx
        return x, self.gate_hinge_z_m - self.gate_length_m * math.sin(a)

    def gate_opening_m(self, gate_deg: float) -> float:
        """Free horizontal opening between the two gate tips (m)."""
        return self.casing_width_m - 2 * self.gate_length_m * math.cos(math.radians(gate_deg))

    def tip_speed_m_s(self, speed_rpm: float) -> float:
        """Flinger tip speed at ``speed_rpm`` (m/s)."""
        return rpm_to_rad_s(speed_rpm) * self.tip_radius_m

    def _check_stage(self, stage: int) -> None:
        if not 1 <= int(stage) <= self.n_stages:
            raise MsmillInputError("stage", stage, f"an integer 1..{self.n_stages}")


def rpm_to_rad_s(speed_rpm: float) -> float:
    """Convert a shaft speed from rpm to rad/s."""
    return float(speed_rpm) * 2.0 * math.pi / 60.0


def size_mm_to_radius_m(size_mm: Any) -> Any:
    """Radius (m) of a rock of size ``size_mm`` (its diameter, mm): ``size_mm / 2000``.

    A scalar gives a float, a sequence or array a float array (same rounding as the division).
    """
    if isinstance(size_mm, int | float):
        return float(size_mm) / 2000.0
    import numpy as np

    return np.asarray(size_mm, dtype=float) / 2000.0


class OperatingPoint(_Model):
    """How the mill is run: feed rate, shaft speeds and gate angle.

    Give either ``speed_rpm`` (all upper stages at that speed, the bottom stage
    at ``bottom_speed_factor`` times it, the paper's training recipe) or an
    explicit ``stage_speeds_rpm`` list (any recipe; stage 1 first). Inputs
    outside the surrogate's design space (domain-notes Section 1) raise an
    :class:`msmill.errors.OutOfDomainWarning`, not an error.

    Parameters
    ----------
    feed_tph : float
        Feed rate (t/h), > 0.
    speed_rpm : float, optional
        Upper-stage shaft speed (rpm), >= 0.
    stage_speeds_rpm : list of float, optional
        Speed of every stage (rpm), top first; overrides ``speed_rpm``.
    bottom_speed_factor : float
        Bottom-stage speed / upper-stage speed when ``speed_rpm`` is given.
    gate_deg : float
        Outlet gate angle below the horizontal (deg, 0-90; see :mod:`msmill.machine`).
    """

    feed_tph: float = Field(gt=0, le=MAX_FEED_TPH)
    speed_rpm: float | None = Field(default=None, ge=0, le=MAX_SPEED_RPM)
    stage_speeds_rpm: list[float] | None = None
    bottom_speed_factor: float = Field(default=2.0, gt=0, le=10)
    gate_deg: float = Field(default=40.0, ge=0, le=90)

    @model_validator(mode="after")
    def _check(self) -> OperatingPoint:
        if self.speed_rpm is None and self.stage_speeds_rpm is None:
            raise ValueError("give speed_rpm or stage_speeds_rpm")
        if self.speed_rpm is not None and self.stage_speeds_rpm is not None:
            raise ValueError("give speed_rpm or stage_speeds_rpm, not both (one would be ignored)")
        if self.stage_speeds_rpm is not None:
            if not self.stage_speeds_rpm or any(not 0 <= s <= MAX_SPEED_RPM for s in self.stage_speeds_rpm):
                raise ValueError(f"stage_speeds_rpm must be a non-empty list of speeds in 0-{MAX_SPEED_RPM:g} rpm")
        if self.speed_rpm is not None and self.speed_rpm * self.bottom_speed_factor > MAX_SPEED_RPM:
            raise ValueError(f"bottom stage speed speed_rpm x bottom_speed_factor = "
                             f"{self.speed_rpm * self.bottom_speed_factor:g} rpm exceeds {MAX_SPEED_RPM:g} rpm")
        _warn_outside("feed_tph", self.feed_tph)
        _warn_outside("gate_deg", self.gate_deg)
        for s in self._upper_speeds():
            if _warn_outside("speed_rpm", s):
                break
        return self

    def _upper_speeds(self) -> list[float]:
        if self.stage_speeds_rpm is not None:
            return list(self.stage_speeds_rpm[:-1]) or list(self.stage_speeds_rpm)
        return [float(self.speed_rpm)]  # type: ignore[arg-type]

    @property
    def upper_speed_rpm(self) -> float:
        """Speed of the upper stages (rpm): ``speed_rpm`` or stage 1's explicit speed."""
        if self.speed_rpm is not None and self.stage_speeds_rpm is None:
            return float(self.speed_rpm)
        return float(self.stage_speeds_rpm[0])  # type: ignore[index]

    def stage_speeds(self, n_stages: int) -> list[float]:
        """Shaft speed of every stage, top first (rpm).

        Raises
        ------
        MsmillInputError
            If an explicit ``stage_speeds_rpm`` list does not have ``n_stages`` entries.
        """
        if self.stage_speeds_rpm is not None:
            if len(self.stage_speeds_rpm) != n_stages:
                raise MsmillInputError("stage_speeds_rpm", self.stage_speeds_rpm, f"{n_stages} speeds (one per stage)")
            return [float(s) for s in self.stage_speeds_rpm]
        v = float(self.speed_rpm)  # type: ignore[arg-type]
        if n_stages == 1:
            return [v]
        return [v] * (n_stages - 1) + [v * self.bottom_speed_factor]

    @classmethod
    def from_dict(cls, data: dict[str, Any], source: str = "operating_point") -> OperatingPoint:
        """Validate a plain dict; errors are one line naming the field."""
        try:
            return cls.model_validate(data)
        except ValidationError as exc:
            raise from_validation_error(exc, prefix=source) from None


def _warn_outside(name: str, value: float) -> bool:
    lo, hi = DESIGN_SPACE[name]
    if not lo <= value <= hi:
        warnings.warn(
            f"{name}={value:g} is outside the design space [{lo:g}, {hi:g}]",
            OutOfDomainWarning,
            stacklevel=4,
        )
        return True
    return False


def check_size_mm(size_mm: float) -> None:
    """Warn (:class:`OutOfDomainWarning`) if a rock size lies outside 2-30 mm."""
    _warn_outside("size_mm", float(size_mm))


def rotation_senses() -> dict[str, list[tuple[str, str]]]:
    """Rotation-sense configurations of the rotation-sense study (issue 37; its machines are ``data/machines``): name ->
    per-stage (left, right) central-gap sweeps, the first stage's pair then the others'
    (``down_down``: all down, today's default; ``up_up``: all up; ``down_up`` / ``up_down``: the top
    stage one way, the rest the other; ``co_rotating``: left down, right up)."""
    return {name: [tuple(p) for p in pattern] for name, pattern in _ROTATION_SENSES.items()}


#: the study's configurations as (top stage, other stages) pairs of sweeps
_ROTATION_SENSES: dict[str, tuple[tuple[str, str], tuple[str, str]]] = {
    "down_down": (("down", "down"), ("down", "down")), "up_up": (("up", "up"), ("up", "up")),
    "down_up": (("down", "down"), ("up", "up")), "up_down": (("up", "up"), ("down", "down")),
    "co_rotating": (("down", "up"), ("down", "up"))}


def _sense_pattern(sweeps: list[tuple[str, str]], n_stages: int) -> list[tuple[str, str]]:
    """Per-stage sweeps of a configuration on a machine of ``n_stages``."""
    top, rest = sweeps
    return [tuple(top)] + [tuple(rest)] * (n_stages - 1)
