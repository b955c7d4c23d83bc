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
        shown = repr(value)
        if len(shown) > 80:
            shown = shown[:77] + "..."
        super().__init__(f"{field}: got {shown}; allowed: {allowed}")


class OutOfDomainWarning(UserWarning):
    """An input lies outside the range a model or surrogate was built on."""


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
    field = f"{prefix}.{loc}" if prefix and loc else (prefix or loc or "input")
    msg = str(err.get("msg", "invalid value"))
    for lead in ("Value error, ", "Assertion failed, "):
        if msg.startswith(lead):
            msg = msg[len(lead):]
    return MsmillInputError(field, err.get("input"), msg)
