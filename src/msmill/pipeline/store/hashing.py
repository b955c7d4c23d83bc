"""Content hashes and the canonical statistics document of the store."""

from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path
from typing import Any

from msmill.errors import MsmillInputError
from msmill.machine import Machine
from msmill.pipeline.store.schema import OUTCOMES
from msmill.stageparams import DesignPoint, RunStatistics

__all__ = ["canonical_statistics", "design_hash", "file_sha256", "machine_hash", "outcome_of", "read_statistics",
           "statistics_hash"]


def _sha256(text: str) -> str:
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def _canonical_json(obj: Any) -> str:
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), allow_nan=False)


def machine_hash(machine: Machine) -> str:
    """SHA-256 of the machine's validated fields (independent of TOML formatting)."""
    return _sha256(_canonical_json(machine.model_dump(mode="json")))


def canonical_statistics(stats: RunStatistics | dict[str, Any]) -> dict[str, Any]:
    """The statistics as a plain JSON dict; standard errors that are NaN (no estimate) are left out.

    ``RunStatistics`` serialises NaN as ``null``, which it cannot read back, so
    the store keeps only finite standard errors.
    """
    d = json.loads(stats.model_dump_json()) if isinstance(stats, RunStatistics) else json.loads(json.dumps(stats))
    for st in d.get("stages", []):
        se = st.get("sampling_error") or {}
        st["sampling_error"] = {k: v for k, v in se.items() if isinstance(v, int | float) and math.isfinite(v)}
    return d


def read_statistics(data: dict[str, Any] | str | Path, source: str = "statistics") -> RunStatistics:
    """Validate a statistics document (dict, JSON text or file) after :func:`canonical_statistics`."""
    if not isinstance(data, dict):
        p = Path(data) if not str(data).lstrip().startswith("{") else None
        try:
            data = json.loads(p.read_text(encoding="utf-8") if p else str(data))
        except json.JSONDecodeError as exc:
            raise MsmillInputError(source, f"line {exc.lineno}", "valid JSON") from None
    return RunStatistics.from_dict(canonical_statistics(data), source=source)


def statistics_hash(stats: RunStatistics | dict[str, Any], machine_sha: str) -> str:
    """Content hash of a run: its statistics (without provenance) and its machine.

    Recomputing the statistics of the same raw data gives the same hash, so a
    run ingested twice (or exported and ingested back) is recorded once.
    """
    d = canonical_statistics(stats)
    d.pop("provenance", None)
    return _sha256(_canonical_json({"machine": machine_sha, "statistics": d}))


def outcome_of(stats: RunStatistics) -> str:
    """Outcome of a finished run: the statistics' ``outcome`` (set by the run protocol, issue 20), else
    ``provenance["outcome"]``, else steady/not_steady by whether a steady-state time was found."""
    for out in (getattr(stats, "outcome", None), stats.provenance.get("outcome")):
        if out in OUTCOMES:
            return str(out)
    return "steady" if stats.steady_state_time_s is not None else "not_steady"


def design_hash(machine_sha: str, d: DesignPoint) -> str:
    return _sha256(_canonical_json({"machine": machine_sha, "design": d.model_dump(mode="json")}))


def file_sha256(path: str | Path) -> str:
    """SHA-256 of a file's bytes (read in 1 MiB blocks)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()
