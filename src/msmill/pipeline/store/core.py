"""The :class:`Store`: open a database, migrate it, record and query DEM runs.

Database URL (first found): the ``url`` argument (CLI ``--db``), the
environment variable ``MSMILL_DB``, else the SQLite file
``$XDG_DATA_HOME/msmill/store.sqlite`` (``~/.local/share/msmill/store.sqlite``).
A plain path is taken as a SQLite file. Opening a store migrates it to the
newest schema (Alembic, migrations shipped inside the package).

Concurrency: the campaign queue (:mod:`msmill.pipeline.store.queue`) claims
planned runs with ``SELECT ... FOR UPDATE SKIP LOCKED`` on PostgreSQL and
inside ``BEGIN IMMEDIATE`` transactions on SQLite (one writer at a time, WAL
journal), and every state change is a conditional ``UPDATE`` on the claim
token, so two drivers never claim or record the same run.
"""

from __future__ import annotations

import hashlib
import math
import os
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from sqlalchemy import Engine, create_engine, event, func, inspect, select
from sqlalchemy.orm import Session, sessionmaker

from msmill.errors import MsmillInputError
from msmill.machine import Machine
from msmill.pipeline.store.hashing import (
    canonical_statistics,
    design_hash,
    machine_hash,
    outcome_of,
    read_statistics,
    statistics_hash,
)
from msmill.pipeline.store.queue import QueueMixin
from msmill.pipeline.store.schema import (
    CampaignRow,
    DesignPointRow,
    MachineRow,
    RawFileRow,
    RunRow,
    StageRow,
    SurrogateRow,
    SurrogateRunRow,
    utcnow,
)
from msmill.stageparams import DESIGN_INPUTS, DesignPoint, RunStatistics
from msmill.validate import user_path

__all__ = [
    "DEFAULT_DB_ENV",
    "DESIGN_FILTERS",
    "RunRecord",
    "Store",
    "canonical_statistics",
    "default_url",
    "machine_hash",
    "outcome_of",
    "read_statistics",
    "statistics_hash",
]

DEFAULT_DB_ENV = "MSMILL_DB"
#: design variables ``list``/``show``/``runs`` can filter on (columns of ``design_points``)
DESIGN_FILTERS = DESIGN_INPUTS
_MIGRATIONS = Path(__file__).parent / "migrations"


def data_home() -> Path:
    """msmill's per-user data folder: ``$XDG_DATA_HOME/msmill`` (``~/.local/share/msmill`` by default)."""
    return Path(os.environ.get("XDG_DATA_HOME") or Path.home() / ".local" / "share") / "msmill"


def default_url() -> str:
    """The store URL used when none is given: ``MSMILL_DB`` or the per-user SQLite file."""
    env = os.environ.get(DEFAULT_DB_ENV)
    if env:
        return env
    return f"sqlite:///{data_home() / 'store.sqlite'}"


def _normalise_url(url: str | None, create: bool = True) -> str:
    """The SQLAlchemy URL of ``url`` (a URL or a SQLite file path); ``create``: make a SQLite file's folder.

    Without ``create`` a SQLite file that does not exist is refused in one line (a read command never
    creates a store, nor folders for it).
    """
    url = url or default_url()
    if "\x00" in url:
        raise MsmillInputError("--db", url.replace("\x00", "\\x00"), "a SQLite file or a database URL without NUL characters")
    if "://" not in url:  # a plain path: a SQLite file
        url = f"sqlite:///{user_path(url, '--db').resolve()}"
    if url.startswith("postgresql://") or url.startswith("postgres://"):
        url = "postgresql+psycopg://" + url.split("://", 1)[1]
    if url.startswith("sqlite:///") and not url.startswith("sqlite:///:memory:"):
        f = Path(url.removeprefix("sqlite:///"))
        if f.is_dir():
            raise MsmillInputError("--db", str(f), "a SQLite file or a database URL (this is a folder)")
        if create:
            try:
                f.parent.mkdir(parents=True, exist_ok=True)
            except OSError as exc:
                raise MsmillInputError("--db", str(f), f"a store in a writable folder ({exc.strerror})") from None
        elif not f.is_file():
            raise MsmillInputError("--db", str(f), "an existing store (no such file; 'msmill db ingest' or "
                                   "'msmill campaign create' makes one)")
    return url


@dataclass(frozen=True)
class RunRecord:
    """One row of ``runs`` with its design point, as handed out by :class:`Store`."""

    id: int
    design_point_id: int
    design: DesignPoint
    machine_hash: str
    campaign: str | None
    mode: str
    source: str
    status: str
    outcome: str | None
    attempts: int
    seed: int
    worker: str | None
    error: str | None
    wall_s: float | None
    content_hash: str | None
    source_path: str | None
    git_commit: str | None
    package_version: str | None
    engine: str | None
    run_settings: dict[str, Any] | None
    cpu_s: float | None = None
    note: str | None = None

    @classmethod
    def from_row(cls, r: RunRow, campaign: str | None) -> RunRecord:
        dp = r.design_point
        design = DesignPoint(size_mm=dp.size_mm, feed_tph=dp.feed_tph, speed_rpm=dp.speed_rpm,
                             gate_deg=dp.gate_deg, stage_speeds_rpm=list(dp.stage_speeds_rpm))
        return cls(id=r.id, design_point_id=r.design_point_id, design=design, machine_hash=r.machine.content_hash,
                   campaign=campaign, mode=r.mode, source=r.source, status=r.status, outcome=r.outcome,
                   attempts=r.attempts, seed=r.seed, worker=r.worker, error=r.error, wall_s=r.wall_s,
                   content_hash=r.content_hash, source_path=r.source_path, git_commit=r.git_commit,
                   package_version=r.package_version, engine=r.engine, run_settings=r.run_settings,
                   cpu_s=r.cpu_s, note=r.note)


def _redacted(url: str) -> str:
    """The URL without its password (for messages)."""
    from sqlalchemy.engine import make_url

    try:
        return make_url(url).render_as_string(hide_password=True)
    except Exception:  # an unparsable URL is shown as given
        return url


def _cause(exc: BaseException) -> str:
    """The driver's own message, on one line (SQLAlchemy wraps it with SQL and a link)."""
    orig = getattr(exc, "orig", None) or exc
    text = " ".join(str(orig).split())
    return (text[:200] + "...") if len(text) > 200 else text or type(orig).__name__


def _sqlite_pragmas(dbapi_conn: Any, _record: Any) -> None:
    dbapi_conn.isolation_level = None  # SQLAlchemy's "begin" event below issues BEGIN IMMEDIATE itself
    cur = dbapi_conn.cursor()
    cur.execute("PRAGMA journal_mode=WAL")
    cur.execute("PRAGMA foreign_keys=ON")
    cur.execute("PRAGMA busy_timeout=60000")
    cur.close()


def _sqlite_begin(conn: Any) -> None:
    conn.exec_driver_sql("BEGIN IMMEDIATE")


class Store(QueueMixin):
    """A training store at a SQLAlchemy URL (see the module docstring for the default).

    Parameters
    ----------
    url : str, optional
        SQLAlchemy URL or a SQLite file path; default :func:`default_url`.
    upgrade : bool
        Migrate the database to the newest schema on opening (default True).
    """

    def __init__(self, url: str | None = None, upgrade: bool = True, create: bool = True) -> None:
        from sqlalchemy.exc import ArgumentError, NoSuchModuleError, SQLAlchemyError

        self.url = _normalise_url(url, create=create)
        shown = _redacted(self.url)
        try:
            self.engine: Engine = self._make_engine(self.url)
        except (ArgumentError, NoSuchModuleError, ImportError) as exc:
            raise MsmillInputError("--db", shown, f"a SQLAlchemy URL or a SQLite file ({_cause(exc)})") from None
        self._sessions = sessionmaker(self.engine, expire_on_commit=False)
        try:
            if upgrade:
                self.upgrade()
            else:
                self.revision()  # reach it now: a store that cannot be opened says so here, in one line
        except SQLAlchemyError as exc:
            raise MsmillInputError("--db", shown, f"a store that can be opened ({_cause(exc)})") from None

    @staticmethod
    def _make_engine(url: str) -> Engine:
        if url.startswith("sqlite"):
            engine = create_engine(url, connect_args={"timeout": 60})
            event.listen(engine, "connect", _sqlite_pragmas)
            event.listen(engine, "begin", _sqlite_begin)
            return engine
        return create_engine(url, pool_pre_ping=True)

    @property
    def dialect(self) -> str:
        """``sqlite`` or ``postgresql`` (or another SQLAlchemy dialect)."""
        return self.engine.dialect.name

    def close(self) -> None:
        """Release all connections."""
        self.engine.dispose()

    def __enter__(self) -> Store:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ schema
    def _alembic_config(self) -> Any:
        from alembic.config import Config

        cfg = Config()
        cfg.set_main_option("script_location", str(_MIGRATIONS))
        cfg.set_main_option("sqlalchemy.url", self.url.replace("%", "%%"))
        return cfg

    def revision(self) -> str | None:
        """Alembic revision of the database (None: empty database)."""
        from alembic.runtime.migration import MigrationContext

        with self.engine.connect() as conn:
            return MigrationContext.configure(conn).get_current_revision()

    def head(self) -> str:
        """Newest revision shipped with this msmill."""
        from alembic.script import ScriptDirectory

        return str(ScriptDirectory.from_config(self._alembic_config()).get_current_head())

    def upgrade(self, target: str = "head") -> str | None:
        """Migrate the database (no-op when current); returns the new revision."""
        if target == "head" and self.revision() == self.head():
            return self.head()
        from alembic import command

        cfg = self._alembic_config()
        try:
            with self.engine.begin() as conn:
                cfg.attributes["connection"] = conn
                command.upgrade(cfg, target)
        except Exception:
            # another process may have migrated at the same moment: fine if it reached the target
            if self.revision() != self.head():
                raise
        return self.revision()

    def table_names(self) -> list[str]:
        """Tables in the database (for checks)."""
        return sorted(inspect(self.engine).get_table_names())

    @contextmanager
    def session(self) -> Iterator[Session]:
        """A session in one transaction (committed on success, rolled back on error)."""
        with self._sessions() as s, s.begin():
            yield s

    # ------------------------------------------------------------------ machines and design points
    def _machine_row(self, s: Session, machine: Machine) -> MachineRow:
        h = machine_hash(machine)
        row = s.scalar(select(MachineRow).where(MachineRow.content_hash == h))
        if row is None:
            row = MachineRow(content_hash=h, name=machine.name, n_stages=machine.n_stages, toml=machine.to_toml())
            s.add(row)
            s.flush()
        return row

    def add_machine(self, machine: Machine) -> str:
        """Store a machine (once per content hash); returns its hash."""
        with self.session() as s:
            return self._machine_row(s, machine).content_hash

    def machine(self, content_hash: str) -> Machine:
        """The machine with this hash (or unique hash prefix)."""
        with self.session() as s:
            rows = s.scalars(select(MachineRow).where(MachineRow.content_hash.startswith(content_hash))).all()
            if len(rows) != 1:
                raise MsmillInputError("machine", content_hash, "the hash (or a unique prefix) of a stored machine")
            return Machine.from_toml(rows[0].toml)

    def _design_row(self, s: Session, machine_row: MachineRow, design: DesignPoint) -> DesignPointRow:
        h = design_hash(machine_row.content_hash, design)
        row = s.scalar(select(DesignPointRow).where(DesignPointRow.point_hash == h))
        if row is None:
            row = DesignPointRow(point_hash=h, machine_id=machine_row.id, size_mm=design.size_mm,
                                 feed_tph=design.feed_tph, speed_rpm=design.speed_rpm, gate_deg=design.gate_deg,
                                 stage_speeds_rpm=list(design.stage_speeds_rpm))
            s.add(row)
            s.flush()
        return row

    # ------------------------------------------------------------------ recording statistics
    @staticmethod
    def _stage_rows(run: RunRow, stats: RunStatistics) -> list[StageRow]:
        doc = canonical_statistics(stats)["stages"]
        return [StageRow(design_point_id=run.design_point_id, stage=st.stage, kickback=st.kickback,
                         refeed=st.refeed, pass_through=st.pass_through,
                         primary_hit_probability=st.primary_hit_probability,
                         primary_velocity_mean_m_s=st.primary_velocity.mean(),
                         primary_velocity_kl=st.primary_velocity_kl, secondary_lambda=st.secondary_lambda,
                         secondary_lambda_kl=st.secondary_lambda_kl,
                         secondary_velocity_mean_m_s=st.secondary_velocity.mean(),
                         secondary_velocity_kl=st.secondary_velocity_kl, n_primary_impacts=st.n_primary_impacts,
                         n_secondary_impacts=st.n_secondary_impacts, n_transport_samples=st.n_transport_samples,
                         mean_holdup_kg=st.mean_holdup_kg, data=d)
                for st, d in zip(stats.stages, doc, strict=True)]

    @staticmethod
    def _check_design(row: DesignPointRow, stats: RunStatistics) -> None:
        """The statistics' design point is the row's: the store keeps the point once, in the row.

        The SQL columns (which queries filter on) come from the plan, the statistics (which training
        reads) from the DEM; a run whose two disagree is refused in one line, nothing written.
        """
        d = stats.design
        pairs = [(k, getattr(row, k), getattr(d, k)) for k in DESIGN_FILTERS]
        pairs += [(f"stage_speeds_rpm[{i}]", a, b) for i, (a, b) in
                  enumerate(zip(row.stage_speeds_rpm, d.stage_speeds_rpm, strict=False))]
        if len(row.stage_speeds_rpm) != len(d.stage_speeds_rpm):
            pairs.append(("stage_speeds_rpm", len(row.stage_speeds_rpm), len(d.stage_speeds_rpm)))
        for name, want, got in pairs:
            if not math.isclose(float(want), float(got), rel_tol=1e-9, abs_tol=1e-12):
                raise MsmillInputError(f"statistics.design.{name}", got,
                                       f"{want:g}, the run's design point in the store")

    @staticmethod
    def _fill_statistics(run: RunRow, stats: RunStatistics, content_hash: str | None) -> None:
        Store._check_design(run.design_point, stats)
        run.statistics = canonical_statistics(stats)
        run.content_hash = content_hash
        run.characteristic_time_s = stats.characteristic_time_s
        run.steady_state_time_s = stats.steady_state_time_s
        run.measurement_window_s = stats.measurement_window_s
        run.mass_out_rate_kg_s = stats.mass_out_rate_kg_s
        run.residence_time_s = stats.residence_time_s
        run.stages = Store._stage_rows(run, stats)

    def find_hash(self, content_hash: str) -> int | None:
        """Id of the run with this content hash, if stored."""
        with self.session() as s:
            return s.scalar(select(RunRow.id).where(RunRow.content_hash == content_hash))

    def record_run(
        self, stats: RunStatistics, machine: Machine, *, source: str = "ingest", source_path: str | None = None,
        seed: int = 0, run_settings: dict[str, Any] | None = None, outcome: str | None = None,
        wall_s: float | None = None, engine: str | None = None, package_version: str | None = None,
        git_commit: str | None = None, raw_files: list[dict[str, Any]] | None = None,
        allow_not_steady: bool = False,
    ) -> tuple[int, bool]:
        """Record a finished run with its statistics; returns ``(run_id, created)``.

        Idempotent: a run with the same content hash (:func:`statistics_hash`)
        is not recorded again (``created`` False). A run whose outcome is not
        ``steady`` raises :class:`MsmillInputError` unless ``allow_not_steady``.
        """
        outcome = outcome or outcome_of(stats)
        if outcome != "steady" and not allow_not_steady:
            raise MsmillInputError("outcome", outcome, "steady (or allow not-steady runs)")
        if len(stats.design.stage_speeds_rpm) != machine.n_stages:
            raise MsmillInputError("statistics.stages", stats.n_stages, f"{machine.n_stages} (the machine's)")
        mh = machine_hash(machine)
        h = statistics_hash(stats, mh)
        prov = stats.provenance
        with self.session() as s:
            old = s.scalar(select(RunRow.id).where(RunRow.content_hash == h))
            if old is not None:
                return int(old), False
            m = self._machine_row(s, machine)
            dp = self._design_row(s, m, stats.design)
            now = utcnow()
            run = RunRow(design_point_id=dp.id, machine_id=m.id, campaign_id=None, mode=stats.mode, source=source,
                         source_path=source_path, status="done", outcome=outcome, attempts=1, seed=seed,
                         run_settings=run_settings if run_settings is not None else prov.get("run_settings"),
                         wall_s=wall_s if wall_s is not None else prov.get("wall_s"),
                         engine=engine or prov.get("engine") or "msmill.dem",
                         package_version=package_version or prov.get("msmill_version"),
                         git_commit=git_commit or prov.get("git_commit"), planned_at=now, finished_at=now)
            s.add(run)
            s.flush()
            self._fill_statistics(run, stats, h)
            run.raw_files = [RawFileRow(**f) for f in raw_files or []]
            s.flush()
            return int(run.id), True

    # ------------------------------------------------------------------ queries
    def _runs_query(self, campaign: str | None, status: str | None, machine_hash: str | None,
                    filters: dict[str, tuple[float | None, float | None]] | None) -> Any:
        q = select(RunRow, CampaignRow.name).join(RunRow.design_point).join(RunRow.machine).outerjoin(
            CampaignRow, CampaignRow.id == RunRow.campaign_id)
        if campaign is not None:
            q = q.where(CampaignRow.name == campaign)
        if status is not None:
            q = q.where(RunRow.status == status)
        if machine_hash is not None:
            q = q.where(MachineRow.content_hash.startswith(machine_hash))
        for name, (lo, hi) in (filters or {}).items():
            if name not in DESIGN_FILTERS:
                raise MsmillInputError("filter", name, ", ".join(DESIGN_FILTERS))
            col = getattr(DesignPointRow, name)
            if lo is not None:
                q = q.where(col >= lo)
            if hi is not None:
                q = q.where(col <= hi)
        return q.order_by(RunRow.id)

    def runs(self, campaign: str | None = None, status: str | None = None, machine_hash: str | None = None,
             filters: dict[str, tuple[float | None, float | None]] | None = None) -> list[RunRecord]:
        """Runs, optionally filtered by campaign, status, machine and design-variable ranges.

        ``filters`` maps a name of :data:`DESIGN_FILTERS` to ``(low, high)``
        (inclusive, None = open).
        """
        with self.session() as s:
            return [RunRecord.from_row(r, c) for r, c in s.execute(
                self._runs_query(campaign, status, machine_hash, filters)).all()]

    def run(self, run_id: int) -> RunRecord:
        """One run by id."""
        with self.session() as s:
            row = s.execute(self._runs_query(None, None, None, None).where(RunRow.id == run_id)).first()
            if row is None:
                raise MsmillInputError("run", run_id, "the id of a stored run")
            return RunRecord.from_row(row[0], row[1])

    def statistics(self, run_id: int) -> RunStatistics:
        """The statistics of a done run."""
        with self.session() as s:
            doc = s.scalar(select(RunRow.statistics).where(RunRow.id == run_id))
        if doc is None:
            raise MsmillInputError("run", run_id, "the id of a run with statistics")
        return RunStatistics.from_dict(doc, source=f"run {run_id}")

    def run_machine(self, run_id: int) -> Machine:
        """The machine of a run."""
        return self.machine(self.run(run_id).machine_hash)

    def raw_files(self, run_id: int) -> list[dict[str, Any]]:
        """Raw files of a run: ``kind``, ``path``, ``sha256``, ``size_bytes``."""
        with self.session() as s:
            rows = s.scalars(select(RawFileRow).where(RawFileRow.run_id == run_id).order_by(RawFileRow.kind))
            return [{"kind": r.kind, "path": r.path, "sha256": r.sha256, "size_bytes": r.size_bytes} for r in rows]

    def training_runs(self, campaign: str | None = None, machine_hash: str | None = None,
                      steady_only: bool = True) -> list[tuple[RunRecord, RunStatistics]]:
        """Done runs with their statistics: the surrogate's training data.

        ``steady_only`` keeps runs whose outcome is ``steady``. A campaign run whose
        statistics equal an already stored run's (``content_hash`` None) is left out.
        """
        recs = [r for r in self.runs(campaign=campaign, status="done", machine_hash=machine_hash)
                if r.content_hash is not None]
        if steady_only:
            recs = [r for r in recs if r.outcome == "steady"]
        return [(r, self.statistics(r.id)) for r in recs]

    def stage_table(self, stage: int | None = None, campaign: str | None = None) -> Any:
        """Per-stage figures of done runs as a pandas DataFrame (one row per run and stage)."""
        import pandas as pd

        cols = [c for c in StageRow.__table__.columns.keys() if c not in ("id", "data")]
        q = (select(*[getattr(StageRow, c) for c in cols], DesignPointRow.size_mm, DesignPointRow.feed_tph,
                    DesignPointRow.speed_rpm, DesignPointRow.gate_deg, RunRow.outcome)
             .join(RunRow, RunRow.id == StageRow.run_id).join(DesignPointRow, DesignPointRow.id == StageRow.design_point_id)
             .outerjoin(CampaignRow, CampaignRow.id == RunRow.campaign_id))
        if stage is not None:
            q = q.where(StageRow.stage == stage)
        if campaign is not None:
            q = q.where(CampaignRow.name == campaign)
        with self.engine.connect() as conn:
            return pd.DataFrame(conn.execute(q.order_by(StageRow.run_id, StageRow.stage)).mappings().all())

    def count_stage_rows(self) -> dict[int, int]:
        """Number of stage rows per run id (a run recorded twice would show up here)."""
        with self.session() as s:
            return {int(r): int(n) for r, n in s.execute(
                select(StageRow.run_id, func.count()).group_by(StageRow.run_id)).all()}

    # ------------------------------------------------------------------ surrogates
    def add_surrogate(
        self, name: str, kind: str, run_ids: list[int], hyperparameters: dict[str, Any] | None = None,
        metrics: dict[str, Any] | None = None, versions: dict[str, Any] | None = None,
        artifact: bytes | None = None, artifact_path: str | None = None, machine_hash: str | None = None,
        campaign: str | None = None,
    ) -> int:
        """Record a trained surrogate and the runs it was trained on; returns its id."""
        with self.session() as s:
            mid = None
            if machine_hash is not None:
                mid = s.scalar(select(MachineRow.id).where(MachineRow.content_hash == machine_hash))
            cid = s.scalar(select(CampaignRow.id).where(CampaignRow.name == campaign)) if campaign else None
            row = SurrogateRow(name=name, kind=kind, hyperparameters=hyperparameters or {}, metrics=metrics or {},
                               versions=versions or {}, artifact=artifact, artifact_path=artifact_path,
                               artifact_sha256=hashlib.sha256(artifact).hexdigest() if artifact else None,
                               machine_id=mid, campaign_id=cid)
            row.runs = [SurrogateRunRow(run_id=int(r)) for r in sorted(set(run_ids))]
            s.add(row)
            s.flush()
            return int(row.id)

    def surrogates(self, name: str | None = None) -> list[dict[str, Any]]:
        """Trained surrogates (newest last) as dicts, with ``run_ids``; the artifact bytes under ``artifact``."""
        with self.session() as s:
            q = select(SurrogateRow).order_by(SurrogateRow.id)
            if name is not None:
                q = q.where(SurrogateRow.name == name)
            return [{"id": r.id, "name": r.name, "kind": r.kind, "created_at": r.created_at,
                     "hyperparameters": r.hyperparameters, "metrics": r.metrics, "versions": r.versions,
                     "artifact": r.artifact, "artifact_path": r.artifact_path, "artifact_sha256": r.artifact_sha256,
                     "run_ids": sorted(x.run_id for x in r.runs)} for r in s.scalars(q)]
