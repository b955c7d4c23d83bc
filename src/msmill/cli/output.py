"""Atomic output folders with a manifest, for every command that writes files.

A command builds all its files in a hidden staging folder and only then moves
them into place, so a failure midway leaves the previous output untouched and
no half-written set. Each committed folder holds ``msmill-manifest.json``: the
run id, the time, the msmill version, the command line, a hash of the inputs
and the name, size and SHA-256 of every file this run wrote. Files a previous
run listed in its manifest but this run did not write (e.g. plots after a
rerun with ``--no-plots``) are removed, so a stale file cannot pass for a
current one.

Usage::

    out = check_writable(folder, "--out")          # before any expensive work
    ...                                            # validate, compute
    with atomic_output(out, inputs=[run_file], settings={...}) as stage:
        (stage / "product.csv").write_bytes(data)  # write with any writer
    # committed here; on an exception nothing in ``out`` changed

Mechanics: if the folder does not exist, the staging folder is a hidden
sibling renamed into place in one ``os.rename``; if it exists, the staging
folder is hidden inside it and each file is moved with ``os.replace`` (atomic
per file), the old manifest having been removed first and the new one written
last, so the folder never carries a manifest that disagrees with its files.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import hashlib
import json
import os
import shutil
import sys
import tempfile
import uuid
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

from msmill._version import __version__
from msmill.errors import MsmillInputError
from msmill.validate import user_path

MANIFEST = "msmill-manifest.json"
_STAGE_PREFIX = ".msmill-stage-"


def check_writable(folder: str | Path, field: str = "--out") -> Path:
    """Check that ``folder`` is (or can be created as) a writable directory; return it.

    Probes by creating and removing a temporary directory in the folder or its
    nearest existing ancestor, so a read-only file system is caught before
    any work starts.
    """
    if not str(folder).strip():
        raise MsmillInputError(field, str(folder), "a folder path")
    p = user_path(folder, field)
    if p.exists() and not p.is_dir():
        raise MsmillInputError(field, str(folder), "a folder (this is an existing file)")
    probe = p
    while not probe.exists():
        probe = probe.parent
    if not probe.is_dir():
        raise MsmillInputError(field, str(folder), f"a folder path ({probe} is a file)")
    try:
        Path(tempfile.mkdtemp(dir=probe, prefix=_STAGE_PREFIX)).rmdir()
    except OSError as exc:
        raise MsmillInputError(field, str(folder), f"a writable folder ({exc.strerror} in {probe})") from None
    return p


def file_sha256(path: Path) -> str:
    """SHA-256 of a file's bytes (hex)."""
    h = hashlib.sha256()
    with path.open("rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def inputs_hash(inputs: Iterable[str | Path] = (), settings: dict[str, Any] | None = None) -> str:
    """SHA-256 over the bytes of the input files and the JSON of the settings (hex)."""
    h = hashlib.sha256()
    for p in inputs:
        q = Path(p)
        h.update(q.name.encode())
        h.update(bytes.fromhex(file_sha256(q)) if q.is_file() else b"<missing>")
    h.update(json.dumps(settings or {}, sort_keys=True, default=str).encode())
    return h.hexdigest()


def read_manifest(folder: str | Path) -> dict[str, Any] | None:
    """The manifest of an output folder, or ``None`` if it has none (or it is unreadable)."""
    try:
        data = json.loads((Path(folder) / MANIFEST).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) and isinstance(data.get("files"), dict) else None


def _manifest(stage: Path, inputs: list[Path], settings: dict[str, Any] | None,
              previous: dict[str, Any] | None) -> dict[str, Any]:
    files = {p.name: {"bytes": p.stat().st_size, "sha256": file_sha256(p)}
             for p in sorted(stage.iterdir()) if p.is_file() and p.name != MANIFEST}
    if previous is not None:  # update mode: keep the earlier run's entries not rewritten
        files = {**previous.get("files", {}), **files}
    return {
        "tool": "msmill", "version": __version__, "run_id": uuid.uuid4().hex,
        "created_utc": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
        "command": ["msmill", *sys.argv[1:]] if Path(sys.argv[0]).name != "pytest" else ["msmill"],
        "inputs": {str(p): file_sha256(p) for p in inputs if p.is_file()},
        "inputs_sha256": inputs_hash(inputs, settings), "settings": settings or {},
        "files": files,
    }


def _write_json(path: Path, data: dict[str, Any]) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(data, indent=2, default=str) + "\n", encoding="utf-8")
    os.replace(tmp, path)


@contextlib.contextmanager
def atomic_output(folder: str | Path, *, field: str = "--out", inputs: Iterable[str | Path] = (),
                  settings: dict[str, Any] | None = None, update: bool = False) -> Iterator[Path]:
    """Yield a staging folder; on normal exit move its files into ``folder`` with a manifest.

    Parameters
    ----------
    folder : path
        Output folder (created if missing, parents too).
    field : str
        Name of the option that gave the folder (for errors).
    inputs : iterable of path
        Input files whose bytes are hashed into the manifest.
    settings : dict, optional
        Settings (JSON-able) hashed into the manifest and stored in it.
    update : bool
        Add to an existing output set (e.g. recomputed statistics in a DEM run
        folder) instead of replacing it: files of the previous manifest that
        this run does not write are kept and stay listed.
    """
    out = check_writable(folder, field)
    inputs = [Path(p) for p in inputs]
    fresh = not out.exists()
    parent = out.parent if fresh else out
    parent.mkdir(parents=True, exist_ok=True)
    stage = Path(tempfile.mkdtemp(dir=parent, prefix=_STAGE_PREFIX if not fresh else f".{out.name}{_STAGE_PREFIX}"))
    os.chmod(stage, 0o777 & ~_umask())  # mkdtemp makes 0700: the folder follows the user's umask
    try:
        yield stage
        if any(p.is_dir() for p in stage.iterdir()):
            raise MsmillInputError("output", "a sub-folder", "plain files in the output folder")
        previous = read_manifest(out) if not fresh else None
        manifest = _manifest(stage, inputs, settings, previous if update else None)
        if fresh and not out.exists():
            _write_json(stage / MANIFEST, manifest)
            os.rename(stage, out)
            return
        (out / MANIFEST).unlink(missing_ok=True)
        for p in stage.iterdir():
            os.replace(p, out / p.name)
        if previous is not None and not update:
            for name in set(previous["files"]) - set(manifest["files"]):
                if Path(name).name == name:  # never follow a path out of the folder
                    (out / name).unlink(missing_ok=True)
        _write_json(out / MANIFEST, manifest)
    finally:
        shutil.rmtree(stage, ignore_errors=True)


def _umask() -> int:
    """The process's umask (read by setting it and setting it back)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def atomic_write_bytes(path: str | Path, data: bytes, field: str = "--out") -> Path:
    """Write one file atomically: a hidden temporary file beside it, then ``os.replace``."""
    p = user_path(path, field)
    if p.is_dir():
        raise MsmillInputError(field, str(path), "a file path (this is a directory)")
    check_writable(p.parent if str(p.parent) else Path("."), field)
    p.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=p.parent, prefix=f".{p.name}.", suffix=".tmp")
    try:
        os.fchmod(fd, 0o666 & ~_umask())  # mkstemp makes 0600: the file follows the user's umask
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
        os.replace(tmp, p)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return p
