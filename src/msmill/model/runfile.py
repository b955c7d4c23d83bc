"""Run files of ``msmill predict``: a validated TOML description of one prediction.

Layout (every section but ``[feed]`` and ``[operating]`` is optional)::

    title = "UG2, 1500 rpm"

    [ore]
    name = "UG2"                 # ore registry name (msmill ore list)
    # file = "my_ore.toml"       # ... or an ore file (msmill ore show --help)
    # l_ref_mm = 25.0            # override the ore's reference size (mm)

    [feed]
    rate_tph = 30.0
    size_mm = [4.75, 9.5, 13.2, 19.0, 26.5, 37.5]   # a passing table ...
    passing_pct = [5.0, 20.0, 35.0, 60.0, 85.0, 100.0]
    # [feed.rosin_rammler]       # ... or a Rosin-Rammler spec
    # size_63_mm = 20.0          # size passing 63.2 % (mm)
    # spread = 1.5               # uniformity exponent
    # top_mm = 45.0              # top size (mm)

    [operating]                  # msmill.machine.OperatingPoint without feed_tph
    speed_rpm = 1500.0
    gate_deg = 40.0

    [machine]
    file = "my_mill.toml"        # optional; default Machine.default()

    [stage_parameters]
    file = "default"             # the shipped surrogate ("table": the single-point DEM table), or a path

    [model]                      # sub-models and solver (msmill.model.Mill)
    solver = "expected_value"
    damage = "tavares"
    band_samples = 64            # GP posterior samples of the 5-95 % band (surrogate only; 0: off)

    [grid]
    min_mm = 0.038
    ratio = 1.4142135623730951

    [output]
    dir = "out"                  # relative to the run file
    csv = "product.csv"
    plots = true

Relative paths are relative to the run file. Errors are one line naming the
field (``ug2.toml.feed.rate_tph: got -3; allowed: ...``).
"""

from __future__ import annotations

import math
import tomllib
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from msmill.errors import MsmillInputError, from_validation_error
from msmill.model.providers import DEFAULT_TABLE, named_parameter_path


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid")


class OreSection(_Section):
    name: str = Field(default="", description="ore registry name; or give file")
    file: str | None = Field(default=None, description="an ore TOML file (msmill.ore.Ore.from_toml)")
    l_ref_mm: float | None = Field(default=None, gt=0)

    @model_validator(mode="after")
    def _name_or_file(self) -> OreSection:
        if not self.name and self.file is None:
            raise ValueError("give the ore's registry name (name) or an ore TOML file (file)")
        return self


class RosinRammler(_Section):
    size_63_mm: float = Field(gt=0, description="size passing 63.2 % (mm)")
    spread: float = Field(gt=0, description="uniformity exponent")
    top_mm: float = Field(gt=0, description="top size (mm)")


class FeedSection(_Section):
    rate_tph: float = Field(gt=0)
    size_mm: list[float] | None = None
    passing_pct: list[float] | None = None
    rosin_rammler: RosinRammler | None = None

    @model_validator(mode="after")
    def _one_spec(self) -> FeedSection:
        table = self.size_mm is not None or self.passing_pct is not None
        if table == (self.rosin_rammler is not None):
            raise ValueError("give either size_mm + passing_pct or [feed.rosin_rammler]")
        if table and (self.size_mm is None or self.passing_pct is None):
            raise ValueError("size_mm and passing_pct go together")
        return self


class OperatingSection(_Section):
    speed_rpm: float | None = Field(default=None, ge=0)
    stage_speeds_rpm: list[float] | None = None
    bottom_speed_factor: float = Field(default=2.0, gt=0)
    gate_deg: float = Field(default=40.0, ge=0, le=90)


class MachineSection(_Section):
    file: str | None = None


class StageParametersSection(_Section):
    file: str = DEFAULT_TABLE


class ModelSection(_Section):
    solver: str = "expected_value"
    transport: str | None = None
    impacts: str | None = None
    breakage: str | None = None
    damage: str | None = None
    impacted: str = "refeed"
    damage_classes: int = Field(default=8, ge=1, le=64)
    quadrature_nodes: int = Field(default=12, ge=1, le=64)
    parcels_per_step: int = Field(default=2000, ge=1)
    mc_steps: int | None = Field(default=None, ge=2)
    seed: int | None = None
    band_samples: int = Field(default=64, ge=0, le=1024)  # GP posterior samples behind the 5-95 % band


class GridSection(_Section):
    min_mm: float = Field(default=0.038, gt=0)
    max_mm: float | None = Field(default=None, gt=0)
    ratio: float = Field(default=math.sqrt(2.0), gt=1)


class OutputSection(_Section):
    dir: str = "."
    csv: str = "product.csv"
    plots: bool = True
    passing_sizes_mm: list[float] = Field(default_factory=lambda: [0.075, 0.15, 0.6, 1.0, 2.0, 5.0, 10.0])


class RunFile(_Section):
    """A validated run file (see the module docstring)."""

    title: str = ""
    ore: OreSection
    feed: FeedSection
    operating: OperatingSection
    machine: MachineSection = Field(default_factory=MachineSection)
    stage_parameters: StageParametersSection = Field(default_factory=StageParametersSection)
    model: ModelSection = Field(default_factory=ModelSection)
    grid: GridSection = Field(default_factory=GridSection)
    output: OutputSection = Field(default_factory=OutputSection)
    base_dir: Path = Field(default=Path("."), exclude=True)
    name: str = Field(default="run", exclude=True)

    @classmethod
    def from_toml(cls, path: str | Path) -> RunFile:
        """Read and validate a run file; errors are one line naming the field."""
        p = Path(path)
        if not p.is_file():
            raise MsmillInputError("run file", str(p), "an existing TOML file")
        try:
            data = tomllib.loads(p.read_text(encoding="utf-8"))
        except tomllib.TOMLDecodeError as exc:
            raise MsmillInputError(p.name, str(exc).split("\n")[0], "valid TOML") from None
        return cls.from_mapping(data, name=p.name, base_dir=p.resolve().parent)

    @classmethod
    def from_mapping(cls, data: dict[str, Any], name: str = "run", base_dir: str | Path = ".") -> RunFile:
        """Validate run-file contents given as a mapping (e.g. a JSON request).

        Parameters
        ----------
        data : dict
            The run file's tables, as :func:`tomllib.loads` would return them.
        name : str
            Prefix of every error's field name (the file name, or ``"request"``).
        base_dir : path
            Folder that relative paths in ``data`` are relative to.
        """
        if not isinstance(data, dict):
            raise MsmillInputError(name, type(data).__name__, "a table of run-file sections")
        for key in ("base_dir", "name"):
            if key in data:
                raise MsmillInputError(f"{name}.{key}", data[key], "not a run-file key")
        try:
            return cls.model_validate({**data, "base_dir": Path(base_dir), "name": name})
        except ValidationError as exc:
            raise from_validation_error(exc, prefix=name) from None

    def path(self, value: str) -> Path:
        """A path from the run file, relative to its folder."""
        q = Path(value).expanduser()
        return q if q.is_absolute() else self.base_dir / q

    # ------------------------------------------------------------------ builders
    def feed_psd(self):
        """The feed PSD (``msmill.psd.PSD``)."""
        from msmill.psd import PSD, SizeGrid

        f = self.feed
        try:
            if f.rosin_rammler is not None:
                rr = f.rosin_rammler
                grid = SizeGrid.geometric(self.grid.min_mm, rr.top_mm, self.grid.ratio)
                x = grid.edges_mm[1:]
                passing = 100.0 * (1.0 - np.exp(-((x / rr.size_63_mm) ** rr.spread)))
                passing[-1] = 100.0
                return PSD.from_passing(x, passing, grid=grid)
            return PSD.from_passing(f.size_mm, f.passing_pct)
        except MsmillInputError as exc:
            raise MsmillInputError(f"{self.name}.feed.{exc.field}", exc.value, exc.allowed) from None

    def model_grid(self, feed):
        """The model size grid (sqrt(2) series from ``grid.min_mm`` to the feed top by default)."""
        from msmill.psd import SizeGrid

        top = self.grid.max_mm or float(feed.grid.edges_mm[-1])
        if top <= self.grid.min_mm:
            raise MsmillInputError(f"{self.name}.grid.max_mm", top, f"a size > grid.min_mm ({self.grid.min_mm})")
        return SizeGrid.geometric(self.grid.min_mm, top, self.grid.ratio)

    def operating_point(self):
        """The :class:`msmill.machine.OperatingPoint`."""
        from msmill.machine import OperatingPoint

        try:
            return OperatingPoint.model_validate({**self.operating.model_dump(exclude_none=True),
                                                  "feed_tph": self.feed.rate_tph})
        except ValidationError as exc:
            raise from_validation_error(exc, prefix=f"{self.name}.operating") from None

    def machine_obj(self):
        """The machine (``Machine.default()`` unless a file is given)."""
        from msmill.machine import Machine

        if self.machine.file is None:
            return Machine.default()
        p = self.path(self.machine.file)
        if not p.is_file():
            raise MsmillInputError(f"{self.name}.machine.file", self.machine.file, "an existing machine TOML file")
        return Machine.from_toml(p)

    def stage_parameter_path(self) -> Path:
        """The stage-parameter file (the packaged default table for ``"default"``)."""
        v = self.stage_parameters.file
        named = named_parameter_path(v, f"{self.name}.stage_parameters.file")
        if named is not None:
            return named
        p = self.path(v)
        if not p.is_file():
            raise MsmillInputError(f"{self.name}.stage_parameters.file", v, "an existing table or run-statistics file")
        return p

    def ore_obj(self):
        """The ore (registry lookup or ``file``, optional ``l_ref_mm`` override)."""
        from msmill.ore import Ore, get_ore

        if self.ore.file is not None:
            p = self.path(self.ore.file)
            if not p.is_file():
                raise MsmillInputError(f"{self.name}.ore.file", self.ore.file, "an existing ore TOML file")
            ore = Ore.from_toml(p)
        else:
            try:
                ore = get_ore(self.ore.name)
            except MsmillInputError as exc:
                raise MsmillInputError(f"{self.name}.ore.name", self.ore.name, exc.allowed) from None
        if self.ore.l_ref_mm is not None:
            ore = ore.with_l_ref(self.ore.l_ref_mm, source=f"run file {self.name}")
        return ore

    def build(self) -> tuple[Any, Any, Any]:
        """Validate everything and return ``(mill, feed_psd, operating_point)``; writes nothing."""
        from msmill.model.mill import Mill

        feed = self.feed_psd()
        op = self.operating_point()
        machine = self.machine_obj()
        from msmill.model.providers import load_provider

        provider = load_provider(self.stage_parameter_path())  # file errors name the file and field
        m = self.model
        try:
            mill = Mill(self.ore_obj(), provider, machine, transport=m.transport, impacts=m.impacts,
                        breakage=m.breakage, damage=m.damage, solver=m.solver, impacted=m.impacted,
                        grid=self.model_grid(feed), damage_classes=m.damage_classes,
                        quadrature_nodes=m.quadrature_nodes, parcels_per_step=m.parcels_per_step,
                        mc_steps=m.mc_steps, seed=m.seed, passing_sizes_mm=self.output.passing_sizes_mm,
                        band_samples=m.band_samples)
        except MsmillInputError as exc:
            field = exc.field
            model_fields = ("solver", "impacted", "damage_classes", "quadrature_nodes", "parcels_per_step")
            if field.startswith("model.") or field in model_fields:
                field = f"{self.name}.model.{field.removeprefix('model.')}"
            elif field.startswith(("machine.", "ore.")):
                field = f"{self.name}.{field}"
            raise MsmillInputError(field, exc.value, exc.allowed) from None
        try:
            op.stage_speeds(mill.provider.n_stages)
        except MsmillInputError as exc:
            raise MsmillInputError(f"{self.name}.operating.{exc.field}", exc.value, exc.allowed) from None
        return mill, feed, op


