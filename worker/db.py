"""The service's state in SQL (SQLAlchemy 2) that the workers share with the gateway: scenes,
environment maps, jobs, their stages, attempts and artifacts. The gateway's own tables (API keys,
dashboard sessions, idempotency keys) are in :mod:`services.db`, on the same metadata.

SQLite is the embedded default (one machine, no setup; WAL mode so a gateway and workers can
share the file); PostgreSQL by URL for several machines. The database is the truth: Redis only
holds the queue, and :func:`worker.queue.reconcile` rebuilds the queue from the ``jobs`` table.
"""

from __future__ import annotations

import os
import threading
import uuid
from contextlib import contextmanager
from datetime import datetime, timezone
from typing import Any, Iterator

from sqlalchemy import (
    JSON, Boolean, DateTime, Float, ForeignKey, Integer, String, Text, TypeDecorator, UniqueConstraint,
    create_engine, event, select, update,
)
from sqlalchemy.engine import Engine
from sqlalchemy.orm import DeclarativeBase, Mapped, Session, mapped_column, relationship, sessionmaker


def utcnow() -> datetime:
    return datetime.now(timezone.utc)


def new_id() -> str:
    return uuid.uuid4().hex[:16]


class UTCDateTime(TypeDecorator):
    """Timezone-aware UTC datetimes on every backend (SQLite returns naive ones otherwise)."""

    impl = DateTime(timezone=True)
    cache_ok = True

    def process_bind_param(self, value, dialect):
        if value is not None and value.tzinfo is None:
            raise ValueError("naive datetime stored; use worker.db.utcnow()")
        return value

    def process_result_value(self, value, dialect):
        if value is not None and value.tzinfo is None:
            value = value.replace(tzinfo=timezone.utc)
        return value


class Base(DeclarativeBase):
    type_annotation_map = {datetime: UTCDateTime, dict[str, Any]: JSON, list[Any]: JSON}


class Scene(Base):
    __tablename__ = "scenes"
    id: Mapped[str] = mapped_column(String(32), primary_key=True, default=new_id)
    tenant: Mapped[str] = mapped_column(String(64), index=True)
    name: Mapped[str] = mapped_column(String(256))
    created_at: Mapped[datetime] = mapped_column(default=utcnow, index=True)
    storage_key: Mapped[str] = mapped_column(String(512), comment="archive in the artifact store")
    archive_format: Mapped[str] = mapped_column(String(16))
    size_bytes: Mapped[int] = mapped_column(Integer)
    frames: Mapped[int] = mapped_column(Integer)
    train_frames: Mapped[int] = mapped_column(Integer)
    test_frames: Mapped[int] = mapped_column(Integer)
    cameras: Mapped[list[Any]] = mapped_column(default=list)
    times: Mapped[int] = mapped_column(Integer)
    objects: Mapped[int] = mapped_column(Integer)
    lidar_sweeps: Mapped[int] = mapped_column(Integer)
    has_ground_truth: Mapped[bool] = mapped_column(Boolean)


class Envmap(Base):
    __tablename__ = "envmaps"
    id: Mapped[str] = mapped_column(String(32), primary_key=True, default=new_id)
    tenant: Mapped[str] = mapped_column(String(64), index=True)
    name: Mapped[str] = mapped_column(String(256))
    format: Mapped[str] = mapped_column(String(8))
    width: Mapped[int] = mapped_column(Integer)
    height: Mapped[int] = mapped_column(Integer)
    size_bytes: Mapped[int] = mapped_column(Integer)
    storage_key: Mapped[str] = mapped_column(String(512))
    created_at: Mapped[datetime] = mapped_column(default=utcnow)


class Job(Base):
    __tablename__ = "jobs"
    id: Mapped[str] = mapped_column(String(32), primary_key=True, default=new_id)
    tenant: Mapped[str] = mapped_column(String(64), index=True)
    scene_id: Mapped[str | None] = mapped_column(ForeignKey("scenes.id"), index=True)
    type: Mapped[str] = mapped_column(String(32))
    queue: Mapped[str] = mapped_column(String(32))
    state: Mapped[str] = mapped_column(String(16), index=True, default="queued")
    stage: Mapped[str | None] = mapped_column(String(64), default=None)
    progress: Mapped[float] = mapped_column(Float, default=0.0)
    eta_s: Mapped[float | None] = mapped_column(Float, default=None)
    params: Mapped[dict[str, Any]] = mapped_column(default=dict)
    schema_version: Mapped[int] = mapped_column(Integer, default=1)
    attempts: Mapped[int] = mapped_column(Integer, default=1,
                                          comment="current attempt number (1 = first run)")
    max_attempts: Mapped[int] = mapped_column(Integer, default=3)
    error: Mapped[str | None] = mapped_column(Text, default=None)
    created_at: Mapped[datetime] = mapped_column(default=utcnow, index=True)
    enqueued_at: Mapped[datetime | None] = mapped_column(default=None)
    started_at: Mapped[datetime | None] = mapped_column(default=None)
    finished_at: Mapped[datetime | None] = mapped_column(default=None)
    heartbeat_at: Mapped[datetime | None] = mapped_column(default=None)
    worker_name: Mapped[str | None] = mapped_column(String(128), default=None)
    stages: Mapped[list["JobStage"]] = relationship(order_by="JobStage.id", cascade="all, delete-orphan",
                                                    lazy="select")

    @property
    def rq_job_id(self) -> str:
        return rq_job_id(self.id, self.attempts)


def rq_job_id(job_id: str, attempt: int, stage: str | None = None) -> str:
    """The RQ job of one attempt (of one stage, for chained job types): a retry is a new RQ job,
    so a stale attempt can never be confused with the current one."""
    return f"{job_id}-a{attempt}" + (f"-{stage}" if stage else "")


class JobStage(Base):
    __tablename__ = "job_stages"
    __table_args__ = (UniqueConstraint("job_id", "name"),)
    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    job_id: Mapped[str] = mapped_column(ForeignKey("jobs.id", ondelete="CASCADE"), index=True)
    name: Mapped[str] = mapped_column(String(64))
    state: Mapped[str] = mapped_column(String(16), default="queued")
    progress: Mapped[float] = mapped_column(Float, default=0.0)
    started_at: Mapped[datetime | None] = mapped_column(default=None)
    finished_at: Mapped[datetime | None] = mapped_column(default=None)
    metrics: Mapped[dict[str, Any]] = mapped_column(default=dict)


class JobAttempt(Base):
    """One attempt of a job: when it was queued, started and ended, on which worker, how it
    ended and why (the reason a retry was needed). ``queued_s`` of a job sums the attempts'
    waits, so a dead attempt's run time never counts as waiting."""

    __tablename__ = "job_attempts"
    __table_args__ = (UniqueConstraint("job_id", "attempt"),)
    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    job_id: Mapped[str] = mapped_column(ForeignKey("jobs.id", ondelete="CASCADE"), index=True)
    attempt: Mapped[int] = mapped_column(Integer)
    queued_at: Mapped[datetime] = mapped_column(default=utcnow)
    started_at: Mapped[datetime | None] = mapped_column(default=None)
    finished_at: Mapped[datetime | None] = mapped_column(default=None)
    worker_name: Mapped[str | None] = mapped_column(String(128), default=None)
    outcome: Mapped[str] = mapped_column(String(16), default="queued",
                                         comment="queued, running, done, failed, canceled, retried")
    reason: Mapped[str | None] = mapped_column(Text, default=None)


def attempt_started(session: Session, job_id: str, attempt: int, worker: str | None, now: datetime) -> None:
    """Record that ``attempt`` started (its row is created if a retry path did not make it)."""
    n = session.execute(update(JobAttempt).where(JobAttempt.job_id == job_id, JobAttempt.attempt == attempt,
                                                 JobAttempt.started_at.is_(None))
                        .values(started_at=now, worker_name=worker, outcome="running")).rowcount
    if not n and session.scalar(select(JobAttempt.id).where(JobAttempt.job_id == job_id,
                                                            JobAttempt.attempt == attempt)) is None:
        job = session.get(Job, job_id)
        queued = (job.created_at if attempt == 1 else job.enqueued_at) or now
        session.add(JobAttempt(job_id=job_id, attempt=attempt, queued_at=min(queued, now), started_at=now,
                               worker_name=worker, outcome="running"))


def attempt_ended(session: Session, job_id: str, attempt: int, outcome: str, reason: str | None = None,
                  next_attempt: bool = False) -> None:
    """Close ``attempt`` with ``outcome`` and ``reason``; with ``next_attempt`` the retry's row
    (attempt + 1, queued now) is created too."""
    now = utcnow()
    n = session.execute(update(JobAttempt).where(JobAttempt.job_id == job_id, JobAttempt.attempt == attempt)
                        .values(finished_at=now, outcome=outcome, reason=reason)).rowcount
    if not n:
        job = session.get(Job, job_id)
        session.add(JobAttempt(job_id=job_id, attempt=attempt, queued_at=job.created_at if job else now,
                               started_at=job.started_at if job else None, finished_at=now, outcome=outcome,
                               reason=reason, worker_name=job.worker_name if job else None))
    if next_attempt:
        session.add(JobAttempt(job_id=job_id, attempt=attempt + 1, queued_at=now))


def pending_stage_names(session: Session, job_id: str) -> list[str]:
    """The stages of a job that are not done, in chain order (inside the caller's session, so a
    claim can read and update in one transaction)."""
    return list(session.scalars(select(JobStage.name).where(JobStage.job_id == job_id, JobStage.state != "done")
                                .order_by(JobStage.id)))


class Artifact(Base):
    __tablename__ = "artifacts"
    __table_args__ = (UniqueConstraint("job_id", "name"),)
    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    job_id: Mapped[str] = mapped_column(ForeignKey("jobs.id", ondelete="CASCADE"), index=True)
    name: Mapped[str] = mapped_column(String(512))
    kind: Mapped[str] = mapped_column(String(16))
    content_type: Mapped[str] = mapped_column(String(64))
    size_bytes: Mapped[int] = mapped_column(Integer)
    storage_key: Mapped[str] = mapped_column(String(1024))
    created_at: Mapped[datetime] = mapped_column(default=utcnow)


def _sqlite_pragmas(dbapi_conn, _record):
    cur = dbapi_conn.cursor()
    cur.execute("PRAGMA journal_mode=WAL")
    cur.execute("PRAGMA busy_timeout=30000")
    cur.execute("PRAGMA foreign_keys=ON")
    cur.execute("PRAGMA synchronous=NORMAL")
    cur.close()


class Database:
    """An engine and a session factory for one URL; create with :func:`get_database`."""

    def __init__(self, url: str):
        self.url = url
        if url.startswith("sqlite"):
            path = url.split("///", 1)[-1]
            if path and path != ":memory:":
                os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
            self.engine: Engine = create_engine(url, connect_args={"check_same_thread": False, "timeout": 30})
            event.listen(self.engine, "connect", _sqlite_pragmas)
        else:
            self.engine = create_engine(url, pool_pre_ping=True, pool_size=10, max_overflow=20)
        self.sessions = sessionmaker(self.engine, expire_on_commit=False)

    def create_all(self) -> None:
        Base.metadata.create_all(self.engine)

    @contextmanager
    def session(self) -> Iterator[Session]:
        s = self.sessions()
        try:
            yield s
            s.commit()
        except BaseException:
            s.rollback()
            raise
        finally:
            s.close()

    @contextmanager
    def read(self):
        """A plain connection for read-only Core queries (about half the cost of an ORM session:
        the gateway's status and listing routes use it)."""
        with self.engine.connect() as c:
            yield c

    def ping(self) -> None:
        from sqlalchemy import text

        with self.engine.connect() as c:
            c.execute(text("SELECT 1"))

    def dispose(self) -> None:
        self.engine.dispose()


_dbs: dict[tuple[str, int], Database] = {}
_lock = threading.Lock()


def get_database(url: str, create: bool = True) -> Database:
    """One :class:`Database` per URL and process (a forked RQ work horse gets its own pool)."""
    key = (url, os.getpid())
    with _lock:
        db = _dbs.get(key)
        if db is None:
            db = Database(url)
            if create:
                db.create_all()
            _dbs[key] = db
        return db
