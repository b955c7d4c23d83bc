"""Error types shared by every layer of msmill.

Every user-facing validation failure raises :class:`MsmillInputError`, whose
message is one line naming the field, the offending value and what is allowed.
The CLI prints that line (no traceback) and exits with status 2.
"""

from __future__ import annotations

from typing import Any


class MsmillError(Exception):
    """Base class of msmill's own errors."""


class MsmillInputError(MsmillError, ValueError):
    """Invalid user input: a field, its value and what is allowed.

    Parameters
    ----------
    field : str
        Name of the offending field (as the user wrote it, e.g. ``feed_tph``).
    value : Any
        The value received.
    allowed : str
        What is allowed, e.g. ``"a number > 0"``.
    """

    def __init__(self, field: str, value: Any, allowed: str) -> None:
        self.field = field
        self.value = value
        self.allowed = allowed
        shown = show_value(value)
        super().__init__(f"{field}: got {shown}; allowed: {allowed}")


class OutOfDomainWarning(UserWarning):
    """An input lies outside the range a model or surrogate was built on."""


class ExtrapolationWarning(OutOfDomainWarning):
    """Much of the product rests on stage statistics extrapolated beyond the sizes the DEM ran."""


class ThinDataWarning(OutOfDomainWarning):
    """Inside the trained range, but far from every training run: the prediction rests on thin data."""


class SummaryNote(UserWarning):
    r"""Information for the run's summary, not a warning (e.g. sizes clamped to the DEM data).

    :class:`msmill.model.Mill` collects these into ``MillResult.notes`` instead of
    re-issuing them; anywhere else they behave as ordinary ``UserWarning``\ s.
    """


def show_value(value: Any, width: int = 80) -> str:
    """A short, one-line text of a user's value (numpy scalars and arrays shown as plain numbers)."""
    try:
        import numpy as np

        if isinstance(value, np.generic):
            value = value.item()
        elif isinstance(value, np.ndarray):
            value = value.tolist() if value.size <= 20 else f"array of shape {value.shape}"
    except ImportError:  # pragma: no cover
        pass
    shown = value if isinstance(value, str) and value.startswith("array of shape") else repr(value)
    shown = " ".join(str(shown).split())
    return shown if len(shown) <= width else shown[: width - 3] + "..."


def from_validation_error(exc: Any, prefix: str = "") -> MsmillInputError:
    """Turn a pydantic ``ValidationError`` into a one-line :class:`MsmillInputError`.

    Parameters
    ----------
    exc : pydantic.ValidationError
        The error raised by a pydantic model.
    prefix : str, optional
        Prepended to the field path (e.g. a file name or section).
    """
    err = exc.errors()[0]
    loc = ".".join(str(p) for p in err.get("loc", ()))
    inner = (err.get("ctx") or {}).get("error")
    if isinstance(inner, MsmillInputError):  # already one line: keep it, add the location
        tail = inner.field if not loc.endswith(inner.field) else ""
        parts = [p for p in (prefix, loc, tail) if p]
        return MsmillInputError(".".join(parts), inner.value, inner.allowed)
    msg = str(err.get("msg", "invalid value"))
    for lead in ("Value error, ", "Assertion failed, "):
        if msg.startswith(lead):
            msg = msg[len(lead):]
    value = err.get("input")
    if err.get("type") == "missing":
        value, msg = None, "a value (this field is required)"
    elif isinstance(value, dict):
        # a model-level check: name the input keys its message mentions, not the whole dict
        import re

        named = [k for k in value if isinstance(k, str) and re.search(rf"\b{re.escape(k)}\b", msg)]
        if named:
            loc = ".".join(p for p in (loc, "/".join(named)) if p)
            value = value[named[0]] if len(named) == 1 else {k: value[k] for k in named}
        elif not value:
            value = "nothing"
    field = f"{prefix}.{loc}" if prefix and loc else (prefix or loc or "input")
    return MsmillInputError(field, value, msg)
