"""Campaigns in the store: planned runs, claims, heartbeats, results, retries.

Life of a campaign run (``runs.status``)::

    planned --claim--> running --complete--> done
                          |  \\--fail (attempts < max)--> planned
                          |   \\-fail (attempts = max)--> failed
                          \\--heartbeat stale (replan_stale)--> planned / failed

Every transition out of ``running`` is a conditional ``UPDATE`` on the run's
claim token: a driver that lost its claim (its heartbeat went stale and
another driver re-planned and claimed the run) cannot record a result, so a
run is recorded at most once. Claims select planned rows with ``FOR UPDATE
SKIP LOCKED`` (PostgreSQL; SQLite serialises writers with ``BEGIN
IMMEDIATE``) and then update each row only ``WHERE status = 'planned'``.
"""

from __future__ import annotations

import uuid
from collections.abc import Iterable
from dataclasses import dataclass
from datetime import timedelta
from typing import Any

from sqlalchemy import func, select, update

from msmill.errors import MsmillInputError
from msmill.machine import Machine
from msmill.pipeline.store.hashing import outcome_of, statistics_hash
from msmill.pipeline.store.schema import (
    OUTCOMES,
    STATUSES,
    CampaignRow,
    RawFileRow,
    RunRow,
    utcnow,
)
from msmill.stageparams import DesignPoint, RunStatistics

__all__ = ["CampaignInfo", "Claim", "QueueMixin", "new_token"]


def new_token() -> str:
    """A fresh claim token (one per driver process)."""
    return uuid.uuid4().hex


@dataclass(frozen=True)
class CampaignInfo:
    """A campaign's DEM setting."""

    id: int
    name: str
    machine_hash: str
    machine_toml: str
    mode: str
    run_settings: dict[str, Any]
    options: dict[str, Any]
    max_attempts: int
    allow_not_steady: bool

    @property
    def machine(self) -> Machine:
        """The campaign's machine."""
        return Machine.from_toml(self.machine_toml)


@dataclass(frozen=True)
class Claim:
    """A run claimed by a driver: what to compute and the token to report it with."""

    run_id: int
    token: str
    design: DesignPoint
    seed: int
    attempt: int


def _info(c: CampaignRow) -> CampaignInfo:
    return CampaignInfo(id=c.id, name=c.name, machine_hash=c.machine.content_hash, machine_toml=c.machine.toml,
                        mode=c.mode, run_settings=dict(c.run_settings), options=dict(c.options or {}),
                        max_attempts=c.max_attempts, allow_not_steady=bool(c.allow_not_steady))


#: characters a campaign name may hold (names become folder names: checkpoints, raw runs)
CAMPAIGN_NAME_CHARS = "letters, digits, '.', '_' and '-', not starting with '.'"


def check_campaign_name(name: Any) -> str:
    """A campaign name as given, or one line saying what is allowed (it becomes a folder name)."""
    import re

    if not isinstance(name, str) or not re.fullmatch(r"[A-Za-z0-9_-][A-Za-z0-9._-]{0,199}", name):
        raise MsmillInputError("campaign name", name, f"1-200 {CAMPAIGN_NAME_CHARS}")
    return name


class QueueMixin:
    """Campaign methods of :class:`msmill.pipeline.store.Store`."""

    def _campaign_row(self, s: Any, name: str) -> CampaignRow:
        row = s.scalar(select(CampaignRow).where(CampaignRow.name == name))
        if row is None:
            raise MsmillInputError("campaign", name, "the name of a campaign in the store ('msmill campaign create')")
        return row

    def create_campaign(self, name: str, machine: Machine, mode: str = "slice",
                        run_settings: dict[str, Any] | None = None, max_attempts: int = 3,
                        allow_not_steady: bool = False, options: dict[str, Any] | None = None) -> CampaignInfo:
        """Create a campaign (its DEM setting: machine, mode, ``RunSettings`` fields as a dict)."""
        check_campaign_name(name)
        if mode not in ("slice", "full"):
            raise MsmillInputError("mode", mode, "slice or full")
        if max_attempts < 1:
            raise MsmillInputError("max_attempts", max_attempts, "an integer >= 1")
        with self.session() as s:
            if s.scalar(select(CampaignRow.id).where(CampaignRow.name == name)) is not None:
                raise MsmillInputError("campaign", name, "a name not used by another campaign")
            m = self._machine_row(s, machine)
            row = CampaignRow(name=name, machine_id=m.id, mode=mode, run_settings=dict(run_settings or {}),
                              options=dict(options or {}), max_attempts=max_attempts,
                              allow_not_steady=int(allow_not_steady))
            s.add(row)
            s.flush()
            return _info(row)

    def campaign(self, name: str) -> CampaignInfo:
        """A campaign by name."""
        with self.session() as s:
            return _info(self._campaign_row(s, name))

    def campaigns(self) -> list[CampaignInfo]:
        """All campaigns."""
        with self.session() as s:
            return [_info(c) for c in s.scalars(select(CampaignRow).order_by(CampaignRow.id))]

    def add_points(self, name: str, designs: Iterable[DesignPoint], seed: int | None = None) -> tuple[int, int]:
        """Plan one run per design point (skipping points already in the campaign); ``(added, existing)``."""
        added = existing = 0
        with self.session() as s:
            c = self._campaign_row(s, name)
            seed = int(c.run_settings.get("seed", 0)) if seed is None else seed
            for d in designs:
                if len(d.stage_speeds_rpm) != c.machine.n_stages:
                    raise MsmillInputError("stage_speeds_rpm", d.stage_speeds_rpm,
                                           f"{c.machine.n_stages} speeds (the machine's stages)")
                if self._plan(s, c, d, seed) is None:
                    existing += 1
                    continue
                added += 1
        return added, existing

    def _plan(self, s: Any, c: CampaignRow, d: DesignPoint, seed: int, **values: Any) -> RunRow | None:
        """A new planned run of ``d`` (``values`` override its columns); None if the campaign has it already."""
        dp = self._design_row(s, c.machine, d)
        old = s.scalar(select(RunRow.id).where(RunRow.campaign_id == c.id, RunRow.design_point_id == dp.id,
                                               RunRow.seed == seed))
        if old is not None:
            return None
        row = RunRow(design_point_id=dp.id, machine_id=c.machine_id, campaign_id=c.id, mode=c.mode,
                     source="campaign", status="planned", attempts=0, seed=seed,
                     run_settings=dict(c.run_settings, seed=seed))
        for k, v in values.items():
            setattr(row, k, v)
        s.add(row)
        s.flush()
        return row

    def add_failed(self, name: str, design: DesignPoint, attempts: int, error: str,
                   seed: int | None = None) -> bool:
        """Record a point that failed elsewhere (a campaign restored from its export) as failed here.

        The planner then counts it as pending instead of proposing it again
        (:meth:`retry_failed` re-plans it). False if the campaign has the point already.
        """
        with self.session() as s:
            c = self._campaign_row(s, name)
            seed = int(c.run_settings.get("seed", 0)) if seed is None else seed
            return self._plan(s, c, design, seed, status="failed", attempts=int(attempts),
                              error=error[-20000:]) is not None

    def claim(self, name: str, n: int, worker: str, token: str) -> list[Claim]:
        """Claim up to ``n`` planned runs of a campaign for this driver (status -> running)."""
        out: list[Claim] = []
        with self.session() as s:
            cid = self._campaign_row(s, name).id
            ids = s.scalars(select(RunRow.id).where(RunRow.campaign_id == cid, RunRow.status == "planned")
                            .order_by(RunRow.id).limit(n).with_for_update(skip_locked=True)).all()
            now = utcnow()
            for i in ids:
                res = s.execute(update(RunRow).where(RunRow.id == i, RunRow.status == "planned").values(
                    status="running", claim_token=token, worker=worker, attempts=RunRow.attempts + 1,
                    heartbeat_at=now, started_at=now), execution_options={"synchronize_session": False})
                if res.rowcount == 1:
                    r = s.get(RunRow, i, populate_existing=True)
                    dp = r.design_point
                    out.append(Claim(run_id=i, token=token, seed=r.seed, attempt=r.attempts,
                                     design=DesignPoint(size_mm=dp.size_mm, feed_tph=dp.feed_tph,
                                                        speed_rpm=dp.speed_rpm, gate_deg=dp.gate_deg,
                                                        stage_speeds_rpm=list(dp.stage_speeds_rpm))))
        return out

    def heartbeat(self, run_ids: Iterable[int], token: str, worker: str | None = None) -> int:
        """Refresh the heartbeat of runs this driver holds; returns how many it still holds."""
        ids = list(run_ids)
        if not ids:
            return 0
        values: dict[str, Any] = {"heartbeat_at": utcnow()}
        if worker is not None:
            values["worker"] = worker
        with self.session() as s:
            res = s.execute(update(RunRow).where(RunRow.id.in_(ids), RunRow.claim_token == token,
                                                 RunRow.status == "running").values(**values),
                            execution_options={"synchronize_session": False})
            return int(res.rowcount)

    def _take(self, s: Any, run_id: int, token: str, values: dict[str, Any]) -> bool:
        res = s.execute(update(RunRow).where(RunRow.id == run_id, RunRow.claim_token == token,
                                             RunRow.status == "running").values(**values),
                        execution_options={"synchronize_session": False})
        return res.rowcount == 1

    def complete(self, run_id: int, token: str, stats: RunStatistics, *, outcome: str | None = None,
                 wall_s: float | None = None, engine: str | None = None, package_version: str | None = None,
                 git_commit: str | None = None, raw_files: list[dict[str, Any]] | None = None,
                 worker: str | None = None, cpu_s: float | None = None, note: str | None = None) -> bool:
        """Record the result of a claimed run; False (nothing written) if this driver no longer holds it.

        ``wall_s``, ``cpu_s``: over the run's parts; ``note``: e.g. that it resumed from a checkpoint.
        """
        outcome = outcome or outcome_of(stats)
        if outcome not in OUTCOMES:
            raise MsmillInputError("outcome", outcome, ", ".join(OUTCOMES))
        with self.session() as s:
            if not self._take(s, run_id, token, {"status": "done", "outcome": outcome, "finished_at": utcnow(),
                                                 "wall_s": wall_s, "heartbeat_at": None, "engine": engine,
                                                 "package_version": package_version, "git_commit": git_commit,
                                                 "worker": worker, "cpu_s": cpu_s, "note": note}):
                return False
            run = s.get(RunRow, run_id, populate_existing=True)
            h = statistics_hash(stats, run.machine.content_hash)
            twin = s.scalar(select(RunRow.id).where(RunRow.content_hash == h))
            if twin is not None:  # identical statistics already stored (e.g. its folder was ingested)
                run.error = (run.error or "") + f"identical statistics to run {twin}\n"
            self._fill_statistics(run, stats, None if twin is not None else h)
            run.raw_files = [RawFileRow(**f) for f in raw_files or []]
            s.flush()
        return True

    def fail(self, run_id: int, token: str, error: str) -> str | None:
        """Record a failed attempt: back to planned while attempts < max, else failed. Returns the new status."""
        with self.session() as s:
            run = s.get(RunRow, run_id)
            if run is None or run.claim_token != token or run.status != "running":
                return None
            c = s.get(CampaignRow, run.campaign_id) if run.campaign_id else None
            status = "planned" if c is not None and run.attempts < c.max_attempts else "failed"
            note = (run.error or "") + f"attempt {run.attempts}: {error.strip()}\n"
            ok = self._take(s, run_id, token, {"status": status, "error": note[-20000:], "heartbeat_at": None,
                                                "claim_token": None, "finished_at": utcnow()})
            return status if ok else None

    def release(self, run_id: int, token: str) -> bool:
        """Give a claimed run back unstarted (the attempt is not counted)."""
        with self.session() as s:
            return self._take(s, run_id, token, {"status": "planned", "claim_token": None, "heartbeat_at": None,
                                                 "attempts": RunRow.attempts - 1})

    def replan_stale(self, name: str, stale_s: float, exclude_token: str | None = None) -> int:
        """Running runs whose heartbeat is older than ``stale_s``: re-planned (or failed at the attempt limit).

        Runs held under ``exclude_token`` (the calling driver's own) are left alone.
        """
        cutoff = utcnow() - timedelta(seconds=stale_s)
        n = 0
        with self.session() as s:
            c = self._campaign_row(s, name)
            rows = s.scalars(select(RunRow).where(RunRow.campaign_id == c.id, RunRow.status == "running",
                                                  (RunRow.heartbeat_at < cutoff) | RunRow.heartbeat_at.is_(None))
                             .with_for_update(skip_locked=True)).all()
            for r in rows:
                if exclude_token is not None and r.claim_token == exclude_token:
                    continue
                status = "planned" if r.attempts < c.max_attempts else "failed"
                note = (r.error or "") + f"attempt {r.attempts}: heartbeat stale for > {stale_s:g} s (driver lost)\n"
                n += self._take(s, r.id, r.claim_token or "", {"status": status, "claim_token": None,
                                                               "heartbeat_at": None, "error": note})
        return n

    def adopt_runs(self, name: str, content_hashes: Iterable[str]) -> int:
        """Make the done runs with these content hashes and no campaign runs of campaign ``name``.

        Runs ingested from an export come in without a campaign; their documents name the one they
        were made in, and :func:`msmill.pipeline.export.restore_campaigns` gives them back to it (so a
        re-export writes the documents unchanged). Runs of another campaign are left alone; returns
        how many runs were adopted.
        """
        hashes = list(dict.fromkeys(content_hashes))
        if not hashes:
            return 0
        with self.session() as s:
            cid = self._campaign_row(s, name).id
            res = s.execute(update(RunRow).where(RunRow.campaign_id.is_(None), RunRow.status == "done",
                                                 RunRow.content_hash.in_(hashes))
                            .values(campaign_id=cid), execution_options={"synchronize_session": False})
            return int(res.rowcount)

    def retry_failed(self, name: str) -> int:
        """Re-plan the failed runs of a campaign with a fresh attempt count; returns how many."""
        with self.session() as s:
            cid = self._campaign_row(s, name).id
            res = s.execute(update(RunRow).where(RunRow.campaign_id == cid, RunRow.status == "failed")
                            .values(status="planned", attempts=0), execution_options={"synchronize_session": False})
            return int(res.rowcount)

    def counts(self, name: str) -> dict[str, int]:
        """Number of runs of a campaign per status (every status present, 0 if none)."""
        with self.session() as s:
            cid = self._campaign_row(s, name).id
            got = dict(s.execute(select(RunRow.status, func.count()).where(RunRow.campaign_id == cid)
                                 .group_by(RunRow.status)).all())
        return {st: int(got.get(st, 0)) for st in STATUSES}
