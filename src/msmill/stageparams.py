"""Per-stage impact and transport statistics: the contract between DEM and model.

A DEM run of the mill at one design point (one rock size, feed rate, shaft
speeds and gate angle) is summarised as a :class:`RunStatistics`: for every
rotor stage, where rocks go in one characteristic time (kickback, refeed,
pass-through), how often flingers hit them (primary impacts) and how many and
how hard the secondary impacts that follow are. The DEM statistics
(``msmill.dem``) write it, the SQL store (``msmill.surrogate``) keeps it, and the
mill model (``msmill.model``) reads it through a stage-parameter provider.

Conventions (schema version 1)
------------------------------
* Stages are numbered 1 (top) to ``n_stages`` (bottom).
* One model time step equals ``characteristic_time_s``. Of the rock mass in
  stage ``s`` at the start of a step, the fraction ``kickback`` is in stage
  ``s - 1`` one step later, ``refeed`` is still in ``s`` and ``pass_through``
  is in ``s + 1``. Kickback from stage 1 goes to the inlet zone and re-enters
  stage 1 with the fresh feed on the next step; pass-through from the bottom
  stage leaves the mill (through the gates) as product.
* ``primary_hit_probability`` is the probability that a rock in the stage is
  hit by a flinger (first rock-flinger contact per rotor per pass) within one
  characteristic time. ``primary_velocity`` is the distribution of the relative
  normal velocity at those impacts (m/s).
* Secondary impacts (rock-liner, rock-rock, and further rock-flinger contacts
  after a primary impact, until the next primary impact or the rock leaves the
  stage): their count per primary impact is Poisson with mean
  ``secondary_lambda`` (paper Eq. 13) and their relative normal velocity is the
  Gaussian mixture ``secondary_velocity`` (paper Eq. 14).
* All quantities are SI (m, s, kg, m/s), except ``size_mm``, ``feed_tph``,
  ``speed_rpm`` and ``gate_deg`` which carry their unit in their name.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from msmill.errors import MsmillInputError, from_validation_error

SCHEMA_VERSION = 1
N_REGIONS = 6  # horizontal regions along the rotor axis (paper Section 3.1.2)
_SUM_TOL = 1e-6


class _Frozen(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")


class _JsonDocument(_Frozen):
    """A frozen model that is written as one JSON document."""

    def to_json(self, path: str | Path | None = None) -> str:
        """Serialise to JSON text (and write it to ``path`` if given)."""
        text = self.model_dump_json(indent=2)
        if path is not None:
            Path(path).write_text(text + "\n", encoding="utf-8")
        return text


class GaussianMixture(_Frozen):
    """A 1-D Gaussian mixture of impact velocities (paper Eq. 14), in m/s.

    Parameters
    ----------
    weights : list of float
        Mixture weights ``phi_i`` (>= 0, summing to 1).
    means_m_s : list of float
        Component means ``mu_i`` (m/s).
    sigmas_m_s : list of float
        Component standard deviations ``sigma_i`` (m/s, > 0).
    """

    weights: list[float] = Field(min_length=1)
    means_m_s: list[float] = Field(min_length=1)
    sigmas_m_s: list[float] = Field(min_length=1)

    @model_validator(mode="after")
    def _check(self) -> GaussianMixture:
        n = len(self.weights)
        if len(self.means_m_s) != n or len(self.sigmas_m_s) != n:
            raise ValueError("weights, means_m_s and sigmas_m_s must have equal lengths")
        w = np.asarray(self.weights)
        if np.any(w < 0) or abs(w.sum() - 1.0) > _SUM_TOL:
            raise ValueError(f"weights must be >= 0 and sum to 1 (sum {w.sum():.6g})")
        if np.any(np.asarray(self.sigmas_m_s) <= 0):
            raise ValueError("sigmas_m_s must be > 0")
        if not np.all(np.isfinite(self.means_m_s)):
            raise ValueError("means_m_s must be finite")
        return self

    @property
    def n_components(self) -> int:
        """Number of mixture components ``K``."""
        return len(self.weights)

    def mean(self) -> float:
        """Mean velocity of the mixture (m/s)."""
        return float(np.dot(self.weights, self.means_m_s))

    def pdf(self, v_m_s: np.ndarray) -> np.ndarray:
        """Probability density at ``v_m_s`` (1/(m/s))."""
        v = np.asarray(v_m_s, dtype=float)[..., None]
        mu = np.asarray(self.means_m_s)
        sd = np.asarray(self.sigmas_m_s)
        z = (v - mu) / sd
        return np.sum(np.asarray(self.weights) * np.exp(-0.5 * z * z) / (sd * np.sqrt(2 * np.pi)), axis=-1)

    @classmethod
    def single(cls, mean_m_s: float, sigma_m_s: float) -> GaussianMixture:
        """A one-component mixture."""
        return cls(weights=[1.0], means_m_s=[mean_m_s], sigmas_m_s=[sigma_m_s])


class StageStatistics(_Frozen):
    """Impact and transport statistics of one rotor stage at one design point."""

    stage: int = Field(ge=1, description="stage number, 1 = top")
    kickback: float = Field(ge=0, le=1, description="mass fraction moving up per characteristic time")
    refeed: float = Field(ge=0, le=1, description="mass fraction staying in the stage")
    pass_through: float = Field(ge=0, le=1, description="mass fraction moving down")
    region_weights: list[float] | None = Field(
        default=None, description="solid-fraction weights of the 6 regions along the rotor axis"
    )
    region_streams: list[list[float]] | None = Field(
        default=None, description="per region: [kickback, refeed, pass_through]"
    )
    primary_hit_probability: float = Field(ge=0, le=1)
    primary_velocity: GaussianMixture
    primary_velocity_kl: float | None = None
    secondary_lambda: float = Field(ge=0, description="mean secondary impacts per primary impact")
    secondary_lambda_kl: float | None = None
    secondary_velocity: GaussianMixture
    secondary_velocity_kl: float | None = None
    n_primary_impacts: int = Field(default=0, ge=0, description="sample size behind the primary stats")
    n_secondary_impacts: int = Field(default=0, ge=0)
    n_transport_samples: int = Field(default=0, ge=0, description="tagged rocks behind the streams")
    mean_holdup_kg: float | None = Field(default=None, ge=0)
    sampling_error: dict[str, float] = Field(
        default_factory=dict, description="standard errors of the estimates, keyed by field name"
    )

    @model_validator(mode="after")
    def _check(self) -> StageStatistics:
        total = self.kickback + self.refeed + self.pass_through
        if abs(total - 1.0) > _SUM_TOL:
            raise ValueError(f"kickback + refeed + pass_through must be 1 (got {total:.6g})")
        if self.region_weights is not None:
            w = np.asarray(self.region_weights)
            if w.size != N_REGIONS or np.any(w < 0) or abs(w.sum() - 1) > _SUM_TOL:
                raise ValueError(f"region_weights must be {N_REGIONS} values >= 0 summing to 1")
        if self.region_streams is not None:
            s = np.asarray(self.region_streams, dtype=float)
            if s.shape != (N_REGIONS, 3) or np.any(s < 0) or np.any(np.abs(s.sum(axis=1) - 1) > _SUM_TOL):
                raise ValueError(f"region_streams must be {N_REGIONS} rows of 3 fractions summing to 1")
        return self

    @property
    def streams(self) -> np.ndarray:
        """``[kickback, refeed, pass_through]`` as an array."""
        return np.array([self.kickback, self.refeed, self.pass_through])


class DesignPoint(_Frozen):
    """The operating point of one DEM run (paper Table 2 design space)."""

    size_mm: float = Field(gt=0, description="rock (sphere) diameter, mm")
    feed_tph: float = Field(gt=0, description="feed rate, t/h")
    speed_rpm: float = Field(ge=0, description="upper-stage shaft speed, rpm")
    gate_deg: float = Field(ge=0, le=90, description="outlet gate angle, deg")
    stage_speeds_rpm: list[float] = Field(min_length=1, description="shaft speed of every stage, rpm")

    @field_validator("stage_speeds_rpm")
    @classmethod
    def _speeds(cls, v: list[float]) -> list[float]:
        if any(s < 0 for s in v):
            raise ValueError("stage speeds must be >= 0")
        return v


class RunStatistics(_JsonDocument):
    """All per-stage statistics of one DEM run, with run-level figures and provenance."""

    schema_version: Literal[1] = SCHEMA_VERSION
    design: DesignPoint
    mode: Literal["full", "slice"] = "slice"
    characteristic_time_s: float = Field(gt=0)
    stages: list[StageStatistics] = Field(min_length=1)
    steady_state_time_s: float | None = Field(default=None, ge=0)
    measurement_window_s: float | None = Field(default=None, ge=0)
    mass_out_rate_kg_s: float | None = Field(default=None, ge=0)
    residence_time_s: float | None = Field(default=None, ge=0)
    mean_centre_velocity_m_s: float | None = None
    provenance: dict[str, Any] = Field(default_factory=dict)
    # operating envelope (issue 20): how the run ended and what the mill passed; None = not recorded
    outcome: Literal["steady", "not_steady", "choked"] | None = Field(
        default=None, description="steady-state outcome of the run (msmill.steadystate); None: not recorded")
    throughput_tph: float | None = Field(
        default=None, ge=0, description="measured product rate in the window, full-mill equivalent, t/h")
    # adaptive measurement window (issue 12): largest sampling error reached per statistic family
    # (msmill.dem.mill.run.sampling_errors_reached); None: some stage had no sample of that family
    sampling_error_reached: dict[str, float | None] = Field(default_factory=dict)

    def require_steady(self, allow_not_steady: bool = False, source: str = "statistics") -> RunStatistics:
        """Return self if the run reached steady state; else raise (unless ``allow_not_steady``).

        Statistics from a filling or choked mill are wrong training data: ingest
        and the stage-parameter table refuse them. ``outcome`` None (files from
        before outcomes were recorded) passes.
        """
        if self.outcome in (None, "steady") or allow_not_steady:
            return self
        raise MsmillInputError(f"{source}.outcome", self.outcome,
                               "'steady' (a not-steady or choked run; allow it explicitly to use it)")

    @model_validator(mode="after")
    def _check(self) -> RunStatistics:
        numbers = [s.stage for s in self.stages]
        if numbers != list(range(1, len(numbers) + 1)):
            raise ValueError(f"stages must be numbered 1..n in order (got {numbers})")
        if len(self.design.stage_speeds_rpm) != len(self.stages):
            raise ValueError("design.stage_speeds_rpm must have one speed per stage")
        return self

    @property
    def n_stages(self) -> int:
        """Number of rotor stages."""
        return len(self.stages)

    @classmethod
    def from_json(cls, path_or_text: str | Path) -> RunStatistics:
        """Read from a JSON file path or JSON text; errors are one line."""
        p = Path(path_or_text) if not str(path_or_text).lstrip().startswith("{") else None
        text = p.read_text(encoding="utf-8") if p is not None else str(path_or_text)
        try:
            data = json.loads(text)
        except json.JSONDecodeError as exc:
            raise MsmillInputError(str(p or "json"), f"line {exc.lineno}", "valid JSON") from None
        return cls.from_dict(data, source=str(p) if p else "statistics")

    @classmethod
    def from_dict(cls, data: dict[str, Any], source: str = "statistics") -> RunStatistics:
        """Validate a plain dict; errors are one line naming the field."""
        version = data.get("schema_version", SCHEMA_VERSION) if isinstance(data, dict) else None
        if version != SCHEMA_VERSION:
            raise MsmillInputError(f"{source}.schema_version", version, f"{SCHEMA_VERSION}")
        try:
            return cls.model_validate(data)
        except ValidationError as exc:
            raise from_validation_error(exc, prefix=source) from None


class StageParameterTable(_JsonDocument):
    """Statistics of several DEM runs at one operating point, differing in rock size.

    This is the shipped default source of stage parameters for the mill model
    (``src/msmill/data/stage_parameters/*.json``) until the surrogate exists. The
    model interpolates between runs in (log) rock size and clamps outside the
    sizes covered, with a warning.
    """

    schema_version: Literal[1] = SCHEMA_VERSION
    kind: Literal["stage_parameter_table"] = "stage_parameter_table"
    runs: list[RunStatistics] = Field(min_length=1)
    provenance: dict[str, Any] = Field(default_factory=dict)
    allow_not_steady: bool = False  # accept runs whose outcome is not "steady" (issue 20)

    @model_validator(mode="after")
    def _check(self) -> StageParameterTable:
        for r in self.runs:
            if r.outcome not in (None, "steady") and not self.allow_not_steady:
                raise ValueError(f"run at {r.design.size_mm:g} mm is {r.outcome}: not-steady statistics are "
                                 "refused (set allow_not_steady to use them)")
        sizes = [r.design.size_mm for r in self.runs]
        if sizes != sorted(sizes) or len(set(sizes)) != len(sizes):
            raise ValueError(f"runs must have distinct rock sizes in ascending order (got {sizes})")
        n = {r.n_stages for r in self.runs}
        if len(n) != 1:
            raise ValueError(f"all runs must have the same number of stages (got {sorted(n)})")
        return self

    @property
    def sizes_mm(self) -> np.ndarray:
        """Rock sizes of the runs (mm), ascending."""
        return np.array([r.design.size_mm for r in self.runs])

    @classmethod
    def from_json(cls, path: str | Path) -> StageParameterTable:
        """Read and validate a table file; errors are one line naming the field."""
        p = Path(path)
        try:
            data = json.loads(p.read_text(encoding="utf-8"))
        except json.JSONDecodeError as exc:
            raise MsmillInputError(str(p), f"line {exc.lineno}", "valid JSON") from None
        if not isinstance(data, dict) or data.get("schema_version") != SCHEMA_VERSION:
            got = data.get("schema_version") if isinstance(data, dict) else type(data).__name__
            raise MsmillInputError(f"{p.name}.schema_version", got, f"{SCHEMA_VERSION}")
        try:
            return cls.model_validate(data)
        except ValidationError as exc:
            raise from_validation_error(exc, prefix=p.name) from None
