"""Semi-analytical mill model (paper Section 3): sub-models, solvers, providers.

Public entry points: :class:`Mill` and :func:`simulate` (also exported lazily
as ``msmill.Mill`` / ``msmill.simulate``), the stage-parameter providers
(:class:`TableProvider`, :class:`RunProvider`) and the result
:class:`MillResult`. See ``docs/model.md``.
"""

from msmill.model import breakage_swebrec as _breakage_swebrec  # noqa: F401  (registers "vogel_swebrec")
from msmill.model.mill import Mill, simulate
from msmill.model.providers import (
    RunProvider,
    StageParameterProvider,
    TableProvider,
    load_provider,
    read_simple_table,
)
from msmill.model.result import MillResult
from msmill.model.solvers import SOLVERS, ExpectedValue, MonteCarlo, Solver
from msmill.model.submodels import (
    SUBMODELS,
    BreakageModel,
    BreakageParameters,
    DamageModel,
    ImpactModel,
    TransportModel,
)

__all__ = [
    "SOLVERS",
    "SUBMODELS",
    "BreakageModel",
    "BreakageParameters",
    "DamageModel",
    "ExpectedValue",
    "ImpactModel",
    "Mill",
    "MillResult",
    "MonteCarlo",
    "RunProvider",
    "Solver",
    "StageParameterProvider",
    "TableProvider",
    "TransportModel",
    "load_provider",
    "read_simple_table",
    "simulate",
]
