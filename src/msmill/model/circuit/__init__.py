"""Closed circuits: the mill with screens, splitters and recycle, at steady state by tear streams, with a 5-95 % band from posterior samples.

Units (:mod:`msmill.model.circuit.units`) are small registered classes behind one
interface; a :class:`Circuit` joins them by streams and solves its steady state by
direct substitution or Wegstein acceleration (:mod:`msmill.model.circuit.solve`);
circuit files are validated TOML (:mod:`msmill.model.circuit.file`). See
``docs/circuit.md``.
"""

from msmill.model.circuit.file import CircuitFile
from msmill.model.circuit.solve import (
    METHODS,
    Circuit,
    CircuitBand,
    CircuitNotConverged,
    CircuitResult,
    Stream,
)
from msmill.model.circuit.units import (
    UNITS,
    BreakageMatrixMill,
    FreshFeed,
    MillUnit,
    Product,
    SampleTransfers,
    Screen,
    Splitter,
    Unit,
    register_unit,
    whiten_fine_partition,
)

__all__ = [
    "METHODS",
    "UNITS",
    "BreakageMatrixMill",
    "Circuit",
    "CircuitBand",
    "CircuitFile",
    "CircuitNotConverged",
    "CircuitResult",
    "FreshFeed",
    "MillUnit",
    "Product",
    "SampleTransfers",
    "Screen",
    "Splitter",
    "Stream",
    "Unit",
    "register_unit",
    "whiten_fine_partition",
]
