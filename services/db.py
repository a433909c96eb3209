"""The gateway's own tables (API keys, dashboard sessions, idempotency keys), on the metadata of
:mod:`worker.db` (one database, one schema), and :func:`get_database`, which creates them too.

The workers never read these tables: a worker alone creates only the shared ones, and the gateway
adds its own on start (``CREATE TABLE`` if missing, as before).
"""

from __future__ import annotations

import weakref
from datetime import datetime

from sqlalchemy import ForeignKey, Integer, String, UniqueConstraint
from sqlalchemy.orm import Mapped, mapped_column

from worker import db as shared
from worker.db import Base, Database, new_id, utcnow


class ApiKey(Base):
    __tablename__ = "api_keys"
    id: Mapped[str] = mapped_column(String(32), primary_key=True, default=new_id)
    tenant: Mapped[str] = mapped_column(String(64), index=True)
    scope: Mapped[str] = mapped_column(String(16))
    name: Mapped[str] = mapped_column(String(128), default="")
    key_hash: Mapped[str] = mapped_column(String(64), unique=True)
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    revoked_at: Mapped[datetime | None] = mapped_column(default=None)


class DashboardSession(Base):
    __tablename__ = "dashboard_sessions"
    token_hash: Mapped[str] = mapped_column(String(64), primary_key=True)
    api_key_id: Mapped[str] = mapped_column(ForeignKey("api_keys.id", ondelete="CASCADE"))
    expires_at: Mapped[datetime]


class IdempotencyKey(Base):
    """A client's ``Idempotency-Key``: the first request with a key creates the resource; a repeat
    with the same body returns it; a repeat with another body is refused."""

    __tablename__ = "idempotency_keys"
    __table_args__ = (UniqueConstraint("tenant", "key"),)
    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    tenant: Mapped[str] = mapped_column(String(64))
    key: Mapped[str] = mapped_column(String(255))
    request_hash: Mapped[str] = mapped_column(String(64))
    resource: Mapped[str] = mapped_column(String(16))
    resource_id: Mapped[str] = mapped_column(String(32))
    created_at: Mapped[datetime] = mapped_column(default=utcnow)


GATEWAY_TABLES = (ApiKey.__table__, DashboardSession.__table__, IdempotencyKey.__table__)
_ready: weakref.WeakSet[Database] = weakref.WeakSet()


def get_database(url: str) -> Database:
    """:func:`worker.db.get_database` with the gateway's tables created (once per process and URL,
    even when a worker in this process opened the database first)."""
    db = shared.get_database(url)
    if db not in _ready:
        Base.metadata.create_all(db.engine, tables=list(GATEWAY_TABLES))
        _ready.add(db)
    return db


def queued_seconds(created_at: datetime, started_at: datetime | None, attempts: list) -> float | None:
    """Time a job spent waiting for a worker: the sum of its attempts' waits (queued -> started);
    without attempt rows (jobs older than the table), submission to the last start."""
    if started_at is None:
        return None
    waits = [(a.started_at - a.queued_at).total_seconds() for a in attempts if a.started_at is not None]
    if not waits:
        return (started_at - created_at).total_seconds()
    return max(sum(waits), 0.0)
