"""API keys (stored as SHA-256 hashes) with scopes ``operator`` and ``client``, tenants, and
dashboard sessions.

A key is ``brdf_`` + 43 random URL-safe characters (256 bits), so a plain SHA-256 is a safe
hash: there is nothing to brute-force. A client sees only its tenant's scenes, jobs and
artifacts, and anything else answers 404 (never 403: it must not learn that the id exists). An
operator sees every tenant and the dashboard. Keys are sent as ``Authorization: Bearer <key>``
or ``X-API-Key: <key>``; the dashboard's session cookie is accepted for GET/HEAD, and for other
methods only with the session's ``X-CSRF-Token`` header (:func:`csrf_token`, embedded in the
dashboard page): a cross-site form can neither read the token nor send the header, so it can
never change anything. The dashboard's buttons call the same routes a client does.
"""

from __future__ import annotations

import hashlib
import secrets
import threading
import time
from dataclasses import dataclass
from datetime import timedelta

from fastapi import HTTPException, Request
from sqlalchemy import select

from services.db import ApiKey, DashboardSession
from worker.db import Database, utcnow

SESSION_COOKIE = "brdf_session"
SCOPES = ("operator", "client")


def hash_secret(secret: str) -> str:
    return hashlib.sha256(secret.encode("utf-8")).hexdigest()


def csrf_token(session_token: str) -> str:
    """The anti-CSRF token of a dashboard session (derived from its secret cookie)."""
    return hashlib.sha256(b"brdf-csrf:" + session_token.encode("utf-8")).hexdigest()


def generate_key() -> str:
    return "brdf_" + secrets.token_urlsafe(32)


@dataclass(frozen=True)
class Principal:
    key_id: str
    tenant: str
    scope: str

    @property
    def operator(self) -> bool:
        return self.scope == "operator"


def create_key(db: Database, tenant: str, scope: str, name: str = "", secret: str | None = None) -> tuple[str, ApiKey]:
    """Register a key; returns (secret, row). The secret is not stored."""
    if scope not in SCOPES:
        raise ValueError(f"scope: expected one of {SCOPES}, got {scope!r}")
    if not tenant:
        raise ValueError("tenant: must not be empty")
    secret = secret or generate_key()
    with db.session() as s:
        existing = s.scalar(select(ApiKey).where(ApiKey.key_hash == hash_secret(secret)))
        if existing is not None:
            return secret, existing
        row = ApiKey(tenant=tenant, scope=scope, name=name, key_hash=hash_secret(secret))
        s.add(row)
    return secret, row


class Authenticator:
    """Verifies keys against the database, caching a verified key for ``cache_s`` seconds."""

    def __init__(self, db: Database, cache_s: float, session_ttl_s: int):
        self.db = db
        self.cache_s = cache_s
        self.session_ttl_s = session_ttl_s
        self._cache: dict[str, tuple[float, Principal | None]] = {}
        self._lock = threading.Lock()

    def _lookup(self, key_hash: str) -> Principal | None:
        now = time.monotonic()
        with self._lock:
            hit = self._cache.get(key_hash)
        if hit is not None and hit[0] > now:
            return hit[1]
        with self.db.session() as s:
            row = s.scalar(select(ApiKey).where(ApiKey.key_hash == key_hash, ApiKey.revoked_at.is_(None)))
            p = Principal(row.id, row.tenant, row.scope) if row else None
        with self._lock:
            if len(self._cache) > 10_000:
                self._cache.clear()
            self._cache[key_hash] = (now + self.cache_s, p)
        return p

    def from_key(self, secret: str) -> Principal | None:
        return self._lookup(hash_secret(secret)) if secret else None

    def from_session(self, token: str) -> Principal | None:
        if not token:
            return None
        th = hash_secret(token)
        with self.db.session() as s:
            row = s.get(DashboardSession, th)
            if row is None or row.expires_at < utcnow():
                return None
            key = s.get(ApiKey, row.api_key_id)
            if key is None or key.revoked_at is not None:
                return None
            return Principal(key.id, key.tenant, key.scope)

    def new_session(self, p: Principal) -> str:
        token = secrets.token_urlsafe(32)
        with self.db.session() as s:
            s.add(DashboardSession(token_hash=hash_secret(token), api_key_id=p.key_id,
                                   expires_at=utcnow() + timedelta(seconds=self.session_ttl_s)))
        return token

    def end_session(self, token: str) -> None:
        with self.db.session() as s:
            row = s.get(DashboardSession, hash_secret(token))
            if row is not None:
                s.delete(row)

    def authenticate(self, request: Request, allow_cookie: bool = True) -> Principal:
        auth = request.headers.get("authorization", "")
        secret = ""
        if auth[:7].lower() == "bearer ":
            secret = auth[7:].strip()
        elif request.headers.get("x-api-key"):
            secret = request.headers["x-api-key"].strip()
        if secret:
            p = self.from_key(secret)
            if p is None:
                raise HTTPException(401, "invalid or revoked API key", headers={"WWW-Authenticate": "Bearer"})
            return p
        cookie = request.cookies.get(SESSION_COOKIE, "")
        if allow_cookie and cookie and (request.method in ("GET", "HEAD") or secrets.compare_digest(
                request.headers.get("x-csrf-token", ""), csrf_token(cookie))):
            p = self.from_session(cookie)
            if p is not None:
                return p
        raise HTTPException(401, "missing API key: send 'Authorization: Bearer <key>' or 'X-API-Key: <key>'",
                            headers={"WWW-Authenticate": "Bearer"})
