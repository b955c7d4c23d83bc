"""One place for validating user input (core layer; used by the CLI and the public API).

Every check raises :class:`msmill.errors.MsmillInputError` with one line naming
the field *as the user wrote it* (``ug2.toml.feed.rate_tph``, ``--size-mm``),
the value and what is allowed. The families:

* files: :func:`read_text` / :func:`read_toml` (exists, is a file, below
  :data:`MAX_TEXT_BYTES`, UTF-8 text), :func:`existing_file`,
  :func:`existing_dir`;
* numbers: :func:`number` (a real number, not a bool, finite, in range, with
  the unit in the message), :func:`integer` (an integral number, range);
* arrays: :func:`sizes` (1-D, finite, > 0, strictly increasing),
  :func:`passing` (0-100 %, non-decreasing, fractions detected, last value
  100 % or an explicit warned oversize);
* conflicts: :func:`exclusive`;
* resource limits: :func:`limit` with the named limits in :data:`LIMITS`
  (anything that allocates by a user's number);
* pydantic: :func:`pydantic_errors` converts a ``ValidationError`` raised in
  its block into :class:`MsmillInputError` (one line).

Warnings about questionable but usable input use :class:`InputWarning`; notes
that belong in a summary rather than a warning use
:class:`msmill.errors.SummaryNote`.
"""

from __future__ import annotations

import contextlib
import math
import numbers
import tomllib
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import BaseModel, ValidationError, model_validator

from msmill.errors import MsmillInputError

__all__ = [
    "LIMITS",
    "MAX_TEXT_BYTES",
    "InputModel",
    "InputWarning",
    "exclusive",
    "existing_dir",
    "existing_file",
    "integer",
    "limit",
    "number",
    "passing",
    "pydantic_errors",
    "read_csv",
    "read_text",
    "read_toml",
    "sizes",
]

#: Largest TOML / JSON text file read (bytes): larger is not a hand-written input.
MAX_TEXT_BYTES = 64 * 2**20

#: Resource limits on numbers that size an allocation or a loop (name: (limit, what)).
LIMITS: dict[str, tuple[int, str]] = {
    "parcels_per_step": (1_000_000, "Monte-Carlo parcels per step"),
    "mc_steps": (200_000, "Monte-Carlo steps"),
    "time_steps": (1_000_000, "time steps marched by the expected-value solver"),
    "parcels_total": (50_000_000, "Monte-Carlo parcels fed (parcels_per_step x steps)"),
    "damage_classes": (64, "damage classes"),
    "quadrature_nodes": (64, "quadrature nodes"),
    "grid_classes": (2_000, "size classes of the model grid"),
    "dem_particles": (5_000_000, "DEM rocks fed during a run"),
    "dem_steps": (100_000_000, "DEM time steps"),
    "csv_rows": (50_000_000, "CSV rows"),
    # a sweep or optimiser grid costs a steady state (and its band) per point: ~1 s each
    "sweep_points": (10_000, "operating points of a sweep or an optimiser grid"),
    "n_grid": (1_000, "optimiser grid points per variable"),
}


class InputModel(BaseModel):
    """pydantic base of msmill's public models: constructing one with bad input raises a one-line
    :class:`MsmillInputError` naming the field (``OperatingPoint(feed_tph=-30)`` ->
    ``feed_tph: got -30; allowed: ...``), not a multi-line ``ValidationError``; and ``true``/``false``
    is not accepted for a number. ``model_validate`` still raises ``ValidationError`` (loaders convert
    it with their file name as prefix).
    """

    def __init__(self, /, **data: Any) -> None:
        try:
            super().__init__(**data)
        except ValidationError as exc:
            from msmill.errors import from_validation_error

            raise from_validation_error(exc) from None

    @model_validator(mode="before")
    @classmethod
    def _no_bools(cls, data: Any) -> Any:
        return reject_bools(cls, data)


class InputWarning(UserWarning):
    """Input that is usable but probably not what was meant (says what and by how much)."""


def _is_number(value: Any) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, bool | np.bool_)


def number(value: Any, field: str, *, unit: str = "", gt: float | None = None,
           ge: float | None = None, lt: float | None = None, le: float | None = None) -> float:
    """A finite real number within bounds; returns it as ``float``.

    Parameters
    ----------
    value : Any
        The user's value (a bool or a string is rejected).
    field : str
        Field name as the user wrote it.
    unit : str
        Unit shown in the message (``"mm"``, ``"m/s"``).
    gt, ge, lt, le : float, optional
        Exclusive / inclusive bounds.
    """
    u = f" {unit}" if unit else ""
    bounds = [f"> {gt:g}{u}" if gt is not None else "", f">= {ge:g}{u}" if ge is not None else "",
              f"< {lt:g}{u}" if lt is not None else "", f"<= {le:g}{u}" if le is not None else ""]
    allowed = "a finite number" + (" " + " and ".join(b for b in bounds if b) if any(bounds) else u)
    if not _is_number(value) or not math.isfinite(float(value)):
        raise MsmillInputError(field, value, allowed)
    v = float(value)
    if ((gt is not None and not v > gt) or (ge is not None and not v >= ge)
            or (lt is not None and not v < lt) or (le is not None and not v <= le)):
        raise MsmillInputError(field, value, allowed)
    return v


def integer(value: Any, field: str, *, ge: int | None = None, le: int | None = None) -> int:
    """An integral number (``3`` or ``3.0``, not ``True`` or ``"3"``) within bounds."""
    parts = [f">= {ge}" if ge is not None else "", f"<= {le}" if le is not None else ""]
    allowed = "an integer" + (" " + " and ".join(p for p in parts if p) if any(parts) else "")
    if not _is_number(value) or not math.isfinite(float(value)) or float(value) != int(value):
        raise MsmillInputError(field, value, allowed)
    v = int(value)
    if (ge is not None and v < ge) or (le is not None and v > le):
        raise MsmillInputError(field, value, allowed)
    return v


def limit(value: float, field: str, name: str | None = None) -> None:
    """Reject ``value`` above the named resource limit :data:`LIMITS` ``[name]``.

    The environment variable ``MSMILL_LIMIT_<NAME>`` (e.g. ``MSMILL_LIMIT_SWEEP_POINTS=50000``) raises a
    limit for a user who means it; the error names it.
    """
    import os

    key = name or field.rsplit(".", 1)[-1]
    cap, what = LIMITS[key]
    env = f"MSMILL_LIMIT_{key.upper()}"
    if os.environ.get(env, "").strip():
        try:
            cap = int(float(os.environ[env]))
        except ValueError:
            raise MsmillInputError(env, os.environ[env], "an integer limit") from None
    if value > cap:
        raise MsmillInputError(field, value, f"at most {cap:,} ({what}; resource limit "
                               f"msmill.validate.LIMITS[{key!r}], raised by {env}=N)")


def one_of(value: Any, field: str, allowed: tuple[Any, ...]) -> Any:
    """``value`` if it is one of ``allowed``; else a one-line error listing them."""
    if value not in allowed:
        raise MsmillInputError(field, value, " or ".join(repr(k) for k in allowed))
    return value


def exclusive(field_a: str, a: Any, field_b: str, b: Any) -> None:
    """Reject giving both of two options that exclude each other."""
    if a is not None and b is not None:
        raise MsmillInputError(f"{field_a}/{field_b}", "both given", f"one of {field_a} or {field_b}, not both")


def user_path(path: str | Path, field: str) -> Path:
    """``path`` with ``~`` / ``~user`` expanded; a user without a home (``~0``) is a one-line error naming ``field``."""
    try:
        return Path(path).expanduser()
    except RuntimeError:  # pathlib: "Could not determine home directory"
        raise MsmillInputError(field, str(path), "a path whose ~user names a user with a home folder") from None


def existing_file(path: Any, field: str, kind: str = "file") -> Path:
    """An existing regular file (not a directory)."""
    if path is None or (isinstance(path, str) and not path.strip()):
        raise MsmillInputError(field, path, f"a path of an existing {kind}")
    if not isinstance(path, str | Path):
        raise MsmillInputError(field, type(path).__name__, f"a path of an existing {kind}")
    p = user_path(path, field)
    if p.is_dir():
        raise MsmillInputError(field, str(path), f"an existing {kind} (this is a directory)")
    if not p.is_file():
        raise MsmillInputError(field, str(path), f"an existing {kind}")
    return p


def existing_dir(path: Any, field: str, kind: str = "directory") -> Path:
    """An existing directory."""
    if not isinstance(path, str | Path) or not str(path).strip():
        raise MsmillInputError(field, path, f"a path of an existing {kind}")
    p = user_path(path, field)
    if not p.is_dir():
        raise MsmillInputError(field, str(path), f"an existing {kind}")
    return p


def read_text(path: Any, field: str, kind: str = "text file",
              max_bytes: int = MAX_TEXT_BYTES) -> str:
    """The UTF-8 text of an existing file no larger than ``max_bytes``."""
    p = existing_file(path, field, kind)
    size = p.stat().st_size
    if size > max_bytes:
        raise MsmillInputError(field, str(path), f"a {kind} of at most {max_bytes / 2**20:g} MiB "
                               f"(this one is {size / 2**20:.3g} MiB)")
    try:
        return p.read_bytes().decode("utf-8")
    except UnicodeDecodeError as exc:
        raise MsmillInputError(field, str(path), f"a UTF-8 {kind} (byte {exc.start} is not UTF-8)") from None
    except OSError as exc:
        raise MsmillInputError(field, str(path), f"a readable {kind} ({exc.strerror})") from None


def read_toml(path: Any, field: str, kind: str = "TOML file") -> dict[str, Any]:
    """Parse an existing UTF-8 TOML file; a syntax error is one line naming the file."""
    text = read_text(path, field, kind)
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise MsmillInputError(Path(path).name, str(exc).split("\n")[0], f"valid TOML ({kind})") from None


def read_csv(path: Any, field: str, kind: str = "CSV file") -> Any:
    """Read an existing CSV file (``#`` lines are comments) into a pandas DataFrame.

    Errors (not a file, not UTF-8, unparsable, no rows, more than
    ``LIMITS["csv_rows"]`` rows) are one line naming the file.
    """
    import pandas as pd

    p = existing_file(path, field, kind)
    try:
        frame = pd.read_csv(p, comment="#", skipinitialspace=True, encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise MsmillInputError(field, str(path), f"a UTF-8 {kind} (byte {exc.start} is not UTF-8)") from None
    except pd.errors.EmptyDataError:
        raise MsmillInputError(field, str(path), f"a {kind} with a header and rows (it is empty)") from None
    except (pd.errors.ParserError, ValueError, OSError) as exc:
        first = " ".join(str(exc).split())[:120]
        raise MsmillInputError(field, str(path), f"a readable {kind} ({first})") from None
    limit(len(frame), field, "csv_rows")
    frame.columns = [str(c).strip() for c in frame.columns]
    return frame


def sizes(values: Any, field: str, min_len: int = 1, unit: str = "mm") -> np.ndarray:
    """A 1-D array of finite, positive, strictly increasing sizes."""
    try:
        arr = np.asarray(values, dtype=float)
    except (TypeError, ValueError):
        raise MsmillInputError(field, values, f"a list of numbers ({unit})") from None
    if arr.ndim != 1 or arr.size < min_len:
        raise MsmillInputError(field, values, f"a 1-D list of at least {min_len} sizes in {unit}")
    if not np.all(np.isfinite(arr)) or np.any(arr <= 0):
        raise MsmillInputError(field, values, f"finite sizes > 0 {unit}")
    if arr.size > 1 and np.any(np.diff(arr) <= 0):
        raise MsmillInputError(field, values, "strictly increasing sizes")
    return arr


def passing(values: Any, field: str, n: int, tol: float = 1e-9) -> np.ndarray:
    """Cumulative % passing: ``n`` values in 0-100, non-decreasing.

    Values that all lie in [0, 1] with more than one distinct value are taken
    to be fractions, not percent, and rejected (say which). If the last value
    is below 100 % the caller treats the rest as an oversize class; this
    function warns (:class:`InputWarning`) saying how much.
    """
    try:
        p = np.asarray(values, dtype=float)
    except (TypeError, ValueError):
        raise MsmillInputError(field, values, "a list of numbers (% passing)") from None
    if p.shape != (n,):
        raise MsmillInputError(field, values, f"{n} values (one per size)")
    if not np.all(np.isfinite(p)) or np.any(p < -tol) or np.any(p > 100 + tol):
        raise MsmillInputError(field, values, "values within 0-100 %")
    if np.any(np.diff(p) < -tol):
        raise MsmillInputError(field, values, "values non-decreasing with size")
    if n > 1 and p[-1] <= 1.0 + tol and p[-1] > 0:
        raise MsmillInputError(field, values, "percent (0-100), not fractions: the last value "
                               f"is {p[-1]:g}; multiply by 100")
    if p[-1] < 100.0 - 1e-6:
        warnings.warn(f"{field} ends at {p[-1]:g} % passing, not 100 %: the remaining "
                      f"{100 - p[-1]:.3g} % is put in an oversize class above the last size",
                      InputWarning, stacklevel=3)
    return p


@contextlib.contextmanager
def pydantic_errors(prefix: str = "") -> Iterator[None]:
    """Turn a pydantic ``ValidationError`` raised in the block into one-line :class:`MsmillInputError`."""
    from pydantic import ValidationError

    from msmill.errors import from_validation_error

    try:
        yield
    except ValidationError as exc:
        raise from_validation_error(exc, prefix=prefix) from None


def reject_bools(model_cls: Any, data: Any) -> Any:
    """Body of a pydantic ``mode="before"`` model validator: no ``true``/``false`` for a number.

    pydantic reads ``true`` as 1 for a number field (``rate_tph = true`` would be
    1 t/h); this rejects a bool (or a list holding one) for any field whose
    annotation does not mention ``bool``.
    """
    if isinstance(data, dict):
        for key, v in data.items():
            f = model_cls.model_fields.get(key)
            items = v if isinstance(v, list) else [v]
            ann = str(f.annotation) if f is not None else ""
            if f is not None and "bool" not in ann and any(isinstance(x, bool) for x in items):
                what = "a number" if ("float" in ann or "int" in ann) else "a value"
                raise ValueError(f"{key} must be {what}, not true/false")
    return data
