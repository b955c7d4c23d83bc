"""A trained surrogate as one versioned JSON document (no pickles).

The file holds everything needed to rebuild the surrogate without
re-optimising: the design space, the target layout, the training data
(design points, targets, sampling variances, run ids and the runs' statistics
for scoring), the speed recipe, and every target's kernel hyperparameters as
plain floats; plus provenance (store query, runs used, accuracy metrics,
package versions, date). Loading refits each GP with its stored
hyperparameters and no optimiser, which repeats the same floating-point
operations as the original fit's final step, so predictions are bit-for-bit
identical (floats are written with ``repr`` precision).

Layout (``schema_version`` 1)::

    {"schema_version": 1, "kind": "msmill_surrogate",
     "design_space": {...}, "layout": {...}, "speed_factors": [...],
     "training": {"X": [[...]], "Y": [[...]], "noise_var": [[...]], "run_ids": [...],
                  "runs": [RunStatistics, ...]},
     "gp": {"hyperparameters": [{"c32", "ls32", "c52", "ls52", "white"}, ...]},
     "filling_curves": null | "table",
     "provenance": {...}}

``filling_curves`` (:attr:`StageSurrogate.filling_curves`) says where the providers built on the file
take filling curves from; a file without it takes the runs' own.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import os
import platform
import re
from pathlib import Path
from typing import Any

import numpy as np

from msmill.errors import MsmillInputError
from msmill.surrogate.gp import SurrogateGP
from msmill.surrogate.space import DesignSpace
from msmill.surrogate.stage_model import FILLING_CURVES, StageSurrogate
from msmill.surrogate.targets import StoredRuns, TargetLayout, TrainingSet

SCHEMA_VERSION = 1
KIND = "msmill_surrogate"


def package_versions() -> dict[str, str]:
    """Versions of msmill and the numerical libraries the surrogate depends on."""
    from importlib.metadata import PackageNotFoundError, version

    out = {"python": platform.python_version()}
    for pkg in ("msmill", "numpy", "scipy", "scikit-learn"):
        try:
            out[pkg] = version(pkg)
        except PackageNotFoundError:  # pragma: no cover
            out[pkg] = "unknown"
    return out


def to_dict(model: StageSurrogate, provenance: dict[str, Any] | None = None) -> dict[str, Any]:
    """The JSON-ready document of a fitted surrogate."""
    ts, gp = model.training_, model.gp_
    prov = {"date_utc": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
            "package_versions": package_versions(), "n_runs": ts.n_runs, "runs_used": list(ts.run_ids),
            **(provenance or {})}
    return {
        "schema_version": SCHEMA_VERSION, "kind": KIND,
        "design_space": model.design_space.to_dict(),
        "layout": ts.layout.to_dict(),
        "speed_factors": [float(v) for v in ts.speed_factors],
        "training": {"X": ts.X.tolist(), "Y": ts.Y.tolist(), "noise_var": ts.noise_var.tolist(),
                     "run_ids": list(ts.run_ids),
                     "runs": [json.loads(r.model_dump_json()) for r in ts.runs]},
        "gp": {"kernel": "C*Matern(ARD,nu=1.5) + C*Matern(ARD,nu=2.5) + White",
               "hyperparameters": gp.hyperparameters()},
        "filling_curves": model.filling_curves,
        "provenance": prov,
        **_correction_doc(model),
    }


def _correction_doc(model: StageSurrogate) -> dict[str, Any]:
    bias = getattr(model, "slice_to_full_", None)
    return {"slice_to_full": bias.to_dict()} if bias is not None else {}


def write_document(doc: dict[str, Any], path: str | Path) -> Path:
    """Write a surrogate document to ``path`` as compact JSON, atomically (temporary file, then rename).

    Compact because the shipped surrogates are package data: indentation added a third to the file
    (6.0 MB -> 4.4 MB for the 121-run default); floats keep ``repr`` precision either way.
    """
    p = Path(path)
    tmp = p.with_name(p.name + ".tmp")
    tmp.write_text(json.dumps(doc, separators=(",", ":")) + "\n", encoding="utf-8")
    tmp.replace(p)
    return p


def save(model: StageSurrogate, path: str | Path, provenance: dict[str, Any] | None = None) -> Path:
    """Write the surrogate to ``path`` (JSON, :func:`write_document`); returns the path."""
    return write_document(to_dict(model, provenance), path)


def from_dict(doc: dict[str, Any], source: str = "surrogate", factors_key: str | None = None) -> StageSurrogate:
    """Rebuild a fitted surrogate from its document (no re-optimisation).

    ``factors_key``: read the GP's factorisations from the user's cache under this key instead of
    refactorising (and write them there when missing): :func:`load` keys them by the file's bytes.
    """
    if not isinstance(doc, dict) or doc.get("kind") != KIND:
        raise MsmillInputError(f"{source}.kind", doc.get("kind") if isinstance(doc, dict) else None, KIND)
    if doc.get("schema_version") != SCHEMA_VERSION:
        raise MsmillInputError(f"{source}.schema_version", doc.get("schema_version"), str(SCHEMA_VERSION))
    try:
        space = DesignSpace.from_dict(doc["design_space"])
        layout = TargetLayout.from_dict(doc["layout"])
        tr = doc["training"]
        X, Y, nv = (np.array(tr[k], dtype=float) for k in ("X", "Y", "noise_var"))
        runs = StoredRuns(list(tr.get("runs", [])), source=f"{source}.training.runs")
        hyper = doc["gp"]["hyperparameters"]
    except (KeyError, TypeError) as exc:
        raise MsmillInputError(f"{source}", f"missing {exc}", "a complete msmill surrogate document") from None
    if Y.shape[1] != layout.n_targets or len(hyper) != layout.n_targets:
        raise MsmillInputError(f"{source}.training.Y", f"{Y.shape[1]} targets", f"{layout.n_targets}")
    ts = TrainingSet(X, Y, nv, layout, np.array(doc["speed_factors"], dtype=float), tuple(tr["run_ids"]), runs)
    gp = None
    factors = _read_factors(factors_key) if factors_key else None
    if factors is not None:
        try:
            gp = SurrogateGP.from_factors(X, Y, nv, hyper, factors, space)
        except MsmillInputError:  # a cache of another shape: made again below
            gp = None
    if gp is None:
        gp = SurrogateGP.rebuild(X, Y, nv, hyper, space)
        if factors_key:
            _write_factors(factors_key, gp.factors())
    filling = doc.get("filling_curves")
    if filling not in FILLING_CURVES:
        raise MsmillInputError(f"{source}.filling_curves", filling, " or ".join(map(str, FILLING_CURVES)))
    model = StageSurrogate(space, filling_curves=filling, n_levels=layout.n_levels)
    model._set(ts, gp)
    model.provenance_ = dict(doc.get("provenance", {}))
    if doc.get("slice_to_full") is not None:
        from msmill.surrogate.fidelity import SliceToFullBias

        model.slice_to_full_ = SliceToFullBias.from_dict(doc["slice_to_full"], layout.n_targets)
    return model


def load(path: str | Path, cache: bool = True) -> StageSurrogate:
    """Read a surrogate file written by :func:`save`; errors are one line.

    ``cache``: keep the GP's factorisations (what prediction needs beyond the file:
    :meth:`SurrogateGP.factors`, about 27 MB for the shipped surrogate) in the user's cache folder
    (``$XDG_CACHE_HOME/msmill/surrogates``, ``~/.cache`` by default), keyed by the file's SHA-256 and
    the numerical libraries' versions, so that a later load reads them (milliseconds) instead of
    refactorising every target (seconds); the predictions are bit for bit the same.
    """
    p = Path(path)
    if not p.is_file():
        raise MsmillInputError("surrogate", str(p), "an existing surrogate JSON file")
    raw = p.read_bytes()
    try:
        doc = json.loads(raw.decode("utf-8"))
    except UnicodeDecodeError:
        raise MsmillInputError(str(p), "not UTF-8 text", "a surrogate JSON file") from None
    except json.JSONDecodeError as exc:
        raise MsmillInputError(str(p), f"line {exc.lineno}", "valid JSON") from None
    return from_dict(doc, source=p.name, factors_key=factors_key(raw) if cache else None)


def factors_key(raw: bytes) -> str:
    """Cache key of a surrogate file's factorisations: its bytes and the libraries that factorise."""
    # the versions, not the libraries themselves: importing scikit-learn costs about a second
    from importlib.metadata import version

    h = hashlib.sha256(raw)
    h.update(" ".join(f"{d} {version(d)}" for d in ("numpy", "scipy", "scikit-learn")).encode())
    return h.hexdigest()[:32]


def factors_cache_dir() -> Path:
    """Folder of cached factorisations (``$XDG_CACHE_HOME/msmill/surrogates``)."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "msmill" / "surrogates"


def _read_factors(key: str) -> dict[str, np.ndarray] | None:
    f = factors_cache_dir() / f"{key}.npz"
    try:
        with np.load(f, allow_pickle=False) as z:
            return {k: z[k] for k in ("alpha", "L_inv")}
    except (OSError, KeyError, ValueError):  # missing, unreadable or damaged: refactorise
        return None


def _write_factors(key: str, factors: dict[str, np.ndarray]) -> None:
    d = factors_cache_dir()
    try:
        d.mkdir(parents=True, exist_ok=True)
        tmp = d / f".{key}.{os.getpid()}.npz"
        np.savez(tmp, **factors)
        os.replace(tmp, d / f"{key}.npz")
    except OSError:  # a read-only home: no cache, every load refactorises
        pass


def is_surrogate_file(path: str | Path) -> bool:
    """True when ``path`` is a JSON file whose ``kind`` is the surrogate's."""
    p = Path(path)
    if p.suffix.lower() != ".json" or not p.is_file():
        return False
    with p.open("rb") as fh:
        head = fh.read(4096).decode("utf-8", errors="replace")  # a binary file is not one (callers say why)
    return re.search(rf'"kind"\s*:\s*"{KIND}"', head) is not None  # compact or indented
