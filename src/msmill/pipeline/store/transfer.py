"""Ingest run folders and exported documents into the store; export runs as JSON documents.

Ingest takes, recursively:

* run folders written by ``msmill dem run`` (``msmill.dem.mill.run.save_run``:
  ``statistics.json``, ``machine.toml``, ``run.toml``, Parquet tables) and
  folders written by ``msmill dem import`` (``statistics.json``,
  ``machine.toml``, ``import.toml``): the statistics are recorded, the raw
  tables referenced by path and SHA-256;
* export documents (``run-*.json``, ``"kind": "msmill_run"``) written by
  :func:`export_runs`.

A run is identified by :func:`msmill.pipeline.store.hashing.statistics_hash`,
so ingesting the same folder or document twice records it once.
"""

from __future__ import annotations

import json
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from msmill.errors import MsmillInputError
from msmill.machine import Machine
from msmill.pipeline.store.core import Store
from msmill.pipeline.store.hashing import (
    canonical_statistics,
    file_sha256,
    read_statistics,
    statistics_hash,
)

__all__ = ["EXPORT_KIND", "IngestResult", "export_runs", "ingest_paths"]

EXPORT_KIND = "msmill_run"
EXPORT_VERSION = 1


@dataclass(frozen=True)
class IngestResult:
    """What happened to one source: ``added``, ``exists`` or ``skipped`` (with the reason)."""

    path: str
    status: str
    run_id: int | None = None
    reason: str = ""


def _raw_files(folder: Path) -> list[dict[str, Any]]:
    files = sorted(p for p in folder.iterdir() if p.suffix in (".parquet", ".csv", ".vtu") and p.is_file())
    return [{"kind": p.stem, "path": str(p.resolve()), "sha256": file_sha256(p), "size_bytes": p.stat().st_size}
            for p in files]


def _ingest_folder(store: Store, folder: Path, allow_not_steady: bool) -> IngestResult:
    stats = read_statistics(folder / "statistics.json", source=str(folder / "statistics.json"))
    machine = Machine.from_toml(folder / "machine.toml")
    kw: dict[str, Any] = {"source": "ingest", "source_path": str(folder.resolve())}
    if (folder / "run.toml").exists():
        run_toml = tomllib.loads((folder / "run.toml").read_text(encoding="utf-8"))
        kw["run_settings"] = run_toml.get("run")
        kw["seed"] = int(run_toml.get("run", {}).get("seed", 0))
        kw["wall_s"] = run_toml.get("result", {}).get("wall_s")
    elif (folder / "import.toml").exists():
        kw["source"] = "import"
    return _record(store, stats, machine, folder, kw | {"raw_files": _raw_files(folder)}, allow_not_steady)


def _record(store: Store, stats: Any, machine: Machine, path: Path, kw: dict[str, Any],
            allow_not_steady: bool) -> IngestResult:
    try:
        run_id, created = store.record_run(stats, machine, allow_not_steady=allow_not_steady, **kw)
    except MsmillInputError as exc:
        if exc.field == "outcome":
            return IngestResult(str(path), "skipped", None, f"outcome {exc.value} (use --allow-not-steady)")
        raise
    return IngestResult(str(path), "added" if created else "exists", run_id)


def _ingest_document(store: Store, path: Path, doc: dict[str, Any], allow_not_steady: bool) -> IngestResult:
    if doc.get("format_version") != EXPORT_VERSION:
        raise MsmillInputError(f"{path.name}.format_version", doc.get("format_version"), str(EXPORT_VERSION))
    stats = read_statistics(doc["statistics"], source=path.name)
    machine = Machine.from_toml(doc["machine_toml"])
    r = doc.get("run", {})
    kw = {k: r.get(k) for k in ("source", "source_path", "seed", "run_settings", "outcome", "wall_s", "engine",
                                "package_version", "git_commit")}
    kw["seed"] = int(kw["seed"] or 0)
    kw["source"] = kw["source"] or "ingest"
    kw["raw_files"] = doc.get("raw_files", [])
    return _record(store, stats, machine, path, kw, allow_not_steady)


def _sources(path: Path) -> list[Path]:
    """Run folders and export documents under ``path`` (sorted, recursive)."""
    if path.is_file():
        return [path]
    if not path.is_dir():
        raise MsmillInputError("path", str(path), "an existing run folder, export folder or run-*.json file")
    if (path / "statistics.json").exists() and (path / "machine.toml").exists():
        return [path]
    found: list[Path] = []
    for child in sorted(path.iterdir()):
        if child.is_dir() or (child.suffix == ".json" and child.name.startswith("run-")):
            found.extend(_sources(child))
    return found


def ingest_paths(store: Store, paths: list[str | Path], allow_not_steady: bool = False) -> list[IngestResult]:
    """Ingest run folders and export documents (recursively); one result per source found."""
    out: list[IngestResult] = []
    for p in paths:
        for src in _sources(Path(p)):
            if src.is_dir():
                out.append(_ingest_folder(store, src, allow_not_steady))
                continue
            try:
                doc = json.loads(src.read_text(encoding="utf-8"))
            except json.JSONDecodeError as exc:
                raise MsmillInputError(str(src), f"line {exc.lineno}", "valid JSON") from None
            if not isinstance(doc, dict) or doc.get("kind") != EXPORT_KIND:
                out.append(IngestResult(str(src), "skipped", None, f"not a {EXPORT_KIND} document"))
                continue
            out.append(_ingest_document(store, src, doc, allow_not_steady))
    return out


def export_document(store: Store, run_id: int) -> dict[str, Any]:
    """The portable JSON document of one done run (what :func:`export_runs` writes)."""
    rec = store.run(run_id)
    keys = ("source", "source_path", "seed", "run_settings", "outcome", "wall_s", "engine", "package_version",
            "git_commit", "campaign", "mode")
    return {"kind": EXPORT_KIND, "format_version": EXPORT_VERSION, "content_hash": rec.content_hash,
            "machine_hash": rec.machine_hash, "machine_toml": store.machine(rec.machine_hash).to_toml(),
            "run": {k: getattr(rec, k) for k in keys}, "raw_files": store.raw_files(run_id),
            "statistics": canonical_statistics(store.statistics(run_id))}


def export_runs(store: Store, out_dir: str | Path, campaign: str | None = None) -> list[Path]:
    """Write one ``run-<hash>.json`` per done run (sorted keys, stable text for git); returns the paths.

    A document already in ``out_dir`` under another name whose run is one of those written (its
    statistics hash to a written run's under today's schema: it was exported before the statistics
    gained an optional field) is removed, so re-exporting an ingested folder never leaves a run twice.
    A run whose statistics equal a stored run's (``content_hash`` None: a bit-identical replica) is
    not written: ingesting its document would only find the run it repeats.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for rec in store.runs(campaign=campaign, status="done"):
        if rec.content_hash is None:
            continue
        doc = export_document(store, rec.id)
        p = out / f"run-{rec.content_hash[:16]}.json"
        p.write_text(json.dumps(doc, indent=1, sort_keys=True, default=str) + "\n", encoding="utf-8")
        written.append(p)
    _remove_renamed(out, written)
    return written


def _remove_renamed(out: Path, written: list[Path]) -> None:
    """Remove the documents in ``out`` that hold a run of ``written`` under an older hash."""
    hashes = {json.loads(p.read_text(encoding="utf-8"))["content_hash"] for p in written}
    names = {p.name for p in written}
    for old in sorted(out.glob("run-*.json")):
        if old.name in names:
            continue
        try:
            doc = json.loads(old.read_text(encoding="utf-8"))
            stats = read_statistics(doc["statistics"], source=old.name)
            h = statistics_hash(stats, doc["machine_hash"])
        except (json.JSONDecodeError, KeyError, TypeError, MsmillInputError):
            continue
        if h in hashes and h != doc.get("content_hash"):
            old.unlink()
