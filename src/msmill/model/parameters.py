"""Per-stage, per-size-class parameter arrays consumed by the sub-models.

The types moved to the core module :mod:`msmill.providers_base` (the surrogate
layer implements providers and cannot import the model layer); they are
re-exported here so existing imports keep working.
"""

from __future__ import annotations

from msmill.providers_base import (
    CountArrays,
    MixtureArrays,
    StageParameterProvider,
    StageParameters,
)

__all__ = ["CountArrays", "MixtureArrays", "StageParameterProvider", "StageParameters"]
