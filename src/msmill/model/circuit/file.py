"""Circuit files: a validated TOML description of units and the streams between them.

Layout::

    title = "UG2 closed circuit"

    [grid]                       # optional: the size classes of every stream
    min_mm = 0.038
    ratio = 1.4142135623730951   # top: the coarsest fresh feed's top size

    [solver]                     # optional
    method = "wegstein"          # or "direct"
    tol = 1e-10                  # relative mass-balance error
    max_iterations = 500

    [band]                       # optional: the 5-95 % band from the surrogate's posterior samples
    samples = 64                 # 0: no band
    seed = 0

    [[units]]
    name = "fresh"
    type = "feed"
    rate_tph = 30.0
    size_mm = [2.0, 9.5, 19.0, 31.5]
    passing_pct = [2.0, 18.0, 58.0, 100.0]

    [[units]]
    name = "mill"
    type = "mill"                # the sections of a run file that describe a mill:
    ore = { name = "UG2" }       # [ore], [operating], [machine], [stage_parameters], [model]
    operating = { speed_rpm = 1500.0, gate_deg = 40.0 }

    [[units]]
    name = "screen"
    type = "screen"
    d50c_mm = 6.0                # Whiten: cut size, sharpness, fish-hook, bypass
    alpha = 4.0
    beta = 0.0
    bypass = 0.05

    [[units]]
    name = "product"
    type = "product"

    [[streams]]
    name = "mill_feed"
    from = "fresh"               # "unit" (its only outlet) or "unit.outlet"
    to = "mill"
    # recycle = true             # counted in the circulating load (default: the torn streams)

Unit types: :data:`msmill.model.circuit.units.UNITS` (``feed``, ``product``, ``screen``,
``splitter`` with ``fractions = {a = 0.4, b = 0.6}``, ``mill``, ``breakage_matrix`` with
``matrix``). Relative paths are relative to the circuit file. Errors are one line naming
the field (``ug2_closed_circuit.toml.units[2].d50c_mm: got -1; allowed: ...``).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

from pydantic import ConfigDict, Field, ValidationError

from msmill.errors import MsmillInputError, from_validation_error
from msmill.model.circuit.solve import DEFAULT_MAX_ITERATIONS, DEFAULT_TOL, METHODS, Circuit, Stream
from msmill.model.circuit.units import (
    UNITS,
    BreakageMatrixMill,
    FreshFeed,
    MillUnit,
    Product,
    Screen,
    Splitter,
)
from msmill.model.mill import DEFAULT_BAND_SAMPLES, MAX_BAND_SAMPLES
from msmill.model.runfile import GridSection
from msmill.validate import InputModel, read_toml, user_path


class _Section(InputModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=True)


class SolverSpec(_Section):
    method: str = "wegstein"
    tol: float = Field(default=DEFAULT_TOL, gt=0, lt=1)
    max_iterations: int = Field(default=DEFAULT_MAX_ITERATIONS, ge=1, le=100000)


class BandSpec(_Section):
    samples: int = Field(default=DEFAULT_BAND_SAMPLES, ge=0, le=MAX_BAND_SAMPLES)
    seed: int = Field(default=0, ge=0)


class StreamSpec(_Section):
    name: str = Field(min_length=1)
    from_: str = Field(alias="from", min_length=1)
    to: str = Field(min_length=1)
    recycle: bool = False


def _unit(i: int, table: Any, name: str, base_dir: Path, grid: GridSection) -> Any:
    where = f"{name}.units[{i}]"
    if not isinstance(table, dict):
        raise MsmillInputError(where, type(table).__name__, "a [[units]] table")
    spec = dict(table)
    uname = spec.pop("name", None)
    if not isinstance(uname, str) or not uname or "." in uname:
        raise MsmillInputError(f"{where}.name", uname, "a unit name (text without '.')")
    utype = spec.pop("type", None)
    if utype not in UNITS:
        from msmill.model.submodels import did_you_mean

        raise MsmillInputError(f"{where}.type", utype, did_you_mean(str(utype), list(UNITS)))
    try:
        if utype == "feed":
            from msmill.model.runfile import FeedSection

            fs = FeedSection.model_validate(spec)
            return FreshFeed(uname, fs.rate_tph, fs.psd(grid.min_mm, grid.ratio, where))
        if utype == "product":
            _no_keys(spec, where, ())
            return Product(uname)
        if utype == "screen":
            _no_keys(spec, where, ("d50c_mm", "alpha", "beta", "bypass"))
            return _renamed(where, uname, lambda: Screen(uname, **spec))
        if utype == "splitter":
            _no_keys(spec, where, ("fractions",))
            if "fractions" not in spec:
                raise MsmillInputError(f"{where}.fractions", None, "a table {outlet = fraction}")
            return _renamed(where, uname, lambda: Splitter(uname, spec["fractions"]))
        if utype == "breakage_matrix":
            _no_keys(spec, where, ("matrix",))
            return _renamed(where, uname, lambda: BreakageMatrixMill(uname, spec.get("matrix")))
        if utype == "mill":
            from msmill.model.mill import DEFAULT_PASSING_SIZES_MM
            from msmill.model.runfile import MillSpec


            ms = MillSpec.model_validate({**spec, "base_dir": base_dir, "name": where})
            mill = ms.build_mill(None, DEFAULT_PASSING_SIZES_MM, band_samples=0)  # the circuit's band is its own
            return _renamed(where, uname, lambda: MillUnit(uname, mill, ms.operating.model_dump(exclude_none=True)))
    except ValidationError as exc:
        raise from_validation_error(exc, prefix=where) from None
    raise AssertionError(utype)  # pragma: no cover - every registered type is handled above


def _no_keys(spec: dict, where: str, allowed: tuple[str, ...]) -> None:
    for k in spec:
        if k not in allowed:
            raise MsmillInputError(f"{where}.{k}", spec[k], "one of: " + ", ".join(("name", "type", *allowed)))


def _renamed(where: str, uname: str, make: Any) -> Any:
    """Build a unit; its errors' fields (``uname.key``) renamed to the file's (``file.units[i].key``)."""
    try:
        return make()
    except TypeError as exc:  # a missing required key
        raise MsmillInputError(where, str(exc).split("(")[-1].rstrip(")") if "(" in str(exc) else str(exc),
                               "the unit's required keys (docs/circuit.md)") from None
    except MsmillInputError as exc:
        f = exc.field
        f = f"{where}.{f.removeprefix(uname + '.')}" if f.startswith(uname + ".") else f
        raise MsmillInputError(f, exc.value, exc.allowed) from None


def _stream(i: int, table: Any, name: str) -> Stream:
    where = f"{name}.streams[{i}]"
    if not isinstance(table, dict):
        raise MsmillInputError(where, type(table).__name__, "a [[streams]] table")
    try:
        s = StreamSpec.model_validate(table)
    except ValidationError as exc:
        raise from_validation_error(exc, prefix=where) from None
    source, _, outlet = s.from_.partition(".")
    return Stream(s.name, source, outlet or "", s.to, s.recycle)


class CircuitFile:
    """A validated circuit file: :attr:`circuit` (a :class:`Circuit`) and the solver settings."""

    def __init__(self, circuit: Circuit, solver: SolverSpec, name: str, band: BandSpec | None = None) -> None:
        self.circuit = circuit
        self.solver = solver
        self.name = name
        self.band_spec = band or BandSpec()

    @classmethod
    def from_toml(cls, path: str | Path) -> CircuitFile:
        """Read and validate a circuit file; errors are one line naming the field."""
        data = read_toml(path, "circuit file", "TOML file")
        p = user_path(path, "circuit file")
        return cls.from_mapping(data, name=p.name, base_dir=p.resolve().parent)

    @classmethod
    def from_mapping(cls, data: dict[str, Any], name: str = "circuit", base_dir: str | Path = ".") -> CircuitFile:
        """Validate circuit-file contents given as a mapping (see the module docstring)."""
        if not isinstance(data, dict):
            raise MsmillInputError(name, type(data).__name__, "a table of circuit-file sections")
        for k in data:
            if k not in ("title", "grid", "solver", "band", "units", "streams"):
                raise MsmillInputError(f"{name}.{k}", data[k], "one of: title, grid, solver, band, units, streams")
        for k in ("units", "streams"):
            if not isinstance(data.get(k), list) or not data[k]:
                raise MsmillInputError(f"{name}.{k}", data.get(k), f"one or more [[{k}]] tables")
        try:
            grid = GridSection.model_validate(data.get("grid", {}))
            solver = SolverSpec.model_validate(data.get("solver", {}))
            band = BandSpec.model_validate(data.get("band", {}))
        except ValidationError as exc:
            raise from_validation_error(exc, prefix=name) from None
        if solver.method not in METHODS:
            raise MsmillInputError(f"{name}.solver.method", solver.method, " or ".join(METHODS))
        title = data.get("title", "")
        if not isinstance(title, str):
            raise MsmillInputError(f"{name}.title", title, "text")
        units = [_unit(i, t, name, Path(base_dir), grid) for i, t in enumerate(data["units"])]
        streams = [_stream(i, t, name) for i, t in enumerate(data["streams"])]
        # "unit" alone names its only outlet
        byname = {u.name: u for u in units}
        streams = [Stream(s.name, s.source, s.outlet or (byname[s.source].outlets[0]
                                                          if s.source in byname and len(byname[s.source].outlets) == 1
                                                          else ""), s.target, s.recycle) for s in streams]
        feeds = [u for u in units if isinstance(u, FreshFeed)]
        top = max((u.top_mm for u in feeds), default=grid.min_mm * 2)
        top = grid.max_mm or top
        if feeds and grid.max_mm is not None and grid.max_mm < max(u.top_mm for u in feeds) * (1 - 1e-9):
            raise MsmillInputError(f"{name}.grid.max_mm", grid.max_mm, "a size >= every fresh feed's top size")
        if top <= grid.min_mm:
            raise MsmillInputError(f"{name}.grid.min_mm", grid.min_mm, f"a size < the top size ({top:.4g} mm)")
        from msmill.psd import SizeGrid
        from msmill.validate import limit

        n = math.ceil(math.log(top / grid.min_mm) / math.log(grid.ratio) - 1e-9)
        limit(n, f"{name}.grid (min_mm, max_mm, ratio)", "grid_classes")
        circuit = Circuit(units, streams, SizeGrid.geometric(grid.min_mm, top, grid.ratio), title=title, prefix=name)
        return cls(circuit, solver, name, band)

    def solve(self) -> Any:
        """The circuit's steady state with the file's solver settings."""
        return self.circuit.solve(self.solver.method, self.solver.tol, self.solver.max_iterations)

    def band(self, result: Any, n_samples: int | None = None) -> Any:
        """The 5-95 % band of ``result`` with the file's ``[band]`` settings (None when samples = 0)."""
        n = self.band_spec.samples if n_samples is None else n_samples
        if not n:
            return None
        return self.circuit.band(result, n, self.band_spec.seed, self.solver.method, self.solver.tol,
                                 self.solver.max_iterations)
