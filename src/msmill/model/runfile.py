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
    rotation_sense = "up_up"     # optional: the rotors turning as one of msmill.machine.rotation_senses()
                                 # ("down_down" is the default's; stage_parameters "default" then names
                                 # that sense's shipped surrogate, a one-line error while none is shipped)

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
import warnings
from pathlib import Path
from typing import Any, Self

import numpy as np
from pydantic import (
    ConfigDict,
    Field,
    ValidationError,
    ValidationInfo,
    field_validator,
    model_validator,
)

from msmill.errors import MsmillInputError, from_validation_error
from msmill.model.mill import MIN_MC_STEPS
from msmill.model.providers import DEFAULT_TABLE, named_parameter_path
from msmill.validate import InputModel, InputWarning, limit, read_toml, user_path


class _Section(InputModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


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


#: A Rosin-Rammler feed is cut at ``top_mm`` and the tail above it put in the top class;
#: below this % passing at ``top_mm`` the cut changes the feed materially and warns
#: (``top_mm = 5`` with ``size_63_mm = 20`` lumps 88 % of the feed; the shipped
#: platreef example cuts a 7.6 % tail and does not warn).
RR_MIN_PASSING_AT_TOP_PCT = 80.0


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


    def psd(self, min_mm: float = 0.038, ratio: float = math.sqrt(2.0), name: str = "run"):
        """The feed PSD (``msmill.psd.PSD``); a Rosin-Rammler spec on the ``min_mm`` / ``ratio`` series.

        ``name`` prefixes the field of every error (``<name>.feed.size_mm``).
        """
        from msmill.psd import PSD, SizeGrid

        try:
            if self.rosin_rammler is not None:
                rr = self.rosin_rammler
                grid = SizeGrid.geometric(min_mm, rr.top_mm, ratio)
                x = grid.edges_mm[1:]
                with np.errstate(over="ignore", under="ignore"):  # a huge spread is a step: exp(-inf) = 0
                    passing = 100.0 * (1.0 - np.exp(-((x / rr.size_63_mm) ** rr.spread)))
                z = min(rr.spread * math.log(rr.top_mm / rr.size_63_mm), 700.0)  # ln((top / x63)^n)
                at_top = 100.0 * (1.0 - math.exp(-math.exp(z)))
                if at_top < RR_MIN_PASSING_AT_TOP_PCT:
                    warnings.warn(f"{name}.feed.rosin_rammler: only {at_top:.3g} % passes top_mm = "
                                  f"{rr.top_mm:g} mm; the other {100 - at_top:.3g} % is put in the top class",
                                  InputWarning, stacklevel=3)
                passing[-1] = 100.0
                return PSD.from_passing(x, passing, grid=grid)
            return PSD.from_passing(self.size_mm, self.passing_pct, prefix=f"{name}.feed.")
        except MsmillInputError as exc:
            field = exc.field if exc.field.startswith(name) else f"{name}.feed.{exc.field}"
            raise MsmillInputError(field, exc.value, exc.allowed) from None


class OperatingSection(_Section):
    speed_rpm: float | None = Field(default=None, ge=0)
    stage_speeds_rpm: list[float] | None = None
    bottom_speed_factor: float = Field(default=2.0, gt=0)
    gate_deg: float = Field(default=40.0, ge=0, le=90)




class MachineSection(_Section):
    file: str | None = None
    rotation_sense: str | None = Field(default=None, description="rotation-sense configuration "
                                       "(msmill.machine.rotation_senses); default the machine's own")


class StageParametersSection(_Section):
    file: str = DEFAULT_TABLE


class ModelSection(_Section):
    solver: str = "expected_value"
    transport: str | None = None
    impacts: str | None = None
    breakage: str | None = None
    damage: str | None = None
    impacted: str = "refeed"
    damage_classes: int = Field(default=8, ge=1)
    quadrature_nodes: int = Field(default=12, ge=1)
    parcels_per_step: int = Field(default=2000, ge=1)
    mc_steps: int | None = Field(default=None, ge=MIN_MC_STEPS)
    seed: int | None = Field(default=None, ge=0, lt=2**63)
    band_samples: int = Field(default=64, ge=0, le=1024)  # GP posterior samples behind the 5-95 % band

    @field_validator("damage_classes", "quadrature_nodes", "parcels_per_step", "mc_steps")
    @classmethod
    def _limits(cls, v: int | None, info: ValidationInfo) -> int | None:
        if v is not None:
            limit(v, info.field_name)  # resource limits, msmill.validate.LIMITS
        return v


class GridSection(_Section):
    min_mm: float = Field(default=0.038, gt=0)
    max_mm: float | None = Field(default=None, gt=0)
    ratio: float = Field(default=math.sqrt(2.0), gt=1)


class OutputSection(_Section):
    dir: str = Field(default=".", min_length=1)
    csv: str = "product.csv"
    plots: bool = True
    passing_sizes_mm: list[float] = Field(default_factory=lambda: [0.075, 0.15, 0.6, 1.0, 2.0, 5.0, 10.0],
                                          min_length=1, max_length=100)

    @model_validator(mode="after")
    def _sizes(self) -> OutputSection:
        c = self.csv
        if not c.endswith(".csv") or c == ".csv" or "/" in c or "\\" in c or c.startswith("."):
            raise ValueError("csv must be a plain file name ending in .csv, without a folder part")
        if any(not s > 0 for s in self.passing_sizes_mm):
            raise ValueError("passing_sizes_mm must be sizes > 0 mm")
        return self


class MillSpec(_Section):
    """The sections that describe one mill (ore, operating settings, machine, stage parameters, model).

    Shared by :class:`RunFile` (one mill and its feed) and the mill units of a circuit
    (:mod:`msmill.model.circuit`), which get their feed from the circuit.
    """

    ore: OreSection
    operating: OperatingSection
    machine: MachineSection = Field(default_factory=MachineSection)
    stage_parameters: StageParametersSection = Field(default_factory=StageParametersSection)
    model: ModelSection = Field(default_factory=ModelSection)
    base_dir: Path = Field(default=Path("."), exclude=True)
    name: str = Field(default="run", exclude=True)

    def path(self, value: str) -> Path:
        """A path from the run file, relative to its folder."""
        q = user_path(value, f"{self.name} path")
        return q if q.is_absolute() else self.base_dir / q

    def operating_point(self, feed_tph: float):
        """The :class:`msmill.machine.OperatingPoint` at ``feed_tph`` (t/h)."""
        from msmill.machine import OperatingPoint

        try:
            return OperatingPoint.model_validate({**self.operating.model_dump(exclude_none=True),
                                                  "feed_tph": feed_tph})
        except ValidationError as exc:
            raise from_validation_error(exc, prefix=f"{self.name}.operating") from None

    def machine_obj(self):
        """The machine (``Machine.default()`` unless a file is given)."""
        from msmill.machine import Machine

        if self.machine.file is None:
            machine = Machine.default()
        else:
            p = self.path(self.machine.file)
            if not p.is_file():
                raise MsmillInputError(f"{self.name}.machine.file", self.machine.file, "an existing machine TOML file")
            machine = Machine.from_toml(p)
        if self.machine.rotation_sense is not None:
            machine = machine.with_rotation_sense(self.machine.rotation_sense, f"{self.name}.machine.rotation_sense")
        return machine

    def with_rotation_sense(self, sense: str) -> Self:
        """A copy whose ``[machine] rotation_sense`` is ``sense`` (checked where the machine is built).

        Its machine and stage parameters then resolve as this spec's would for that sense
        (:meth:`machine_obj`, :meth:`stage_parameter_path`): a sweep over senses builds its mills from these.
        """
        return self.model_copy(update={"machine": self.machine.model_copy(update={"rotation_sense": sense})})

    def stage_parameter_path(self) -> Path:
        """The stage-parameter file (the packaged default table for ``"default"``)."""
        v = self.stage_parameters.file
        named = named_parameter_path(v, f"{self.name}.stage_parameters.file", self.machine_obj())
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

    def build_mill(self, grid, passing_sizes_mm, band_samples: int | None = None, feed_tph: float | None = None):
        """The :class:`msmill.model.Mill` on ``grid`` (validated; writes nothing).

        ``feed_tph`` (t/h) only serves the check that the operating section gives a
        speed for every stage (None: a mill whose feed is not known yet, e.g. in a
        circuit; the feed rate's own checks are then left to the run); ``band_samples``
        overrides the model section's.
        """
        from msmill.model.mill import Mill
        from msmill.model.providers import load_provider

        with warnings.catch_warnings():
            if feed_tph is None:
                warnings.simplefilter("ignore")  # no feed rate yet: its design-space warning is the run's
            op = self.operating_point(1.0 if feed_tph is None else feed_tph)
        machine = self.machine_obj()
        provider = load_provider(self.stage_parameter_path())  # file errors name the file and field
        m = self.model
        try:
            mill = Mill(self.ore_obj(), provider, machine, transport=m.transport, impacts=m.impacts,
                        breakage=m.breakage, damage=m.damage, solver=m.solver, impacted=m.impacted,
                        grid=grid, damage_classes=m.damage_classes,
                        quadrature_nodes=m.quadrature_nodes, parcels_per_step=m.parcels_per_step,
                        mc_steps=m.mc_steps, seed=m.seed, passing_sizes_mm=passing_sizes_mm,
                        band_samples=m.band_samples if band_samples is None else band_samples)
        except MsmillInputError as exc:
            field = exc.field
            model_fields = ("solver", "impacted", "damage_classes", "quadrature_nodes", "parcels_per_step")
            if field.startswith("model.") or field in model_fields:
                field = f"{self.name}.model.{field.removeprefix('model.')}"
            elif field.startswith(("machine.", "ore.")):
                field = f"{self.name}.{field}"
            raise MsmillInputError(field, exc.value, exc.allowed) from None
        if m.solver == "monte_carlo" and m.mc_steps is not None:
            limit(m.parcels_per_step * m.mc_steps, f"{self.name}.model.parcels_per_step x mc_steps",
                  "parcels_total")
        try:
            op.stage_speeds(mill.provider.n_stages)
        except MsmillInputError as exc:
            raise MsmillInputError(f"{self.name}.operating.{exc.field}", exc.value, exc.allowed) from None
        return mill


class RunFile(MillSpec):
    """A validated run file (see the module docstring)."""

    title: str = ""
    feed: FeedSection
    grid: GridSection = Field(default_factory=GridSection)
    output: OutputSection = Field(default_factory=OutputSection)

    @classmethod
    def from_toml(cls, path: str | Path) -> RunFile:
        """Read and validate a run file; errors are one line naming the field."""
        data = read_toml(path, "run file", "TOML file")
        p = user_path(path, "run file")
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
        missing = [k for k in ("ore", "feed", "operating") if k not in data]
        if missing:
            raise MsmillInputError(f"{name}.{missing[0]}", None, f"a [{missing[0]}] section "
                                   "(every run file needs [ore], [feed] and [operating])")
        for key in ("base_dir", "name"):
            if key in data:
                raise MsmillInputError(f"{name}.{key}", data[key], "not a run-file key")
        try:
            return cls.model_validate({**data, "base_dir": Path(base_dir), "name": name})
        except ValidationError as exc:
            raise from_validation_error(exc, prefix=name) from None

    # ------------------------------------------------------------------ builders
    def feed_psd(self):
        """The feed PSD (``msmill.psd.PSD``)."""
        return self.feed.psd(self.grid.min_mm, self.grid.ratio, self.name)

    def model_grid(self, feed):
        """The model size grid (sqrt(2) series from ``grid.min_mm`` to the feed top by default)."""
        from msmill.psd import SizeGrid

        feed_top = float(feed.grid.edges_mm[-1])
        top = self.grid.max_mm or feed_top
        if top <= self.grid.min_mm:
            if self.grid.max_mm is None:
                raise MsmillInputError(f"{self.name}.grid.min_mm", self.grid.min_mm,
                                       f"a size < the feed's top size ({feed_top:.4g} mm)")
            raise MsmillInputError(f"{self.name}.grid.max_mm", top, f"a size > grid.min_mm ({self.grid.min_mm})")
        if top < feed_top * (1 - 1e-9):
            raise MsmillInputError(f"{self.name}.grid.max_mm", self.grid.max_mm,
                                   f"a size >= the feed's top size ({feed_top:.4g} mm); a smaller grid "
                                   "would lump the coarser feed into its top class")
        n = math.ceil(math.log(top / self.grid.min_mm) / math.log(self.grid.ratio) - 1e-9)
        limit(n, f"{self.name}.grid (min_mm, max_mm, ratio)", "grid_classes")
        return SizeGrid.geometric(self.grid.min_mm, top, self.grid.ratio)

    def operating_point(self, feed_tph: float | None = None):
        """The :class:`msmill.machine.OperatingPoint` at the feed's rate (or ``feed_tph``, t/h)."""
        return super().operating_point(self.feed.rate_tph if feed_tph is None else feed_tph)

    def build(self) -> tuple[Any, Any, Any]:
        """Validate everything and return ``(mill, feed_psd, operating_point)``; writes nothing."""
        feed = self.feed_psd()
        op = self.operating_point()
        mill = self.build_mill(self.model_grid(feed), self.output.passing_sizes_mm, feed_tph=self.feed.rate_tph)
        return mill, feed, op
