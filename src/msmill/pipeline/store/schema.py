"""Tables of the training store (SQLAlchemy 2.0 declarative ORM).

The Alembic migrations in ``migrations/versions`` create exactly these tables;
``tests/pipeline/test_store.py`` checks that the migrated database matches
this metadata, so a change here needs a new migration.

All times are naive UTC ``datetime`` values (the same on SQLite and
PostgreSQL). JSON columns use the generic :class:`sqlalchemy.JSON` type
(``JSON`` on PostgreSQL, text on SQLite).
"""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Any

from sqlalchemy import (
    JSON,
    DateTime,
    Float,
    ForeignKey,
    Integer,
    LargeBinary,
    String,
    Text,
    UniqueConstraint,
)
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column, relationship

#: run lifecycle (``runs.status``)
STATUSES = ("planned", "running", "done", "failed")
#: outcome of a finished DEM run (``runs.outcome``); the run protocol decides which
OUTCOMES = ("steady", "not_steady", "choked")


def utcnow() -> datetime:
    """Current time, naive UTC (the store's convention)."""
    return datetime.now(UTC).replace(tzinfo=None)


class Base(DeclarativeBase):
    """Declarative base of the store's tables."""


class MachineRow(Base):
    """A machine description, identified by the SHA-256 of its TOML text."""

    __tablename__ = "machines"
    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    content_hash: Mapped[str] = mapped_column(String(64), unique=True)
    name: Mapped[str] = mapped_column(String(200))
    n_stages: Mapped[int] = mapped_column(Integer)
    toml: Mapped[str] = mapped_column(Text)
    created_at: Mapped[datetime] = mapped_column(DateTime, default=utcnow)


class CampaignRow(Base):
    """A named set of planned DEM runs with one DEM setting."""

    __tablename__ = "campaigns"
    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    name: Mapped[str] = mapped_column(String(200), unique=True)
    machine_id: Mapped[int] = mapped_column(ForeignKey("machines.id"))
    mode: Mapped[str] = mapped_column(String(16))  # slice / full
    run_settings: Mapped[dict[str, Any]] = mapped_column(JSON)  # RunSettings fields, passed through
    options: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)  # ore, raw-event folder, ...
    max_attempts: Mapped[int] = mapped_column(Integer, default=3)
    allow_not_steady: Mapped[int] = mapped_column(Integer, default=0)
    created_at: Mapped[datetime] = mapped_column(DateTime, default=utcnow)
    machine: Mapped[MachineRow] = relationship()


class DesignPointRow(Base):
    """One operating point on one machine (``msmill.stageparams.DesignPoint``)."""

    __tablename__ = "design_points"
    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    point_hash: Mapped[str] = mapped_column(String(64), unique=True)  # machine hash + design values
    machine_id: Mapped[int] = mapped_column(ForeignKey("machines.id"), index=True)
    size_mm: Mapped[float] = mapped_column(Float, index=True)
    feed_tph: Mapped[float] = mapped_column(Float, index=True)
    speed_rpm: Mapped[float] = mapped_column(Float, index=True)
    gate_deg: Mapped[float] = mapped_column(Float, index=True)
    stage_speeds_rpm: Mapped[list[float]] = mapped_column(JSON)
    created_at: Mapped[datetime] = mapped_column(DateTime, default=utcnow)
    machine: Mapped[MachineRow] = relationship()


class RunRow(Base):
    """A DEM run: planned by a campaign, or ingested / imported with its statistics."""

    __tablename__ = "runs"
    __table_args__ = (UniqueConstraint("campaign_id", "design_point_id", "seed", name="uq_runs_campaign_point_seed"),)
    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    design_point_id: Mapped[int] = mapped_column(ForeignKey("design_points.id"), index=True)
    machine_id: Mapped[int] = mapped_column(ForeignKey("machines.id"), index=True)
    campaign_id: Mapped[int | None] = mapped_column(ForeignKey("campaigns.id"), index=True)
    mode: Mapped[str] = mapped_column(String(16))
    source: Mapped[str] = mapped_column(String(16))  # campaign / ingest / import
    source_path: Mapped[str | None] = mapped_column(Text)
    status: Mapped[str] = mapped_column(String(16), index=True)
    outcome: Mapped[str | None] = mapped_column(String(16))
    attempts: Mapped[int] = mapped_column(Integer, default=0)
    claim_token: Mapped[str | None] = mapped_column(String(64))
    worker: Mapped[str | None] = mapped_column(String(200))
    heartbeat_at: Mapped[datetime | None] = mapped_column(DateTime)
    planned_at: Mapped[datetime] = mapped_column(DateTime, default=utcnow)
    started_at: Mapped[datetime | None] = mapped_column(DateTime)
    finished_at: Mapped[datetime | None] = mapped_column(DateTime)
    wall_s: Mapped[float | None] = mapped_column(Float)  # over the run's parts (a resumed run has several)
    cpu_s: Mapped[float | None] = mapped_column(Float)
    # what the run record should say besides errors: resumed from a checkpoint, a checkpoint refused
    note: Mapped[str | None] = mapped_column(Text)
    error: Mapped[str | None] = mapped_column(Text)
    engine: Mapped[str | None] = mapped_column(String(100))  # e.g. "msmill.dem 0.1.0", "LIGGGHTS 3.8"
    package_version: Mapped[str | None] = mapped_column(String(50))
    git_commit: Mapped[str | None] = mapped_column(String(64))
    seed: Mapped[int] = mapped_column(Integer, default=0)
    run_settings: Mapped[dict[str, Any] | None] = mapped_column(JSON)
    content_hash: Mapped[str | None] = mapped_column(String(64), unique=True)  # of the statistics document
    statistics: Mapped[dict[str, Any] | None] = mapped_column(JSON)  # the RunStatistics document
    characteristic_time_s: Mapped[float | None] = mapped_column(Float)
    steady_state_time_s: Mapped[float | None] = mapped_column(Float)
    measurement_window_s: Mapped[float | None] = mapped_column(Float)
    mass_out_rate_kg_s: Mapped[float | None] = mapped_column(Float)
    residence_time_s: Mapped[float | None] = mapped_column(Float)
    design_point: Mapped[DesignPointRow] = relationship()
    machine: Mapped[MachineRow] = relationship()
    stages: Mapped[list[StageRow]] = relationship(order_by="StageRow.stage", cascade="all, delete-orphan")
    raw_files: Mapped[list[RawFileRow]] = relationship(cascade="all, delete-orphan")


class StageRow(Base):
    """Statistics of one stage of one run: the main figures as columns, all of it as JSON."""

    __tablename__ = "stage_statistics"
    __table_args__ = (UniqueConstraint("run_id", "stage", name="uq_stage_statistics_run_stage"),)
    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    run_id: Mapped[int] = mapped_column(ForeignKey("runs.id", ondelete="CASCADE"), index=True)
    design_point_id: Mapped[int] = mapped_column(ForeignKey("design_points.id"), index=True)
    stage: Mapped[int] = mapped_column(Integer, index=True)
    kickback: Mapped[float] = mapped_column(Float)
    refeed: Mapped[float] = mapped_column(Float)
    pass_through: Mapped[float] = mapped_column(Float)
    primary_hit_probability: Mapped[float] = mapped_column(Float)
    primary_velocity_mean_m_s: Mapped[float] = mapped_column(Float)
    primary_velocity_kl: Mapped[float | None] = mapped_column(Float)
    secondary_lambda: Mapped[float] = mapped_column(Float)
    secondary_lambda_kl: Mapped[float | None] = mapped_column(Float)
    secondary_velocity_mean_m_s: Mapped[float] = mapped_column(Float)
    secondary_velocity_kl: Mapped[float | None] = mapped_column(Float)
    n_primary_impacts: Mapped[int] = mapped_column(Integer)
    n_secondary_impacts: Mapped[int] = mapped_column(Integer)
    n_transport_samples: Mapped[int] = mapped_column(Integer)
    mean_holdup_kg: Mapped[float | None] = mapped_column(Float)
    data: Mapped[dict[str, Any]] = mapped_column(JSON)  # the StageStatistics document


class RawFileRow(Base):
    """A raw file of a run (events, snapshots ...), by path and SHA-256; the file stays on disk."""

    __tablename__ = "raw_files"
    __table_args__ = (UniqueConstraint("run_id", "kind", name="uq_raw_files_run_kind"),)
    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    run_id: Mapped[int] = mapped_column(ForeignKey("runs.id", ondelete="CASCADE"), index=True)
    kind: Mapped[str] = mapped_column(String(50))
    path: Mapped[str] = mapped_column(Text)
    sha256: Mapped[str] = mapped_column(String(64), index=True)
    size_bytes: Mapped[int] = mapped_column(Integer)


class SurrogateRow(Base):
    """A trained surrogate: what it was trained on, how, and how well."""

    __tablename__ = "surrogates"
    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    name: Mapped[str] = mapped_column(String(200), index=True)
    kind: Mapped[str] = mapped_column(String(100))  # e.g. "gp"
    created_at: Mapped[datetime] = mapped_column(DateTime, default=utcnow)
    machine_id: Mapped[int | None] = mapped_column(ForeignKey("machines.id"))
    campaign_id: Mapped[int | None] = mapped_column(ForeignKey("campaigns.id"))
    hyperparameters: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)
    metrics: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)
    versions: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)  # msmill, scikit-learn, ...
    artifact_path: Mapped[str | None] = mapped_column(Text)
    artifact_sha256: Mapped[str | None] = mapped_column(String(64))
    artifact: Mapped[bytes | None] = mapped_column(LargeBinary)
    runs: Mapped[list[SurrogateRunRow]] = relationship(cascade="all, delete-orphan")


class SurrogateRunRow(Base):
    """Which runs a surrogate was trained on."""

    __tablename__ = "surrogate_runs"
    surrogate_id: Mapped[int] = mapped_column(ForeignKey("surrogates.id", ondelete="CASCADE"), primary_key=True)
    run_id: Mapped[int] = mapped_column(ForeignKey("runs.id"), primary_key=True)
