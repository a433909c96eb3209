"""The FastAPI gateway: ``create_app(settings)``; ``brdf serve`` runs it under uvicorn.

Routes (every body is an ``api_schemas`` model; every error an ``ErrorOut``):

- ``POST /scenes`` (a .zip / .tar.gz bundle as the raw body, streamed to disk under a size cap,
  unpacked safely and validated by ``core.bundle``), ``GET /scenes``, ``GET /scenes/{id}``;
- ``POST /scenes/{id}/render`` (the export render, queued), ``/relight``, ``/night``,
  ``/reconstruct`` (validated; 409 "not available in this build" until their pipeline is
  registered as a job type: never a fake job);
- ``POST /envmaps`` (.exr / .hdr, NaN/Inf rejected), ``GET /envmaps``, ``GET /envmaps/{id}``;
- ``GET /jobs``, ``GET /jobs/{id}``, ``DELETE /jobs/{id}`` (cancel), ``GET /jobs/{id}/artifacts``,
  ``GET|HEAD /jobs/{id}/artifacts/{name}`` (HTTP Range);
- ``POST /keys``, ``GET /system`` (operator); ``GET /healthz``, ``/readyz``, ``/metrics``;
- ``/dashboard`` (see :mod:`services.dashboard`).
"""


import asyncio
import contextlib
import hashlib
import json
import logging
import os
import shutil
import uuid
from pathlib import Path
from typing import Annotated

import anyio
import pydantic_core
import redis
from fastapi import Depends, FastAPI, Header, HTTPException, Path as PathParam, Query, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, PlainTextResponse, Response
from sqlalchemy import func, select
from sqlalchemy.exc import IntegrityError

import api_schemas as S
from services.auth import Authenticator, Principal, create_key
from services.metrics import MetricsMiddleware, Registry
from services.ranges import file_response
from worker.db import Artifact, Envmap, IdempotencyKey, Job, JobStage, Scene, get_database, new_id, utcnow
from worker.queue import list_workers, queue_stats, reconcile, redis_conn, request_cancel, try_enqueue
from worker.registry import job_type
from worker.settings import Settings, get_settings
from worker.storage import StorageError, get_store

log = logging.getLogger("brdf.gateway")
VERSION = "0.1.0"
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


def job_out(j, stages=None) -> dict:
    """The ``JobOut`` document of ``j`` (a Job or a row of the jobs table) as a plain dict, ready
    for :func:`ok_json`: the status and listing routes are the hot path, and building pydantic
    models for every job and stage costs more than the queries. ``test_job_out_is_valid`` checks
    that the result validates as ``JobOut``. ``stages``: its stage rows (default j.stages)."""
    now = utcnow()
    queued_s = (j.started_at - j.created_at).total_seconds() if j.started_at else None
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
        "params": j.params or {}, "artifacts_url": f"/jobs/{j.id}/artifacts"}


def ok_json(doc, status: int = 200) -> Response:
    """A plain document serialized by pydantic-core (same JSON as the models: ISO datetimes)."""
    return Response(pydantic_core.to_json(doc), status_code=status, media_type="application/json")


def envmap_out(e: Envmap) -> S.EnvmapOut:
    return S.EnvmapOut(id=e.id, name=e.name, format=e.format, width=e.width, height=e.height,
                       size_bytes=e.size_bytes, created_at=e.created_at)


# --- the app ----------------------------------------------------------------------------------

def create_app(settings: Settings | None = None) -> FastAPI:
    settings = settings or get_settings()
    settings.data_dir.mkdir(parents=True, exist_ok=True)
    db = get_database(settings.db_url)
    store = get_store(settings.store_url, settings.artifact_store_options)
    auth = Authenticator(db, settings.auth_cache_s, settings.session_ttl_s)
    registry = Registry()
    if settings.bootstrap_operator_key:
        create_key(db, "operator", "operator", "bootstrap", secret=settings.bootstrap_operator_key)

    def rconn() -> redis.Redis:
        return redis_conn(settings.redis_url)

    @contextlib.asynccontextmanager
    async def lifespan(app: FastAPI):
        async def loop():
            while True:
                try:
                    done = await anyio.to_thread.run_sync(reconcile, settings, db, rconn())
                    if any(done.values()):
                        log.info("reconcile: %s", done)
                except Exception as e:  # noqa: BLE001 - Redis down: try again next round
                    log.warning("reconcile failed: %s", e)
                await asyncio.sleep(settings.reconcile_interval_s)

        task = asyncio.create_task(loop())
        try:
            yield
        finally:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task

    app = FastAPI(
        title="BRDFusion rendering service", version=VERSION, lifespan=lifespan,
        summary=f"API version {S.API_VERSION}: upload driving scenes, queue renders, fetch EXR/MP4/PNG results.",
        description="Authenticate with `Authorization: Bearer <key>` (or `X-API-Key`). A client key sees only "
                    "its tenant's resources; others answer 404. Job submissions accept an `Idempotency-Key` "
                    "header: a repeat with the same body returns the same job.",
    )
    app.state.settings, app.state.db, app.state.store, app.state.auth = settings, db, store, auth
    app.state.metrics, app.state.rconn = registry, rconn
    app.add_middleware(MetricsMiddleware, registry=registry, max_body=settings.max_request_json_bytes,
                       upload_paths=UPLOAD_PATHS)

    @app.exception_handler(HTTPException)
    async def http_error(request: Request, exc: HTTPException):
        return JSONResponse({"detail": exc.detail if isinstance(exc.detail, str) else str(exc.detail),
                             "errors": getattr(exc, "errors", [])}, status_code=exc.status_code,
                            headers=exc.headers)

    @app.exception_handler(RequestValidationError)
    async def validation_error(request: Request, exc: RequestValidationError):
        errors = []
        for e in exc.errors():
            loc = ".".join(str(x) for x in e.get("loc", ()))
            msg = e.get("msg", "invalid")
            if e.get("type") == "json_invalid":
                msg = f"malformed JSON: {e.get('ctx', {}).get('error', msg)}"
            errors.append(f"{loc}: {msg}")
        return JSONResponse({"detail": f"invalid request ({len(errors)} problem(s)): {errors[0] if errors else ''}",
                             "errors": errors}, status_code=422)

    # async dependencies run on the event loop: no thread hop per request (a verified key is cached,
    # so the database is read at most once per key and auth_cache_s)
    async def principal(request: Request) -> Principal:
        return auth.authenticate(request)

    async def operator(p: Annotated[Principal, Depends(principal)]) -> Principal:
        if not p.operator:
            raise _err(404, "not found")
        return p

    P = Annotated[Principal, Depends(principal)]
    IdPath = Annotated[str, PathParam(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_-]+$")]
    IdemKey = Annotated[str | None, Header(alias="Idempotency-Key", max_length=255,
                                           description="repeat-safe submission key (per tenant)")]

    def visible(stmt, model, p: Principal):
        return stmt if p.operator else stmt.where(model.tenant == p.tenant)

    def get_scene(s, scene_id: str, p: Principal) -> Scene:
        sc = s.scalar(visible(select(Scene).where(Scene.id == scene_id), Scene, p))
        if sc is None:
            raise _err(404, f"scene {scene_id!r} not found")
        return sc

    jobs_t, stages_t = Job.__table__, JobStage.__table__

    def job_rows(s, stmt) -> list:  # s: a connection or a session
        """Jobs and their stages by two Core queries (the hot status/listing path: no ORM)."""
        rows = s.execute(stmt).all()
        st: dict[str, list] = {r.id: [] for r in rows}
        if rows:
            for r in s.execute(select(stages_t).where(stages_t.c.job_id.in_(list(st))).order_by(stages_t.c.id)):
                st[r.job_id].append(r)
        return [job_out(r, st[r.id]) for r in rows]

    def read_job_out(s, job_id: str, p: Principal) -> dict:
        q = select(jobs_t).where(jobs_t.c.id == job_id)
        out = job_rows(s, q if p.operator else q.where(jobs_t.c.tenant == p.tenant))
        if not out:
            raise _err(404, f"job {job_id!r} not found")
        return out[0]

    def get_job(s, job_id: str, p: Principal) -> Job:
        j = s.scalar(visible(select(Job).where(Job.id == job_id), Job, p))
        if j is None:
            raise _err(404, f"job {job_id!r} not found")
        return j

    # --- health -----------------------------------------------------------------------------
    @app.get("/healthz", response_model=S.Health, tags=["system"])
    def healthz():
        """The process is up (no dependency checked)."""
        return S.Health(status="ok", version=VERSION)

    @app.get("/readyz", response_model=S.Ready, tags=["system"], responses={503: {"model": S.Ready}})
    def readyz():
        """Database, Redis and the artifact store answer; 503 naming what failed otherwise."""
        checks = {}
        for name, fn in (("database", db.ping), ("redis", lambda: rconn().ping()), ("artifact_store", store.ping)):
            try:
                fn()
                checks[name] = "ok"
            except Exception as e:  # noqa: BLE001
                checks[name] = f"{type(e).__name__}: {e}"[:300]
        ok = all(v == "ok" for v in checks.values())
        return JSONResponse(S.Ready(ready=ok, checks=checks).model_dump(), status_code=200 if ok else 503)

    @app.get("/metrics", response_class=PlainTextResponse, tags=["system"])
    def metrics():
        """Prometheus text format."""
        gauges = []
        with db.session() as s:
            rows = s.execute(select(Job.state, func.count()).group_by(Job.state)).all()
            counts = {st: 0 for st in ("queued", "running", "done", "failed", "canceled")}
            counts.update({k: v for k, v in rows})
            gauges.append(("brdf_jobs", "Jobs by state.", [({"state": k}, v) for k, v in sorted(counts.items())]))
            gauges.append(("brdf_scenes", "Stored scenes.", [({}, s.scalar(select(func.count()).select_from(Scene)))]))
        try:
            c = rconn()
            qs = queue_stats(c)
            ws = list_workers(c)
            gauges.append(("brdf_redis_up", "Redis answers.", [({}, 1)]))
            gauges.append(("brdf_queue_depth", "Jobs waiting in each RQ queue.",
                           [({"queue": q["name"]}, q["queued"]) for q in qs]))
            gauges.append(("brdf_queue_started", "Jobs executing per queue.",
                           [({"queue": q["name"]}, q["started"]) for q in qs]))
            gauges.append(("brdf_workers", "Registered RQ workers.", [({}, len(ws))]))
        except redis.RedisError:
            gauges.append(("brdf_redis_up", "Redis answers.", [({}, 0)]))
        return PlainTextResponse(registry.render(gauges), media_type="text/plain; version=0.0.4")

    # --- keys and system ----------------------------------------------------------------------
    @app.post("/keys", response_model=S.ApiKeyCreated, status_code=201, tags=["admin"], responses=E)
    def create_api_key(body: S.ApiKeyCreate, p: Annotated[Principal, Depends(operator)]):
        """Create an API key for a tenant (operator only). The secret is returned once."""
        secret, row = create_key(db, body.tenant, body.scope.value, body.name)
        return S.ApiKeyCreated(id=row.id, tenant=row.tenant, scope=S.Scope(row.scope), key=secret)

    @app.get("/system", response_model=S.SystemStatus, tags=["admin"], responses=E)
    def system(p: Annotated[Principal, Depends(operator)]):
        """Queue depths and workers with their heartbeats (operator only)."""
        try:
            c = rconn()
            return S.SystemStatus(queues=[S.QueueStats(**q) for q in queue_stats(c)],
                                  workers=[S.WorkerOut(**w) for w in list_workers(c)], redis="ok")
        except redis.RedisError as e:
            return S.SystemStatus(queues=[], workers=[], redis=f"unreachable: {e}")

    # --- scenes -------------------------------------------------------------------------------
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

    def idem_lookup(s, p: Principal, key: str | None, fingerprint: str, resource: str) -> str | None:
        if not key:
            return None
        rec = s.scalar(select(IdempotencyKey).where(IdempotencyKey.tenant == p.tenant, IdempotencyKey.key == key))
        if rec is None:
            return None
        if rec.request_hash != fingerprint or rec.resource != resource:
            raise _err(409, f"Idempotency-Key {key!r} was already used with a different request")
        return rec.resource_id

    def ingest_scene(upload: Path, work: Path, size: int, digest: str, name: str | None, p: Principal,
                     idem: str | None) -> tuple[Scene, bool]:
        from core.bundle import ArchiveLimits, open_bundle, unpack_bundle, validate_bundle
        from core.bundle.archive import archive_kind
        from core.errors import CoreError

        def clean(msg: str) -> str:
            return msg.replace(str(work / "bundle") + "/", "").replace(str(work / "bundle"), "bundle") \
                      .replace(str(upload), "upload")

        fp = _fingerprint("scene", digest, name)
        with db.session() as s:
            existing = idem_lookup(s, p, idem, fp, "scene")
            if existing:
                return s.get(Scene, existing), True
        try:
            kind = archive_kind(upload)
            root = unpack_bundle(upload, work / "bundle", ArchiveLimits(
                max_entries=settings.archive_max_entries, max_total_bytes=settings.archive_max_total_bytes))
            issues = validate_bundle(root)
            if issues:
                raise _err(422, f"scene bundle is invalid ({len(issues)} problem(s)): {clean(str(issues[0]))}",
                           [clean(str(i)) for i in issues])
            b = open_bundle(root, validate=False)
        except CoreError as e:
            raise _err(422, f"scene bundle rejected: {clean(str(e))}") from None
        m = b.manifest
        sid = new_id()
        key = f"scenes/{sid}/bundle.{'zip' if kind == 'zip' else 'tar.gz'}"
        store.put_file(upload, key)
        row = Scene(id=sid, tenant=p.tenant, name=(name or m.name)[:256], storage_key=key, archive_format=kind,
                    size_bytes=size, frames=len(m.frames), train_frames=len(m.split("train")),
                    test_frames=len(m.split("test")), cameras=sorted(m.cameras), times=len(m.times),
                    objects=len(m.objects), lidar_sweeps=len(m.lidar), has_ground_truth=m.ground_truth is not None)
        try:
            with db.session() as s:
                s.add(row)
                if idem:
                    s.add(IdempotencyKey(tenant=p.tenant, key=idem, request_hash=fp, resource="scene", resource_id=sid))
        except IntegrityError:
            store.delete_prefix(f"scenes/{sid}")
            with db.session() as s:
                existing = idem_lookup(s, p, idem, fp, "scene")
                if existing:
                    return s.get(Scene, existing), True
            raise
        except BaseException:
            store.delete_prefix(f"scenes/{sid}")
            raise
        # warm this machine's scene cache (workers elsewhere fetch the archive from the store)
        cache = settings.data_dir / "cache" / "scenes" / sid
        try:
            cache.parent.mkdir(parents=True, exist_ok=True)
            os.replace(work / "bundle", cache)
            (cache / ".complete").write_text(str(cache / root.relative_to(work / "bundle")))
        except OSError as e:
            log.warning("scene %s: cache not warmed: %s", sid, e)
        return row, False

    @app.post("/scenes", response_model=S.SceneOut, status_code=201, tags=["scenes"], responses=E,
              openapi_extra={"requestBody": {"required": True, "description": "a scene bundle as .zip or .tar.gz",
                                             "content": {t: {"schema": {"type": "string", "format": "binary"}}
                                                         for t in ("application/zip", "application/gzip")}}})
    async def upload_scene(request: Request, p: P, idem: IdemKey = None,
                           name: Annotated[str | None, Query(min_length=1, max_length=256)] = None):
        """Upload a scene bundle (the raw .zip / .tar.gz as the body). Streamed to disk under the
        upload limit, unpacked with zip-slip / symlink / zip-bomb protection, validated; nothing is
        stored unless all of it is valid."""
        ctype = request.headers.get("content-type", "").split(";")[0].strip().lower()
        if ctype not in SCENE_TYPES:
            raise _err(415, f"Content-Type {ctype or '(none)'!r} not accepted: send the bundle as application/zip "
                            "or application/gzip (.tar.gz)")
        work = settings.data_dir / "uploads" / uuid.uuid4().hex
        work.mkdir(parents=True)
        try:
            upload = work / "upload.bin"
            size, digest = await stream_upload(request, upload, settings.max_upload_bytes, "scene upload")
            row, replay = await anyio.to_thread.run_sync(ingest_scene, upload, work, size, digest, name, p, idem)
        finally:
            await anyio.to_thread.run_sync(lambda: shutil.rmtree(work, ignore_errors=True))
        return JSONResponse(scene_out(row).model_dump(mode="json"), status_code=200 if replay else 201,
                            headers={"Location": f"/scenes/{row.id}"})

    scenes_t, artifacts_t = Scene.__table__, Artifact.__table__

    # The status and listing routes (the hot path: clients poll them) are ``async def`` and run
    # their short indexed reads on the event loop: no thread hand-off per request, which on a
    # CPU-starved machine measured 20-30% less gateway CPU and a lower p99 (benchmarks/bench_load.py).
    # Everything that writes, uploads or may be slow stays ``def`` (thread pool) or awaits a thread.

    def page_total(c, q, n_rows: int, limit: int, offset: int) -> int:
        if offset == 0 and n_rows < limit:
            return n_rows
        return c.scalar(select(func.count()).select_from(q.subquery()))

    @app.get("/scenes", response_model=S.SceneList, tags=["scenes"], responses=E)
    async def list_scenes(p: P, limit: Annotated[int, Query(ge=1, le=500)] = 50,
                          offset: Annotated[int, Query(ge=0, le=10**9)] = 0):
        with db.read() as c:
            q = select(scenes_t) if p.operator else select(scenes_t).where(scenes_t.c.tenant == p.tenant)
            rows = c.execute(q.order_by(scenes_t.c.created_at.desc(), scenes_t.c.id).limit(limit).offset(offset)).all()
            total = page_total(c, q, len(rows), limit, offset)
        return ok(S.SceneList(items=[scene_out(r) for r in rows], total=total, limit=limit, offset=offset))

    @app.get("/scenes/{scene_id}", response_model=S.SceneOut, tags=["scenes"], responses=E)
    async def read_scene(scene_id: IdPath, p: P):
        q = select(scenes_t).where(scenes_t.c.id == scene_id)
        with db.read() as c:
            row = c.execute(q if p.operator else q.where(scenes_t.c.tenant == p.tenant)).first()
        if row is None:
            raise _err(404, f"scene {scene_id!r} not found")
        return ok(scene_out(row))

    # --- job submission -----------------------------------------------------------------------
    def submit(p: Principal, scene_id: str, type_name: str, params, idem: str | None) -> JSONResponse:
        jt = job_type(type_name)
        with db.session() as s:
            get_scene(s, scene_id, p)
        if jt is None:  # 409, not 501: the request is valid; this build cannot serve it (no 5xx for clients)
            raise _err(409, f"{type_name} is not available in this build: its pipeline stages have not landed "
                            "yet, so no job was queued")
        why = jt.unavailable(params) if jt.unavailable is not None else None
        if why:
            raise _err(409, f"{why}; no job was queued")
        if jt.precondition is not None:
            with db.session() as s:
                why = jt.precondition(s, scene_id, get_scene(s, scene_id, p).tenant)
            if why:
                raise _err(409, f"{why}; no job was queued")
        pj = params.model_dump(mode="json")
        fp = _fingerprint(type_name, scene_id, pj)
        jid = new_id()
        try:
            with db.session() as s:
                existing = idem_lookup(s, p, idem, fp, "job")
                if existing is None:
                    s.add(Job(id=jid, tenant=p.tenant, scene_id=scene_id, type=type_name, queue=jt.queue,
                              state="queued", params=pj, schema_version=S.SCHEMA_VERSION, attempts=1,
                              max_attempts=settings.max_attempts))
                    s.flush()
                    for st in jt.stages_of(params):
                        s.add(JobStage(job_id=jid, name=st))
                    if idem:
                        s.add(IdempotencyKey(tenant=p.tenant, key=idem, request_hash=fp, resource="job",
                                             resource_id=jid))
        except IntegrityError:  # a concurrent request with the same Idempotency-Key won
            with db.session() as s:
                existing = idem_lookup(s, p, idem, fp, "job")
            if existing is None:
                raise
        if existing is None:
            with db.session() as s:
                job = s.get(Job, jid)
            try_enqueue(settings, db, rconn(), job)
        else:
            with db.session() as s:
                job = s.get(Job, existing)
        body = S.JobAccepted(id=job.id, state=S.JobState(job.state), status_url=f"/jobs/{job.id}")
        headers = {"Location": f"/jobs/{job.id}"}
        if existing:
            headers["Idempotent-Replayed"] = "true"
        return JSONResponse(body.model_dump(mode="json"), status_code=202, headers=headers)

    R202 = {**E, 202: {"model": S.JobAccepted, "description": "queued; Location is the job's status URL"}}
    R409 = {**R202, 409: {"model": S.ErrorOut, "description": "this job type is not available in this build "
                                                               "(or the Idempotency-Key was used for another request)"}}

    @app.post("/scenes/{scene_id}/render", status_code=202, response_model=S.JobAccepted, tags=["jobs"],
              responses=R202)
    def render(scene_id: IdPath, body: S.RenderRequest, p: P, idem: IdemKey = None):
        """Queue a render of the scene's frames: multi-layer EXR per frame, MP4 and a PNG preview."""
        return submit(p, scene_id, "render", body, idem)

    @app.post("/scenes/{scene_id}/relight", status_code=202, response_model=S.JobAccepted, tags=["jobs"],
              responses=R409)
    def relight(scene_id: IdPath, body: S.RelightRequest, p: P, idem: IdemKey = None):
        """Relight the reconstructed scene (its latest finished reconstruct job) under another
        environment map, with local lights and object edits: EXR frames, MP4 and a PNG preview.
        409 while the scene has no finished reconstruction."""
        if body.envmap_id is not None:
            with db.session() as s:
                if s.scalar(visible(select(Envmap).where(Envmap.id == body.envmap_id), Envmap, p)) is None:
                    raise _err(404, f"envmap {body.envmap_id!r} not found")
        return submit(p, scene_id, "relight", body, idem)

    @app.post("/scenes/{scene_id}/night", status_code=202, response_model=S.JobAccepted, tags=["jobs"],
              responses=R409)
    def night(scene_id: IdPath, body: S.NightRequest, p: P, idem: IdemKey = None):
        """Night scenario: the scene's sky dimmed, headlights on every tracked object, street lights
        given as ``lights``. 409 while the scene has no finished reconstruction."""
        return submit(p, scene_id, "night", body, idem)

    @app.post("/scenes/{scene_id}/reconstruct", status_code=202, response_model=S.JobAccepted, tags=["jobs"],
              responses=R409)
    def reconstruct(scene_id: IdPath, body: S.ReconstructRequest, p: P, idem: IdemKey = None):
        """Queue the optimization stage chain (409 until the training stages exist)."""
        return submit(p, scene_id, "reconstruct", body, idem)

    # --- jobs ---------------------------------------------------------------------------------
    @app.get("/jobs", response_model=S.JobList, tags=["jobs"], responses=E)
    async def list_jobs(p: P, state: S.JobState | None = None,
                        scene_id: Annotated[str | None, Query(max_length=64)] = None,
                        limit: Annotated[int, Query(ge=1, le=500)] = 50,
                        offset: Annotated[int, Query(ge=0, le=10**9)] = 0):
        with db.read() as c:
            q = select(jobs_t) if p.operator else select(jobs_t).where(jobs_t.c.tenant == p.tenant)
            if state is not None:
                q = q.where(jobs_t.c.state == state.value)
            if scene_id is not None:
                q = q.where(jobs_t.c.scene_id == scene_id)
            items = job_rows(c, q.order_by(jobs_t.c.created_at.desc(), jobs_t.c.id).limit(limit).offset(offset))
            total = page_total(c, q, len(items), limit, offset)
        return ok_json({"items": items, "total": total, "limit": limit, "offset": offset})

    @app.get("/jobs/{job_id}", response_model=S.JobOut, tags=["jobs"], responses=E)
    async def read_job(job_id: IdPath, p: P):
        with db.read() as c:
            return ok_json(read_job_out(c, job_id, p))

    @app.delete("/jobs/{job_id}", response_model=S.JobOut, tags=["jobs"], responses=E)
    def cancel_job(job_id: IdPath, p: P):
        """Cancel a queued or running job (a running one stops within a heartbeat). A finished job
        is returned unchanged."""
        with db.session() as s:
            get_job(s, job_id, p)
        request_cancel(db, rconn(), job_id)
        with db.read() as c:
            return ok_json(read_job_out(c, job_id, p))

    @app.get("/jobs/{job_id}/artifacts", response_model=S.ArtifactList, tags=["artifacts"], responses=E)
    async def list_artifacts(job_id: IdPath, p: P):
        q = select(jobs_t.c.id).where(jobs_t.c.id == job_id)
        with db.read() as c:
            if c.execute(q if p.operator else q.where(jobs_t.c.tenant == p.tenant)).first() is None:
                raise _err(404, f"job {job_id!r} not found")
            rows = c.execute(select(artifacts_t).where(artifacts_t.c.job_id == job_id)
                             .order_by(artifacts_t.c.name)).all()
            return ok(S.ArtifactList(job_id=job_id, items=[
                S.ArtifactOut(name=a.name, kind=a.kind, content_type=a.content_type, size_bytes=a.size_bytes,
                              url=f"/jobs/{job_id}/artifacts/{a.name}") for a in rows]))

    @app.get("/jobs/{job_id}/artifacts/{name:path}", tags=["artifacts"],
             responses={**E, 206: {"description": "partial content (Range)"}, 416: {"model": S.ErrorOut},
                        200: {"content": {"application/octet-stream": {}}}})
    def get_artifact(job_id: IdPath, name: Annotated[str, PathParam(min_length=1, max_length=512)],
                     request: Request, p: P):
        """An artifact file (EXR, MP4, PNG); supports ``Range: bytes=a-b``."""
        with db.session() as s:
            get_job(s, job_id, p)
            a = s.scalar(select(Artifact).where(Artifact.job_id == job_id, Artifact.name == name))
            if a is None:
                raise _err(404, f"job {job_id!r} has no artifact {name!r}")
            key, ctype = a.storage_key, a.content_type
        try:
            size = store.size(key)
        except StorageError:
            raise _err(404, f"artifact {name!r} of job {job_id!r} is missing from the store") from None
        return file_response(request, store, key, size, ctype, os.path.basename(name))

    app.add_api_route("/jobs/{job_id}/artifacts/{name:path}", get_artifact, methods=["HEAD"], include_in_schema=False)

    # --- environment maps ---------------------------------------------------------------------
    def ingest_envmap(upload: Path, size: int, digest: str, name: str, p: Principal, idem: str | None):
        from core.errors import CoreError
        from core.io import exr_header, read_envmap

        fp = _fingerprint("envmap", digest, name)
        with db.session() as s:
            existing = idem_lookup(s, p, idem, fp, "envmap")
            if existing:
                return s.get(Envmap, existing), True
        with open(upload, "rb") as fh:
            head = fh.read(16)
        if head[:4] == b"\x76\x2f\x31\x01":
            fmt = "exr"
        elif head[:2] == b"#?":
            fmt = "hdr"
        else:
            raise _err(415, "not an OpenEXR or Radiance .hdr file (unknown magic bytes)")
        path = upload.with_suffix("." + fmt)
        os.replace(upload, path)
        try:
            if fmt == "exr":
                exr_header(path)
            rgb = read_envmap(path)
        except CoreError as e:
            raise _err(422, f"environment map rejected: {str(e).replace(str(path), 'upload')}") from None
        eid = new_id()
        key = f"envmaps/{eid}.{fmt}"
        store.put_file(path, key)
        row = Envmap(id=eid, tenant=p.tenant, name=name, format=fmt, width=int(rgb.shape[1]),
                     height=int(rgb.shape[0]), size_bytes=size, storage_key=key)
        try:
            with db.session() as s:
                s.add(row)
                if idem:
                    s.add(IdempotencyKey(tenant=p.tenant, key=idem, request_hash=fp, resource="envmap",
                                         resource_id=eid))
        except BaseException:
            store.delete_prefix(key)
            raise
        return row, False

    @app.post("/envmaps", response_model=S.EnvmapOut, status_code=201, tags=["envmaps"], responses=E,
              openapi_extra={"requestBody": {"required": True, "description": "an equirectangular map, .exr or .hdr",
                                             "content": {t: {"schema": {"type": "string", "format": "binary"}}
                                                         for t in ("image/x-exr", "image/vnd.radiance")}}})
    async def upload_envmap(request: Request, p: P, idem: IdemKey = None,
                            name: Annotated[str, Query(min_length=1, max_length=256)] = "envmap"):
        """Upload an HDR environment map (W = 2 H; finite, non-negative values)."""
        ctype = request.headers.get("content-type", "").split(";")[0].strip().lower()
        if ctype not in ENVMAP_TYPES:
            raise _err(415, f"Content-Type {ctype or '(none)'!r} not accepted: send image/x-exr or "
                            "image/vnd.radiance")
        work = settings.data_dir / "uploads" / uuid.uuid4().hex
        work.mkdir(parents=True)
        try:
            upload = work / "upload.bin"
            size, digest = await stream_upload(request, upload, settings.max_envmap_bytes, "environment map")
            row, replay = await anyio.to_thread.run_sync(ingest_envmap, upload, size, digest, name, p, idem)
        finally:
            await anyio.to_thread.run_sync(lambda: shutil.rmtree(work, ignore_errors=True))
        return JSONResponse(envmap_out(row).model_dump(mode="json"), status_code=200 if replay else 201,
                            headers={"Location": f"/envmaps/{row.id}"})

    @app.get("/envmaps", response_model=S.EnvmapList, tags=["envmaps"], responses=E)
    def list_envmaps(p: P):
        with db.session() as s:
            rows = s.scalars(visible(select(Envmap), Envmap, p).order_by(Envmap.created_at.desc()).limit(500)).all()
            return S.EnvmapList(items=[envmap_out(r) for r in rows])

    @app.get("/envmaps/{envmap_id}", response_model=S.EnvmapOut, tags=["envmaps"], responses=E)
    def read_envmap_meta(envmap_id: IdPath, p: P):
        with db.session() as s:
            e = s.scalar(visible(select(Envmap).where(Envmap.id == envmap_id), Envmap, p))
            if e is None:
                raise _err(404, f"envmap {envmap_id!r} not found")
            return envmap_out(e)

    from services.dashboard import mount_dashboard

    mount_dashboard(app)
    return app
