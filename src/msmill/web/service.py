"""Predictions for the web app and HTTP API (no physics here: it calls :mod:`msmill.model`).

A request has the same fields as a run file (:mod:`msmill.model.runfile`),
given as JSON, plus an optional ``attachments`` table holding the text of
uploaded files, by kind:

``feed_csv``
    a feed PSD in the ``msmill psd`` CSV layout (columns ``size_mm``,
    ``passing_pct``); it replaces ``feed.size_mm``/``passing_pct``.
``ore_toml``
    an ore file (``msmill.ore.Ore.from_toml``); it replaces ``ore.name``.
``stage_parameters_json``
    a stage-parameter table or run-statistics file.
``machine_toml``
    a machine file.

A request cannot name files on the server: ``machine.file``,
``stage_parameters.file`` and ``ore.file`` accept only the shipped defaults
(``"default"``) or come from attachments. The run file is validated by the
same code as ``msmill predict``; so are the limits on anything that allocates
by a user's number.

Built mills are cached (LRU) by everything but the feed and the operating
point, so moving a slider re-runs only the expected-value steady state and the
dynamics at the new point.
"""

from __future__ import annotations

import hashlib
import io
import json
import math
import tempfile
import threading
import warnings
from collections import OrderedDict
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import tomli_w

from msmill.errors import MsmillInputError

ATTACHMENT_KINDS = ("feed_csv", "ore_toml", "stage_parameters_json", "machine_toml")
MAX_ATTACHMENT_CHARS = 200_000
_MILL_CACHE_SIZE = 16


def _finite(x: Any) -> Any:
    """A JSON-safe value: NaN and infinities become ``None``."""
    if isinstance(x, float | np.floating):
        return float(x) if math.isfinite(x) else None
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, np.bool_):
        return bool(x)
    return x


def _records(df: pd.DataFrame) -> list[dict[str, Any]]:
    return [{k: _finite(v) for k, v in row.items()} for row in df.to_dict(orient="records")]


def _strip_attachments(data: dict[str, Any]) -> tuple[dict[str, Any], dict[str, str]]:
    if not isinstance(data, dict):
        raise MsmillInputError("request", type(data).__name__, "a JSON object with run-file sections")
    body = {k: v for k, v in data.items() if k != "attachments"}
    att = data.get("attachments") or {}
    if not isinstance(att, dict):
        raise MsmillInputError("request.attachments", type(att).__name__, "an object of file texts by kind")
    for kind, text in att.items():
        if kind not in ATTACHMENT_KINDS:
            raise MsmillInputError(f"request.attachments.{kind}", kind, f"one of {', '.join(ATTACHMENT_KINDS)}")
        if not isinstance(text, str):
            raise MsmillInputError(f"request.attachments.{kind}", type(text).__name__, "the file's text")
        if len(text) > MAX_ATTACHMENT_CHARS:
            raise MsmillInputError(f"request.attachments.{kind}", f"{len(text)} characters",
                                   f"at most {MAX_ATTACHMENT_CHARS} characters")
    return body, att


def _no_server_paths(body: dict[str, Any]) -> None:
    for section, key in (("machine", "file"), ("stage_parameters", "file"), ("ore", "file")):
        sec = body.get(section)
        if isinstance(sec, dict) and key in sec and sec[key] not in (None, "default", "table"):
            raise MsmillInputError(f"request.{section}.{key}", sec[key],
                                   "'default' (upload a file as an attachment instead of naming a server path)")


def _feed_from_csv(text: str) -> tuple[list[float], list[float]]:
    """Size and passing columns of an uploaded feed CSV, validated as ``msmill psd`` reads it."""
    from msmill.psd import PSD

    field = "request.attachments.feed_csv"
    try:
        frame = pd.read_csv(io.StringIO(text), comment="#", skipinitialspace=True)
    except (pd.errors.ParserError, pd.errors.EmptyDataError) as exc:
        raise MsmillInputError(field, str(exc).splitlines()[0] if str(exc) else "empty",
                               "a CSV with columns size_mm, passing_pct") from None
    frame.columns = [str(c).strip() for c in frame.columns]
    try:
        PSD.from_frame(frame)
    except MsmillInputError as exc:
        raise MsmillInputError(f"{field}.{exc.field}", exc.value, exc.allowed) from None
    df = frame[["size_mm", "passing_pct"]].astype(float).sort_values("size_mm", kind="stable")
    return df["size_mm"].tolist(), df["passing_pct"].tolist()


def _materialise(body: dict[str, Any], att: dict[str, str], folder: Path) -> dict[str, Any]:
    """Put attachments into ``folder`` and point the run-file sections at them."""
    body = json.loads(json.dumps(body))  # deep copy of plain JSON
    if "feed_csv" in att:
        size, passing = _feed_from_csv(att["feed_csv"])
        feed = dict(body.get("feed") or {})
        feed.pop("rosin_rammler", None)
        body["feed"] = {**feed, "size_mm": size, "passing_pct": passing}
    files = {"ore_toml": ("ore", "ore.toml"), "stage_parameters_json": ("stage_parameters", "stage_parameters.json"),
             "machine_toml": ("machine", "machine.toml")}
    for kind, (section, fname) in files.items():
        if kind in att:
            (folder / fname).write_text(att[kind], encoding="utf-8")
            sec = dict(body.get(section) or {})
            sec["file"] = fname
            if section == "ore":
                sec.pop("name", None)
            body[section] = sec
    return body


def _cache_key(rf: Any, att: dict[str, str]) -> str:
    dump = rf.model_dump(mode="json", exclude={"feed", "operating", "title", "output"})
    dump["passing_sizes_mm"] = rf.output.passing_sizes_mm
    dump["files"] = {k: hashlib.sha256(v.encode()).hexdigest() for k, v in att.items() if k != "feed_csv"}
    return json.dumps(dump, sort_keys=True)


class PredictionService:
    """Validate requests, build (cached) mills and serialise predictions."""

    def __init__(self, cache_size: int = _MILL_CACHE_SIZE) -> None:
        self._cache: OrderedDict[str, Any] = OrderedDict()
        self._cache_size = cache_size
        self._lock = threading.Lock()

    def run_file(self, data: dict[str, Any], folder: Path) -> tuple[Any, dict[str, str], dict[str, Any]]:
        """Validate a request: ``(RunFile, attachments, materialised body)``; raises MsmillInputError.

        Attached files are written to ``folder`` (the request's own temporary folder, removed with it).
        """
        from msmill.model.runfile import RunFile

        body, att = _strip_attachments(data)
        _no_server_paths(body)
        full = _materialise(body, att, folder)
        return RunFile.from_mapping(full, name="request", base_dir=folder), att, full

    def _mill(self, rf: Any, att: dict[str, str]) -> tuple[Any, Any, Any]:
        key = _cache_key(rf, att)
        feed = rf.feed_psd()
        op = rf.operating_point()
        mill = self._cache.get(key)
        if mill is None:
            mill, feed, op = rf.build()
            self._cache[key] = mill
            while len(self._cache) > self._cache_size:
                self._cache.popitem(last=False)
        else:
            self._cache.move_to_end(key)
            op.stage_speeds(mill.provider.n_stages)  # same check as RunFile.build
        return mill, feed, op

    def warm(self) -> float:
        """Build and run the page's default prediction once (the mill, its provider and caches), so that the
        first request costs what later ones do; returns the seconds it took."""
        import time

        t0 = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            self.predict(default_request())
        return time.perf_counter() - t0

    def predict(self, data: dict[str, Any]) -> dict[str, Any]:
        """Predict a request and return the JSON-ready response (see :func:`result_payload`)."""
        # the request's files live only as long as the request, also when it fails
        with tempfile.TemporaryDirectory(prefix="msmill-web-") as tmp:
            rf, att, body = self.run_file(data, Path(tmp))
            with self._lock, warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                mill, feed, op = self._mill(rf, att)
                result = mill.run(feed, op)
        messages = list(dict.fromkeys(str(w.message) for w in caught))
        payload = result_payload(result)
        payload["warnings"] = messages
        payload["run_file_toml"] = run_file_text(body, att)
        payload["title"] = rf.title
        return payload


def result_payload(result: Any) -> dict[str, Any]:
    """A :class:`msmill.model.result.MillResult` as plain JSON (summary, PSD table, stages, series)."""
    summary = {k: _finite(v) for k, v in result.summary().items()}
    psd = result.psd_table.copy()
    for col, mask in (("extrapolated", result.extrapolated_classes), ("thin_data", result.thin_data_classes)):
        psd[col] = np.zeros(len(psd), dtype=bool) if mask is None else np.asarray(mask, dtype=bool)
    out: dict[str, Any] = {
        "summary": summary,
        "passing_pct": [{"size_mm": float(s), "passing_pct": _finite(v)} for s, v in result.passing_pct.items()],
        "psd": _records(psd),
        "stages": _records(result.stages),
        "timeseries": _records(result.timeseries),
        "notes": list(result.notes),
        "solver": result.solver,
        "submodels": dict(result.submodels),
    }
    band = {k: getattr(result, k) for k in ("p80_band_mm",) if getattr(result, k, None) is not None}
    if band:
        out["band"] = {k: [_finite(x) for x in v] for k, v in band.items()}
    return out


def run_file_text(body: dict[str, Any], att: dict[str, str]) -> str:
    """A run file (TOML) that reproduces the request on the command line.

    Uploaded ore, machine and stage-parameter files are referred to by the
    names the user should save them under beside the run file.
    """
    clean = {k: v for k, v in body.items() if v is not None}
    header = "# run file written by msmill serve: msmill predict this_file.toml\n"
    if any(k in att for k in ("ore_toml", "stage_parameters_json", "machine_toml")):
        header += "# save the uploaded files beside it under the names given in [ore]/[machine]/[stage_parameters]\n"
    return header + tomli_w.dumps(_drop_none(clean))


def _drop_none(d: Any) -> Any:
    if isinstance(d, dict):
        return {k: _drop_none(v) for k, v in d.items() if v is not None}
    if isinstance(d, list):
        return [_drop_none(v) for v in d]
    return d


def default_request(example: str | Path | None = None) -> dict[str, Any]:
    """The shipped UG2 example as a request (the page's initial state)."""
    import tomllib

    p = Path(example) if example else Path(__file__).resolve().parents[3] / "examples" / "ug2.toml"
    if p.is_file():
        data = tomllib.loads(p.read_text(encoding="utf-8"))
        data.pop("output", None)
        data.setdefault("output", {})["passing_sizes_mm"] = [0.075, 0.15, 0.6, 1.0, 2.0, 5.0, 10.0]
        data["output"]["plots"] = False
        return data
    return {
        "title": "UG2, 30 t/h, 1500/3000 rpm, gates 40 deg",
        "ore": {"name": "UG2"},
        "feed": {"rate_tph": 30.0, "size_mm": [2.0, 4.75, 9.5, 13.2, 19.0, 26.5, 31.5],
                 "passing_pct": [2.0, 6.0, 18.0, 32.0, 58.0, 88.0, 100.0]},
        "operating": {"speed_rpm": 1500.0, "bottom_speed_factor": 2.0, "gate_deg": 40.0},
        "output": {"plots": False, "passing_sizes_mm": [0.075, 0.15, 0.6, 1.0, 2.0, 5.0, 10.0]},
    }
