"""Where a result came from: the git commit of the source tree (for the provenance of every artefact).

One helper for the package, its scripts and benchmarks (issue 43): the commit of the checkout the
running msmill was imported from, and whether given paths have uncommitted changes.
"""

from __future__ import annotations

import subprocess
from collections.abc import Iterable
from pathlib import Path

_HERE = Path(__file__).resolve().parent


def _git(*args: str) -> str | None:
    try:
        out = subprocess.run(["git", "-C", str(_HERE), *args], capture_output=True, text=True, timeout=10,
                             check=False)
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout if out.returncode == 0 else None


def git_commit(short: bool = False) -> str | None:
    """HEAD of the checkout msmill runs from (``short``: abbreviated); None outside a git checkout."""
    out = _git("rev-parse", *(["--short"] if short else []), "HEAD")
    return (out or "").strip() or None


def git_uncommitted(paths: Iterable[str | Path]) -> bool:
    """Whether any of ``paths`` has changes not committed (False outside a git checkout)."""
    out = _git("status", "--porcelain", "--", *(str(Path(p).resolve()) for p in paths))
    return bool((out or "").strip())
