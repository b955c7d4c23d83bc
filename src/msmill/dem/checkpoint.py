"""Checkpoints of a DEM run: its complete state on disk, written atomically, read back to resume.

A checkpoint directory holds

* ``state.pkl``: a JSON-able *header* (format, code digest, the run's inputs,
  time accounting) followed by the pickled state (the scene with its
  :class:`msmill.dem.Simulation`, the run loop's own state);
* ``seg/``: segments of the state's *append-only lists* (finished events,
  removed particles, time series, snapshots). A list named in ``append_only``
  is pickled by reference; each write adds one segment with the items since
  the last write, so a checkpoint costs what the run added since the last one,
  not what it holds.

Every file is written to a temporary name, flushed to disk and renamed, and
``state.pkl`` last: a kill at any moment leaves the previous checkpoint
whole (segments it does not list are ignored and removed by the next write).

Checkpoints are pickles: load only your own (like LAMMPS restart files, they
are a run's private state, not an exchange format).
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import pickle
import shutil
from collections.abc import Callable
from importlib import resources
from pathlib import Path
from typing import Any

from msmill.errors import MsmillInputError

FORMAT = 1
STATE = "state.pkl"
SEGMENTS = "seg"

#: modules whose code decides a run's trajectory and when it stops (engine, mill scene and run loop,
#: statistics behind the adaptive window, steady-state test, machine): a checkpoint written by other
#: code of these is refused. Other modules (model, CLI, docs) may change under a long run.
TRAJECTORY_CODE = ("dem", "steadystate.py", "machine.py", "stageparams.py", "distributions.py", "sampling.py")


def code_digest() -> str:
    """SHA-256 over the source of :data:`TRAJECTORY_CODE` (first 16 hex digits)."""
    root = resources.files("msmill")
    h = hashlib.sha256()
    for name in TRAJECTORY_CODE:
        node = Path(str(root / name))
        files = sorted(node.rglob("*.py")) if node.is_dir() else [node]
        for f in files:
            h.update(str(f.relative_to(Path(str(root)))).encode())
            h.update(f.read_bytes())
    return h.hexdigest()[:16]


def _write_atomic(path: Path, write: Callable[[io.BufferedWriter], None]) -> None:
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as f:
        write(f)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


class _Pickler(pickle.Pickler):
    def __init__(self, file: Any, refs: dict[int, str]) -> None:
        super().__init__(file, protocol=pickle.HIGHEST_PROTOCOL)
        self._refs = refs

    def persistent_id(self, obj: Any) -> Any:
        if type(obj) is list:
            name = self._refs.get(id(obj))
            if name is not None:
                return ("append_only", name)
        return None


class _Unpickler(pickle.Unpickler):
    def __init__(self, file: Any, lists: dict[str, list]) -> None:
        super().__init__(file)
        self._lists = lists

    def persistent_load(self, pid: Any) -> Any:
        kind, name = pid
        if kind != "append_only" or name not in self._lists:
            raise pickle.UnpicklingError(f"unknown reference {pid!r}")
        return self._lists[name]


class CheckpointWriter:
    """Writes the checkpoints of one run into ``directory``.

    Parameters
    ----------
    directory : path
        Created if missing.
    segments : dict, optional
        Segments already on disk per append-only list (from :func:`read_checkpoint`
        of the checkpoint a run resumed from): ``{name: [(file, n_items), ...]}``.
    """

    def __init__(self, directory: str | Path, segments: dict[str, list[tuple[str, int]]] | None = None) -> None:
        self.directory = Path(directory)
        self.segments: dict[str, list[tuple[str, int]]] = {k: list(v) for k, v in (segments or {}).items()}
        self.writes = 0

    def write(self, header: dict[str, Any], state: Any, append_only: dict[str, list]) -> Path:
        """Write one checkpoint: new list segments first, then the header and state; returns ``state.pkl``."""
        seg_dir = self.directory / SEGMENTS
        seg_dir.mkdir(parents=True, exist_ok=True)
        for name, items in append_only.items():
            have = self.segments.setdefault(name, [])
            done = sum(n for _f, n in have)
            if len(items) < done:
                raise RuntimeError(f"append-only list {name!r} shrank from {done} to {len(items)} items")
            if len(items) > done:
                fname = f"{name}.{done:09d}-{len(items):09d}.pkl"
                new = items[done:]
                _write_atomic(seg_dir / fname, lambda f, new=new: pickle.dump(new, f, pickle.HIGHEST_PROTOCOL))
                have.append((fname, len(items) - done))
        head = {**header, "format": FORMAT, "segments": self.segments}
        refs = {id(items): name for name, items in append_only.items()}

        def dump(f: io.BufferedWriter) -> None:
            pickle.dump(head, f, pickle.HIGHEST_PROTOCOL)
            _Pickler(f, refs).dump(state)

        _write_atomic(self.directory / STATE, dump)
        keep = {fname for segs in self.segments.values() for fname, _n in segs}
        for p in seg_dir.iterdir():  # segments of a write that was cut off before its state file
            if p.name not in keep:
                p.unlink(missing_ok=True)
        self.writes += 1
        return self.directory / STATE


def has_checkpoint(directory: str | Path) -> bool:
    """Whether ``directory`` holds a checkpoint (a complete ``state.pkl``)."""
    return (Path(directory) / STATE).is_file()


def read_header(directory: str | Path) -> dict[str, Any]:
    """The header of the checkpoint in ``directory`` (the state is not read)."""
    path = Path(directory) / STATE
    if not path.is_file():
        raise MsmillInputError("checkpoint", str(directory), "a directory holding a checkpoint (state.pkl)")
    try:
        with open(path, "rb") as f:
            head = pickle.load(f)
    except Exception as exc:  # a damaged file: pickle raises many types
        raise MsmillInputError("checkpoint", str(path), f"a readable checkpoint ({type(exc).__name__})") from None
    if not isinstance(head, dict) or head.get("format") != FORMAT:
        raise MsmillInputError("checkpoint", str(path), f"a checkpoint of format {FORMAT}")
    return head


def read_checkpoint(directory: str | Path) -> tuple[dict[str, Any], Any]:
    """The header and the state of the checkpoint in ``directory`` (append-only lists reassembled)."""
    d = Path(directory)
    head = read_header(d)
    lists: dict[str, list] = {}
    try:
        for name, segs in head["segments"].items():
            items: list = []
            for fname, n in segs:
                with open(d / SEGMENTS / fname, "rb") as f:
                    part = pickle.load(f)
                if len(part) != n:
                    raise ValueError(f"segment {fname} holds {len(part)} items, not {n}")
                items.extend(part)
            lists[name] = items
        with open(d / STATE, "rb") as f:
            pickle.load(f)  # the header
            state = _Unpickler(f, lists).load()
    except (OSError, ValueError, pickle.UnpicklingError, EOFError) as exc:
        raise MsmillInputError("checkpoint", str(d), f"a complete checkpoint ({exc})") from None
    return head, state


def remove_checkpoint(directory: str | Path) -> None:
    """Delete a checkpoint directory (after the run's results are safely written)."""
    d = Path(directory)
    if has_checkpoint(d) or (d / SEGMENTS).is_dir():
        shutil.rmtree(d, ignore_errors=True)


def first_difference(a: dict[str, Any], b: dict[str, Any], prefix: str = "") -> str | None:
    """The first key (dotted path) at which two JSON-like dicts differ, with both values; None if equal."""
    for k in sorted(set(a) | set(b)):
        va, vb = a.get(k, "<missing>"), b.get(k, "<missing>")
        if isinstance(va, dict) and isinstance(vb, dict):
            d = first_difference(va, vb, f"{prefix}{k}.")
            if d is not None:
                return d
        elif json.dumps(va, sort_keys=True, default=str) != json.dumps(vb, sort_keys=True, default=str):
            return f"{prefix}{k}: {va!r} here, {vb!r} in the checkpoint"
    return None
