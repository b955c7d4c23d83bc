"""Reading a saved DEM run folder (``msmill dem run --out DIR``, :func:`msmill.dem.mill.run.save_run`).

Its own module so that the run loop and the warm start both read saved runs without importing each
other (issue 43).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pandas as pd

from msmill.errors import MsmillInputError
from msmill.machine import Machine

__all__ = ["load_raw"]


def load_raw(run_dir: str | Path) -> dict[str, Any]:
    """Read the raw tables and settings a :func:`save_run` directory holds."""
    d = Path(run_dir)
    if not d.is_dir():
        raise MsmillInputError("run_dir", str(d), "an existing directory written by 'msmill dem run'")
    if not (d / "events.parquet").exists():
        raise MsmillInputError("run_dir", str(d), "a directory written by 'msmill dem run' (events.parquet missing)")
    from msmill.validate import read_toml

    settings = read_toml(d / "run.toml", "run_dir/run.toml", "run.toml of a DEM run")
    for key in ("design", "result", "feed", "rock"):
        if not isinstance(settings.get(key), dict):
            raise MsmillInputError(f"run.toml.{key}", settings.get(key), "a table written by 'msmill dem run'")
    raw: dict[str, Any] = {"settings": settings, "machine": Machine.from_toml(d / "machine.toml")}
    for name in ("events", "removed", "timeseries", "snapshots"):
        try:
            raw[name] = pd.read_parquet(d / f"{name}.parquet")
        except Exception as exc:  # pyarrow raises many types for a damaged file
            raise MsmillInputError(f"{name}.parquet", str(d / f"{name}.parquet"),
                                   f"a readable Parquet file written by 'msmill dem run' ({type(exc).__name__})") from None
    return raw
