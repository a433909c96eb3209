"""What the gateway's routers share: error and response helpers, the ``JobOut`` document built
without re-validation (the hot status path), authentication dependencies, path and header
parameter types, and :class:`Ctx`, the app's settings, database, store and Redis with the
queries the routers share (:func:`make_context`)."""

from __future__ import annotations

import hashlib
import json
import shutil
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Callable

import anyio
import pydantic_core
import redis
from fastapi import APIRouter, Depends, Header, HTTPException, Path as PathParam, Request
from fastapi.responses import JSONResponse, Response
from sqlalchemy import func, select

import api_schemas as S
from services.auth import Authenticator, Principal
from services.metrics import Registry
from services.db import IdempotencyKey, queued_seconds
from worker.db import Database, Envmap, Job, JobAttempt, JobStage, Scene, utcnow
from worker.settings import Settings
from worker.storage import ArtifactStore

SCENE_TYPES = {"application/zip", "application/x-zip-compressed", "application/gzip", "application/x-gzip",
               "application/x-tar+gzip", "application/x-compressed-tar", "application/octet-stream"}
ENVMAP_TYPES = {"image/x-exr", "image/aces", "image/vnd.radiance", "image/x-hdr", "application/octet-stream"}
UPLOAD_PATHS = ("/scenes", "/envmaps")

E = {code: {"model": S.ErrorOut} for code in (400, 401, 404, 409, 413, 415, 422)}


def _err(code: int, detail: str, errors: list[str] | None = None) -> HTTPException:
    e = HTTPException(code, detail)
    e.errors = errors or []  # type: ignore[attr-defined]
    return e


def ok(model, status: int = 200, headers: dict | None = None) -> Response:
    """A validated model serialized once by pydantic-core (FastAPI would validate and encode the
    returned model a second time: a measurable cost on the hot status/listing routes)."""
    return Response(model.model_dump_json(), status_code=status, media_type="application/json", headers=headers)


def _fingerprint(*parts) -> str:
    return hashlib.sha256(json.dumps(parts, sort_keys=True, default=str).encode()).hexdigest()


# --- conversions ------------------------------------------------------------------------------

def scene_out(s: Scene) -> S.SceneOut:
    return S.SceneOut(id=s.id, name=s.name, created_at=s.created_at, frames=s.frames, train_frames=s.train_frames,
                      test_frames=s.test_frames, cameras=list(s.cameras or []), times=s.times, objects=s.objects,
                      lidar_sweeps=s.lidar_sweeps, has_ground_truth=s.has_ground_truth, size_bytes=s.size_bytes)


def attempt_out(a) -> dict:
    return {"attempt": a.attempt, "outcome": a.outcome, "reason": a.reason, "worker": a.worker_name,
            "queued_at": a.queued_at, "started_at": a.started_at, "finished_at": a.finished_at}


def job_out(j, stages=None, attempts=()) -> dict:
    """The ``JobOut`` document of ``j`` (a Job or a row of the jobs table) as a plain dict, ready
    for :func:`ok_json`: the status and listing routes are the hot path, and building pydantic
    models for every job and stage costs more than the queries. ``test_job_out_is_valid`` checks
    that the result validates as ``JobOut``. ``stages``: its stage rows (default j.stages);
    ``attempts``: its attempt rows (oldest first)."""
    now = utcnow()
    queued_s = queued_seconds(j.created_at, j.started_at, attempts)
    run_s = None
    if j.started_at:
        run_s = ((j.finished_at or now) - j.started_at).total_seconds() if j.state != "queued" else None
    stage_rows = j.stages if stages is None else stages
    return {
        "id": j.id, "type": j.type, "scene_id": j.scene_id, "state": j.state, "stage": j.stage,
        "progress": min(max(j.progress or 0.0, 0.0), 1.0), "eta_s": j.eta_s if j.state == "running" else None,
        "attempts": j.attempts, "max_attempts": j.max_attempts, "error": j.error,
        "timings": {"created_at": j.created_at, "started_at": j.started_at, "finished_at": j.finished_at,
                    "queued_s": queued_s, "run_s": run_s},
        "stages": [{"name": st.name, "state": st.state, "progress": min(max(st.progress, 0.0), 1.0),
                    "started_at": st.started_at, "finished_at": st.finished_at, "metrics": st.metrics or {}}
                   for st in stage_rows],
        "attempt_history": [attempt_out(a) for a in attempts],
        "params": j.params or {}, "artifacts_url": f"/jobs/{j.id}/artifacts"}


def ok_json(doc, status: int = 200) -> Response:
    """A plain document serialized by pydantic-core (same JSON as the models: ISO datetimes)."""
    return Response(pydantic_core.to_json(doc), status_code=status, media_type="application/json")


def envmap_out(e: Envmap) -> S.EnvmapOut:
    return S.EnvmapOut(id=e.id, name=e.name, format=e.format, width=e.width, height=e.height,
                       size_bytes=e.size_bytes, created_at=e.created_at)


# --- authentication and parameters ------------------------------------------------------------
# async dependencies run on the event loop: no thread hop per request (a verified key is cached,
# so the database is read at most once per key and auth_cache_s)
async def principal(request: Request) -> Principal:
    return request.app.state.auth.authenticate(request)


async def operator(p: Annotated[Principal, Depends(principal)]) -> Principal:
    if not p.operator:
        raise _err(404, "not found")
    return p


P = Annotated[Principal, Depends(principal)]
Operator = Annotated[Principal, Depends(operator)]
IdPath = Annotated[str, PathParam(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_-]+$")]
IdemKey = Annotated[str | None, Header(alias="Idempotency-Key", max_length=255,
                                       description="repeat-safe submission key (per tenant)")]


def visible(stmt, model, p: Principal):
    return stmt if p.operator else stmt.where(model.tenant == p.tenant)


def page_total(c, q, n_rows: int, limit: int, offset: int) -> int:
    if offset == 0 and n_rows < limit:
        return n_rows
    return c.scalar(select(func.count()).select_from(q.subquery()))


async def stream_upload(request: Request, dest: Path, limit: int, what: str) -> tuple[int, str]:
    cl = request.headers.get("content-length")
    if cl is not None and cl.isdigit() and int(cl) > limit:
        raise _err(413, f"{what} of {int(cl)} bytes exceeds the upload limit of {limit} bytes")
    h = hashlib.sha256()
    n = 0
    with open(dest, "wb") as fh:
        async for chunk in request.stream():
            n += len(chunk)
            if n > limit:
                raise _err(413, f"{what} exceeds the upload limit of {limit} bytes")
            h.update(chunk)
            fh.write(chunk)
    if n == 0:
        raise _err(400, f"empty body: send the {what} as the request body")
    return n, h.hexdigest()


def binary_body(description: str, *types: str) -> dict:
    """The ``openapi_extra`` of a route whose body is a raw file of one of the media ``types``."""
    return {"requestBody": {"required": True, "description": description,
                            "content": {t: {"schema": {"type": "string", "format": "binary"}} for t in types}}}


def require_content_type(request: Request, accepted: set[str], send: str) -> None:
    """415 unless the request's Content-Type is one of ``accepted``; ``send`` says what to send."""
    ctype = request.headers.get("content-type", "").split(";")[0].strip().lower()
    if ctype not in accepted:
        raise _err(415, f"Content-Type {ctype or '(none)'!r} not accepted: send {send}")


async def receive_upload(request: Request, data_dir: Path, limit: int, what: str, ingest: Callable):
    """Stream the body into a new work directory under ``data_dir/uploads`` (at most ``limit``
    bytes; ``what`` names it in errors), run ``ingest(upload, work, size, sha256)`` in a thread
    and remove the work directory; what ``ingest`` returns."""
    work = data_dir / "uploads" / uuid.uuid4().hex
    work.mkdir(parents=True)
    try:
        upload = work / "upload.bin"
        size, digest = await stream_upload(request, upload, limit, what)
        return await anyio.to_thread.run_sync(ingest, upload, work, size, digest)
    finally:
        await anyio.to_thread.run_sync(lambda: shutil.rmtree(work, ignore_errors=True))


def created(model, replay: bool, location: str) -> JSONResponse:
    """An upload's answer: 201 with its Location, or 200 when an idempotent repeat replays it."""
    return JSONResponse(model.model_dump(mode="json"), status_code=200 if replay else 201,
                        headers={"Location": location})


# --- the app's context ------------------------------------------------------------------------
jobs_t, stages_t, attempts_t = Job.__table__, JobStage.__table__, JobAttempt.__table__


@dataclass
class Ctx:
    """The app's dependencies, made once by :func:`services.app.create_app` and bound into each
    router by its ``build(ctx)`` (no per-request dependency resolution on the hot path)."""

    settings: Settings
    db: Database
    store: ArtifactStore
    auth: Authenticator
    registry: Registry
    rconn: Callable[[], redis.Redis]
    unserved_queues: Callable[[], list[str]] | None = None
    version: str = "0.1.0"
    jobs_t = jobs_t
    stages_t = stages_t
    attempts_t = attempts_t

    def get_scene(self, s, scene_id: str, p: Principal) -> Scene:
        sc = s.scalar(visible(select(Scene).where(Scene.id == scene_id), Scene, p))
        if sc is None:
            raise _err(404, f"scene {scene_id!r} not found")
        return sc

    def get_job(self, s, job_id: str, p: Principal) -> Job:
        j = s.scalar(visible(select(Job).where(Job.id == job_id), Job, p))
        if j is None:
            raise _err(404, f"job {job_id!r} not found")
        return j

    def job_rows(self, s, stmt) -> list:  # s: a connection or a session
        """Jobs with their stages and attempts by three Core queries (the hot status/listing
        path: no ORM)."""
        rows = s.execute(stmt).all()
        st: dict[str, list] = {r.id: [] for r in rows}
        at: dict[str, list] = {r.id: [] for r in rows}
        if rows:
            for r in s.execute(select(stages_t).where(stages_t.c.job_id.in_(list(st))).order_by(stages_t.c.id)):
                st[r.job_id].append(r)
            for r in s.execute(select(attempts_t).where(attempts_t.c.job_id.in_(list(at)))
                               .order_by(attempts_t.c.attempt)):
                at[r.job_id].append(r)
        return [job_out(r, st[r.id], at[r.id]) for r in rows]

    def read_job_out(self, s, job_id: str, p: Principal) -> dict:
        q = select(jobs_t).where(jobs_t.c.id == job_id)
        out = self.job_rows(s, q if p.operator else q.where(jobs_t.c.tenant == p.tenant))
        if not out:
            raise _err(404, f"job {job_id!r} not found")
        return out[0]

    def idem_lookup(self, s, p: Principal, key: str | None, fingerprint: str, resource: str) -> str | None:
        if not key:
            return None
        rec = s.scalar(select(IdempotencyKey).where(IdempotencyKey.tenant == p.tenant, IdempotencyKey.key == key))
        if rec is None:
            return None
        if rec.request_hash != fingerprint or rec.resource != resource:
            raise _err(409, f"Idempotency-Key {key!r} was already used with a different request")
        return rec.resource_id


def route_context(ctx: Ctx) -> tuple[APIRouter, Settings, Database, ArtifactStore]:
    """What a router's ``build(ctx)`` starts from: a new router and the context's settings,
    database and store, bound once as locals that its handlers close over."""
    return APIRouter(), ctx.settings, ctx.db, ctx.store
