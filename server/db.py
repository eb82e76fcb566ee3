"""Metadata store: SQLAlchemy 2 models, the engine (SQLite in WAL mode by default, PostgreSQL by
URL) and Alembic migrations applied at start."""

from __future__ import annotations

import sqlite3
import time
from datetime import UTC, datetime
from pathlib import Path

from alembic import command
from alembic.config import Config
from sqlalchemy import (
    JSON,
    Boolean,
    DateTime,
    Float,
    ForeignKey,
    Index,
    Integer,
    String,
    UniqueConstraint,
    create_engine,
    event,
    false,
    text,
)
from sqlalchemy.engine import Engine
from sqlalchemy.ext.compiler import compiles
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column, sessionmaker
from sqlalchemy.sql.functions import FunctionElement
from sqlalchemy.types import TypeDecorator

MIGRATIONS = Path(__file__).parent / "migrations"


def utcnow() -> datetime:
    return datetime.now(UTC)


class UTCDateTime(TypeDecorator):
    """A timezone-aware UTC datetime on every backend (SQLite stores it without the zone)."""

    impl = DateTime(timezone=True)
    cache_ok = True

    def process_bind_param(self, value, dialect):
        return value.astimezone(UTC) if value is not None and value.tzinfo is not None else value

    def process_result_value(self, value, dialect):
        return value.replace(tzinfo=UTC) if value is not None and value.tzinfo is None else value


class Base(DeclarativeBase):
    pass


class ApiToken(Base):
    __tablename__ = "api_tokens"
    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    name: Mapped[str] = mapped_column(String(128), unique=True)
    role: Mapped[str] = mapped_column(String(16))
    token_hash: Mapped[str] = mapped_column(String(64), unique=True, index=True)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)
    revoked: Mapped[bool] = mapped_column(Boolean, default=False)


class db_epoch(FunctionElement):  # noqa: N801 - reads like the SQL function it renders
    """The database server's clock in seconds since the epoch (a float): leases expire by this clock, so
    processes on machines whose clocks disagree still agree on who holds one."""

    type = Float()
    inherit_cache = True


@compiles(db_epoch)
def _epoch_default(element, compiler, **kw) -> str:  # PostgreSQL; clock_timestamp() is not frozen per transaction
    return "extract(epoch from clock_timestamp())"


@compiles(db_epoch, "sqlite")
def _epoch_sqlite(element, compiler, **kw) -> str:
    return "((julianday('now') - 2440587.5) * 86400.0)"


class PolicyVersion(Base):
    """One version of a policy lineage (``name``), addressed as ``name@version``.

    manifest: the data it was trained on (pretraining episodes, takeover segments); calibration: its
    threshold and the calibration set; evaluation: success per task; status_reason: why it has its
    status (the promotion gate's decision, a promote or rollback)."""

    __tablename__ = "policy_versions"
    __table_args__ = (
        UniqueConstraint("name", "version", name="uq_policy_versions_name_version"),
        # at most one active version per lineage, whatever writes at the same time (CLI, API, the job)
        Index(
            "uq_policy_versions_one_active",
            "name",
            unique=True,
            sqlite_where=text("status = 'active'"),
            postgresql_where=text("status = 'active'"),
        ),
    )
    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    name: Mapped[str] = mapped_column(String(256))
    version: Mapped[int] = mapped_column(Integer, default=1)
    path: Mapped[str] = mapped_column(String(1024), unique=True)
    task: Mapped[str] = mapped_column(String(64))
    threshold: Mapped[float | None] = mapped_column(Float, nullable=True)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)
    status: Mapped[str] = mapped_column(String(16), default="candidate", index=True)  # see POLICY_STATUSES
    parent_id: Mapped[int | None] = mapped_column(ForeignKey("policy_versions.id"), nullable=True)
    manifest: Mapped[dict] = mapped_column(JSON, default=dict)
    calibration: Mapped[dict] = mapped_column(JSON, default=dict)
    evaluation: Mapped[dict] = mapped_column(JSON, default=dict)
    command: Mapped[str | None] = mapped_column(String(2048), nullable=True)
    status_reason: Mapped[str | None] = mapped_column(String(1024), nullable=True)

    @property
    def ref(self) -> str:
        return f"{self.name}@{self.version}"


POLICY_STATUSES = ("candidate", "active", "retired")


class EpisodeRecord(Base):
    __tablename__ = "episodes"
    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    robot_id: Mapped[int] = mapped_column(Integer, index=True)
    task: Mapped[str] = mapped_column(String(64), index=True)
    seed: Mapped[int] = mapped_column(Integer)
    policy_id: Mapped[int | None] = mapped_column(ForeignKey("policy_versions.id"), nullable=True)
    outcome: Mapped[str | None] = mapped_column(
        String(16), nullable=True
    )  # success | timeout | faulted | reset | stopped | interrupted (left open by a crash)
    steps: Mapped[int] = mapped_column(Integer, default=0)
    assisted_steps: Mapped[int] = mapped_column(Integer, default=0)
    assistance_events: Mapped[int] = mapped_column(Integer, default=0)
    started_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)
    ended_at: Mapped[datetime | None] = mapped_column(UTCDateTime(), nullable=True)
    path: Mapped[str | None] = mapped_column(String(1024), nullable=True)


FINISHED = ("success", "timeout")  # episode outcomes of episodes that ended on their own

SEGMENT_ENDS = (
    "hand-back",
    "lease-expired",
    "episode-ended",
    "worker-fault",
    "reset",
    "service-stopped",
    "crash-recovered",
)


class SegmentRecord(Base):
    """One takeover: status open -> closed, or recovered after a crash; ended_by: one of SEGMENT_ENDS.

    The request it answers (``server.fleet.assistance.AskRecord``): reason, and from migration 0007
    signal (the asking signal's name, "watchdog", or None for help requested through the service),
    score and threshold (the numbers the queue ranked it by) and paper_u (the paper's denoising U when
    the robot asked). Rows recorded before 0007 have None in these four: not recorded, not an error."""

    __tablename__ = "segments"
    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    robot_id: Mapped[int] = mapped_column(Integer, index=True)
    episode_id: Mapped[int | None] = mapped_column(ForeignKey("episodes.id"), nullable=True)
    task: Mapped[str] = mapped_column(String(64), index=True)
    policy_id: Mapped[int | None] = mapped_column(ForeignKey("policy_versions.id"), nullable=True)
    operator: Mapped[str] = mapped_column(String(128))
    reason: Mapped[str] = mapped_column(String(256))
    signal: Mapped[str | None] = mapped_column(String(64), nullable=True)
    score: Mapped[float | None] = mapped_column(Float, nullable=True)
    threshold: Mapped[float | None] = mapped_column(Float, nullable=True)
    paper_u: Mapped[float | None] = mapped_column(Float, nullable=True)
    status: Mapped[str] = mapped_column(String(16), index=True, default="open")
    ended_by: Mapped[str | None] = mapped_column(String(32), nullable=True)
    steps: Mapped[int] = mapped_column(Integer, default=0)
    path: Mapped[str] = mapped_column(String(1024))  # relative to the service's data_dir
    meta: Mapped[dict] = mapped_column(JSON, default=dict)
    started_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)
    ended_at: Mapped[datetime | None] = mapped_column(UTCDateTime(), nullable=True)
    # the operator's verdict (migration 0006): label one of SEGMENT_LABELS or None; a discarded takeover
    # keeps its file and is never trained on (server.finetune.plan)
    label: Mapped[str | None] = mapped_column(String(8), nullable=True)
    discarded: Mapped[bool] = mapped_column(Boolean, default=False, server_default=false())
    note: Mapped[str | None] = mapped_column(String(500), nullable=True)
    labelled_by: Mapped[str | None] = mapped_column(String(128), nullable=True)
    labelled_at: Mapped[datetime | None] = mapped_column(UTCDateTime(), nullable=True)


SEGMENT_LABELS = ("good", "bad")
NOTE_MAX = 500

JOB_STATUSES = ("queued", "running", "succeeded", "failed", "interrupted")


class FinetuneJob(Base):
    """One fine-tuning run of a lineage: from the parent version to a candidate (or promoted) child.

    status: one of JOB_STATUSES (``succeeded`` means the job finished; ``gate`` says whether its version
    was promoted); stage: what it is doing (data, train, calibrate, evaluate, gate); data: counts, the
    segments used and the ones skipped with their reason; work_dir: its checkpoints (relative to the
    service's data_dir), from which an interrupted job resumes."""

    __tablename__ = "finetune_jobs"
    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    lineage: Mapped[str] = mapped_column(String(256), index=True)
    status: Mapped[str] = mapped_column(String(16), index=True, default="queued")
    stage: Mapped[str | None] = mapped_column(String(32), nullable=True)
    progress: Mapped[float] = mapped_column(Float, default=0.0)
    source: Mapped[str] = mapped_column(String(32), default="takeovers")
    trigger: Mapped[str] = mapped_column(String(32), default="cli")
    parent_id: Mapped[int | None] = mapped_column(ForeignKey("policy_versions.id"), nullable=True)
    version_id: Mapped[int | None] = mapped_column(ForeignKey("policy_versions.id"), nullable=True)
    since: Mapped[datetime | None] = mapped_column(UTCDateTime(), nullable=True)
    data: Mapped[dict] = mapped_column(JSON, default=dict)
    evaluation: Mapped[dict] = mapped_column(JSON, default=dict)
    gate: Mapped[dict] = mapped_column(JSON, default=dict)
    error: Mapped[str | None] = mapped_column(String(4096), nullable=True)
    command: Mapped[str | None] = mapped_column(String(2048), nullable=True)
    work_dir: Mapped[str | None] = mapped_column(String(1024), nullable=True)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)
    started_at: Mapped[datetime | None] = mapped_column(UTCDateTime(), nullable=True)
    ended_at: Mapped[datetime | None] = mapped_column(UTCDateTime(), nullable=True)


class JobLease(Base):
    """A named lease (one row per name): held by ``owner`` until ``expires_at`` (seconds since the
    epoch, by the database's clock); ``fence`` grows by one at every acquisition, so a holder that
    lost its lease cannot write as if it still held it (server.lease)."""

    __tablename__ = "job_leases"
    name: Mapped[str] = mapped_column(String(64), primary_key=True)
    owner: Mapped[str | None] = mapped_column(String(256), nullable=True)
    fence: Mapped[int] = mapped_column(Integer, default=0)
    expires_at: Mapped[float] = mapped_column(Float, default=0.0)


class ConsoleSession(Base):
    """An operator console log-in shared by every API process (``web.sessions.SharedConsoleSessions``):
    the SHA-256 of the cookie's session id, the hash of the API token it was opened with (re-checked at
    every use, so a revocation applies), and when it was opened (seconds since the epoch, the
    database's clock)."""

    __tablename__ = "console_sessions"
    sid_hash: Mapped[str] = mapped_column(String(64), primary_key=True)
    token_hash: Mapped[str] = mapped_column(String(64))
    opened_at: Mapped[float] = mapped_column(Float)


def _sqlite_dir(url: str) -> None:
    if url.startswith("sqlite:///"):
        Path(url.removeprefix("sqlite:///")).parent.mkdir(parents=True, exist_ok=True)


def _ensure_wal(cur, attempts: int = 100) -> None:
    """Puts the SQLite file in WAL mode, a property of the file kept once set. Setting it takes a lock
    without waiting for it, so processes opening a new database at the same instant may find it taken
    ("database is locked"): then one of them is converting the file, and the others wait for that."""
    for _ in range(attempts):
        if str(cur.execute("PRAGMA journal_mode").fetchone()[0]).lower() == "wal":
            return
        try:
            cur.execute("PRAGMA journal_mode=WAL")
        except sqlite3.OperationalError as exc:
            if "locked" not in str(exc):
                raise
            time.sleep(0.05)
    raise sqlite3.OperationalError("database is locked: could not put it in WAL mode")


def make_engine(url: str) -> Engine:
    _sqlite_dir(url)
    if url.startswith("sqlite:///"):
        # a writer waits up to 30 s for another process's write (the service, a job, a CLI command)
        engine = create_engine(url, connect_args={"check_same_thread": False, "timeout": 30.0})

        @event.listens_for(engine, "connect")
        def _wal(dbapi_conn, _record) -> None:
            cur = dbapi_conn.cursor()
            _ensure_wal(cur)
            cur.execute("PRAGMA synchronous=NORMAL")
            cur.execute("PRAGMA foreign_keys=ON")
            cur.close()

        return engine
    return create_engine(url, pool_pre_ping=True)


def migrate(url: str) -> None:
    """Applies every Alembic migration up to head."""
    _sqlite_dir(url)
    cfg = Config()
    cfg.set_main_option("script_location", str(MIGRATIONS))
    cfg.set_main_option("sqlalchemy.url", url.replace("%", "%%"))
    command.upgrade(cfg, "head")
    if url.startswith("sqlite:///"):  # in WAL mode from its creation, before several processes open it
        engine = make_engine(url)
        engine.connect().close()
        engine.dispose()


def session_factory(engine: Engine) -> sessionmaker:
    return sessionmaker(engine, expire_on_commit=False)
