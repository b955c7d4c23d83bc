"""The training campaign's text export, versioned in git (``msmill/data/campaigns/<name>/``).

A campaign runs for days on machines that may go away. Everything needed to
continue it elsewhere lives in one folder that is committed as batches finish:

* ``run-<hash>.json``: one document per done run (``msmill db export`` format,
  :func:`msmill.pipeline.store.transfer.export_document`: statistics,
  machine, run settings, seed, engine, commit, wall time, outcome, and the raw
  tables *by reference* — path, SHA-256, size; no raw events);
* ``campaigns.json``: the campaigns' definitions (machine hash, mode, run
  settings, options such as the planner's size range, attempt limit) and
  their runs still planned or running, so a new machine re-creates them.

On a fresh machine: ``msmill db ingest <folder>`` records the runs (the same
content hash, so ingesting twice is harmless), :func:`restore_campaigns`
re-creates the campaigns and their pending points (``scripts/campaign_loop.py``
does both), then ``msmill campaign resume NAME`` continues.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

from msmill.errors import MsmillInputError
from msmill.machine import DESIGN_SPACE, Machine
from msmill.pipeline.store import Store
from msmill.pipeline.store.hashing import read_statistics
from msmill.pipeline.store.transfer import EXPORT_KIND, export_runs
from msmill.stageparams import DesignPoint, RunStatistics

__all__ = ["CAMPAIGNS_FILE", "ExportedRun", "default_export_dir", "export_campaign", "in_design_space",
           "read_export", "restore_campaigns", "split_runs"]

CAMPAIGNS_FILE = "campaigns.json"


def default_export_dir(name: str = "default") -> Path:
    """Folder of the packaged campaign export ``msmill/data/campaigns/<name>`` (may not exist)."""
    return Path(str(resources.files("msmill").joinpath(f"data/campaigns/{name}")))


@dataclass(frozen=True)
class ExportedRun:
    """One exported run: its document's run facts and its statistics.

    Attributes
    ----------
    path : Path
        The ``run-*.json`` file.
    content_hash : str
        The store's content hash of the run.
    mode : str
        ``"slice"`` or ``"full"``.
    outcome : str
        ``"steady"``, ``"not_steady"`` or ``"choked"``.
    wall_s : float or None
        Wall time of the DEM run (s).
    campaign : str or None
        Campaign the run belonged to in the exporting store.
    statistics : RunStatistics
        The run's statistics.
    """

    path: Path
    content_hash: str
    mode: str
    outcome: str
    wall_s: float | None
    campaign: str | None
    statistics: RunStatistics


#: characters of a failed run's error text kept in the export (the end: the last attempts)
FAILED_ERROR_CHARS = 2000


def _campaign_doc(store: Store, info: Any) -> dict[str, Any]:
    runs = store.runs(campaign=info.name)
    pending = [r.design.model_dump() for r in runs if r.status in ("planned", "running")]
    # failed points with their attempts and the end of their error text: a store restored from the
    # export does not plan them again (the planner counts them as pending)
    failed = [{"design": r.design.model_dump(), "attempts": r.attempts, "seed": r.seed,
               "error": (r.error or "")[-FAILED_ERROR_CHARS:]} for r in runs if r.status == "failed"]
    return {"name": info.name, "machine_hash": info.machine_hash, "machine_toml": info.machine_toml,
            "mode": info.mode, "run_settings": info.run_settings, "options": info.options,
            "max_attempts": info.max_attempts, "allow_not_steady": info.allow_not_steady,
            "counts": store.counts(info.name), "pending": pending, "failed": failed}


def export_campaign(store: Store, out_dir: str | Path) -> tuple[list[Path], Path]:
    """Write every done run of the store and the campaigns' definitions to ``out_dir``.

    Returns the run documents written and the path of ``campaigns.json``. Run
    documents already there are overwritten with identical text (stable keys),
    documents of runs no longer in the store are kept (nothing is lost).
    """
    out = Path(out_dir)
    runs = export_runs(store, out)
    docs = [_campaign_doc(store, c) for c in store.campaigns()]
    cpath = out / CAMPAIGNS_FILE
    cpath.write_text(json.dumps({"kind": "msmill_campaigns", "format_version": 1, "campaigns": docs},
                                indent=1, sort_keys=True, default=str) + "\n", encoding="utf-8")
    return runs, cpath


def runs_machine(runs: list[ExportedRun]) -> Machine:
    """The one machine (by :meth:`~msmill.machine.Machine.geometry_hash`) the exported runs were made on.

    A surrogate or an envelope is for one machine: runs of several give a one-line error naming them.
    """
    machines: dict[str, Machine] = {}
    for r in runs:
        m = Machine.from_toml(json.loads(r.path.read_text(encoding="utf-8"))["machine_toml"])
        machines.setdefault(m.geometry_hash(), m)
    if len(machines) != 1:
        names = ", ".join(f"{m.name} ({m.rotation_sense})" for m in machines.values()) or "none"
        raise MsmillInputError("export", names, "runs of one machine (one export folder per machine)")
    return next(iter(machines.values()))


def read_export(folder: str | Path) -> list[ExportedRun]:
    """The run documents of an export folder, sorted by file name (no store needed)."""
    f = Path(folder)
    if not f.is_dir():
        raise MsmillInputError("export", str(f), "an existing campaign export folder")
    out = []
    for p in sorted(f.glob("run-*.json")):
        doc = json.loads(p.read_text(encoding="utf-8"))
        if doc.get("kind") != EXPORT_KIND:
            continue
        r = doc.get("run", {})
        st = read_statistics(doc["statistics"], source=p.name)
        out.append(ExportedRun(p, doc.get("content_hash", ""), r.get("mode") or st.mode, r.get("outcome") or "steady",
                               r.get("wall_s"), r.get("campaign"), st))
    return out


def in_design_space(design: DesignPoint) -> bool:
    """Whether a run's point lies in the surrogate's design space (:data:`msmill.machine.DESIGN_SPACE`)."""
    return all(lo - 1e-9 <= getattr(design, k) <= hi + 1e-9 for k, (lo, hi) in DESIGN_SPACE.items())


def split_runs(runs: list[ExportedRun]) -> tuple[list[ExportedRun], list[ExportedRun]]:
    """Steady slice runs in the design space (training) and steady full-mill runs (slice-to-full bias).

    Steady runs outside the design space (capacity probes at feeds far above
    60 t/h, issue 20) stay in the export for the operating envelope but do not
    train the surrogate. Each list keeps the export's order (sorted by hash).
    """
    steady = [r for r in runs if r.outcome == "steady"]
    return ([r for r in steady if r.mode == "slice" and in_design_space(r.statistics.design)],
            [r for r in steady if r.mode == "full"])


def _done_points(store: Store, machine_hash: str) -> set[tuple[float, ...]]:
    return {_key(r.design) for r in store.runs(status="done", machine_hash=machine_hash)}


def _key(d: DesignPoint) -> tuple[float, ...]:
    return tuple(round(v, 6) for v in (*d.inputs(), *d.stage_speeds_rpm))


def restore_campaigns(store: Store, folder: str | Path, raw_dir: str | None = None) -> list[str]:
    """Re-create the exported campaigns missing from ``store`` and plan their pending points.

    Points already done in the store (e.g. ingested from the export) are not
    planned again; runs ingested from the folder without a campaign go back to
    the campaign their documents name (:meth:`~msmill.pipeline.store.Store.adopt_runs`),
    so the campaign's counts hold and a re-export rewrites the documents unchanged.
    ``raw_dir`` replaces the exporting machine's raw-folder option (``None`` drops it).
    Returns one line per campaign.
    """
    from msmill.machine import Machine

    p = Path(folder) / CAMPAIGNS_FILE
    if not p.is_file():
        return []
    have = {c.name for c in store.campaigns()}
    members: dict[str, list[str]] = {}
    for r in read_export(folder):
        if r.campaign:
            members.setdefault(r.campaign, []).append(r.content_hash)
    lines = []
    for c in json.loads(p.read_text(encoding="utf-8"))["campaigns"]:
        if c["name"] in have:
            adopted = store.adopt_runs(c["name"], members.get(c["name"], []))
            lines.append(f"campaign {c['name']}: already in the store"
                         + (f", {adopted} ingested runs given back to it" if adopted else ""))
            continue
        opts = {k: v for k, v in c["options"].items() if k != "raw_dir"}
        if raw_dir:
            opts["raw_dir"] = raw_dir
        store.create_campaign(c["name"], Machine.from_toml(c["machine_toml"]), mode=c["mode"],
                              run_settings=c["run_settings"], max_attempts=c["max_attempts"],
                              allow_not_steady=c.get("allow_not_steady", False), options=opts)
        store.adopt_runs(c["name"], members.get(c["name"], []))
        done = _done_points(store, c["machine_hash"])
        todo = [d for d in (DesignPoint(**x) for x in c["pending"]) if _key(d) not in done]
        added, _ = store.add_points(c["name"], todo)
        failed = sum(store.add_failed(c["name"], DesignPoint(**f["design"]), f["attempts"], f["error"], f["seed"])
                     for f in c.get("failed", []) if _key(DesignPoint(**f["design"])) not in done)
        lines.append(f"campaign {c['name']}: re-created, {added} pending runs planned"
                     + (f", {failed} failed points kept failed" if failed else ""))
    return lines
