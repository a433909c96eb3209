"""The FastAPI gateway: ``create_app(settings)``; ``brdf serve`` runs it under uvicorn. The routes
live in routers under :mod:`services.routes`; this module builds the app around them.

Routes (every body is an ``api_schemas`` model; every error an ``ErrorOut``):

- ``POST /scenes`` (a .zip / .tar.gz bundle as the raw body, streamed to disk under a size cap,
  unpacked safely and validated by ``core.bundle``), ``GET /scenes``, ``GET /scenes/{id}``;
- ``POST /scenes/{id}/render`` (the export render, queued), ``/relight``, ``/night``,
  ``/reconstruct`` (validated; 409 "not available in this build" until their pipeline is
  registered as a job type: never a fake job);
- ``POST /envmaps`` (.exr / .hdr, NaN/Inf rejected), ``GET /envmaps``, ``GET /envmaps/{id}``;
- ``GET /jobs``, ``GET /jobs/{id}``, ``DELETE /jobs/{id}`` (cancel), ``POST /jobs/{id}/retry``, ``GET /jobs/{id}/artifacts``,
  ``GET|HEAD /jobs/{id}/artifacts/{name}`` (HTTP Range);
- ``POST /keys``, ``GET /system`` (operator); ``GET /healthz``, ``/readyz``, ``/metrics``;
- ``/dashboard`` (see :mod:`services.dashboard`).
"""

import asyncio
import contextlib
import logging

import anyio
import redis
from fastapi import FastAPI, HTTPException, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from sqlalchemy.exc import OperationalError

import api_schemas as S
from services.auth import Authenticator, create_key
from services.dashboard import mount_dashboard
from services.db import get_database
from services.metrics import MetricsMiddleware, Registry
from services.routes import envmaps as envmap_routes
from services.routes import jobs as job_routes
from services.routes import objects as object_routes
from services.routes import scenes as scene_routes
from services.routes import system as system_routes
from services.routes.common import UPLOAD_PATHS, Ctx, E, _err, attempt_out, envmap_out, job_out, ok, ok_json, scene_out  # noqa: F401
from worker.queue import expire_failed_artifacts, reconcile, redis_conn, sweep_work_dirs
from worker.settings import Settings, get_settings
from worker.storage import get_store

log = logging.getLogger("brdf.gateway")
VERSION = "0.1.0"


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
            next_sweep = 0.0
            while True:
                try:
                    done = await anyio.to_thread.run_sync(reconcile, settings, db, rconn())
                    if any(done.values()):
                        log.info("reconcile: %s", done)
                except Exception as e:  # noqa: BLE001 - Redis down: try again next round
                    log.warning("reconcile failed: %s", e)
                if asyncio.get_running_loop().time() >= next_sweep:
                    next_sweep = asyncio.get_running_loop().time() + settings.janitor_interval_s
                    try:
                        expired = await anyio.to_thread.run_sync(expire_failed_artifacts, settings, db)
                        swept = await anyio.to_thread.run_sync(sweep_work_dirs, settings, db)
                        if expired or swept:
                            log.info("janitor: %d expired artifact(s) of failed jobs, %d dead work dir(s) removed",
                                     expired, swept)
                    except Exception as e:  # noqa: BLE001
                        log.warning("janitor failed: %s", e)
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

    @app.exception_handler(OperationalError)
    async def database_unavailable(request: Request, exc: OperationalError):
        # SQLite answers "database is locked" when a writer (e.g. a worker frozen inside a write
        # transaction) holds the lock past the busy timeout; PostgreSQL raises this class when the
        # server is down. Either way nothing was changed: say so and ask for a retry, not a 500.
        reason = str(getattr(exc, "orig", None) or exc).splitlines()[0][:200]
        log.warning("%s %s: database unavailable (%s)", request.method, request.url.path, reason)
        return JSONResponse({"detail": f"database busy or unavailable ({reason}); nothing was changed, "
                                       f"retry in a few seconds", "errors": []},
                            status_code=503, headers={"Retry-After": "5"})

    @app.exception_handler(RequestValidationError)
    async def validation_error(request: Request, exc: RequestValidationError):
        errors = []
        body = None
        for e in exc.errors():
            loc = ".".join(str(x) for x in e.get("loc", ()))
            msg = e.get("msg", "invalid")
            if e.get("type") == "json_invalid":
                # FastAPI's location is ("body", <character offset>): say line and column instead
                loc_t = e.get("loc", ())
                pos = loc_t[1] if len(loc_t) > 1 and isinstance(loc_t[1], int) else None
                where = ""
                if pos is not None:
                    if body is None:
                        body = (await request.body()).decode("utf-8", "replace")
                    line = body.count("\n", 0, pos) + 1
                    col = pos - (body.rfind("\n", 0, pos) + 1) + 1
                    where = f" at line {line}, column {col} (character {pos})"
                loc = "body"
                msg = f"malformed JSON{where}: {e.get('ctx', {}).get('error', msg)}"
            errors.append(f"{loc}: {msg}")
        return JSONResponse({"detail": f"invalid request ({len(errors)} problem(s)): {errors[0] if errors else ''}",
                             "errors": errors}, status_code=422)

    ctx = Ctx(settings=settings, db=db, store=store, auth=auth, registry=registry, rconn=rconn, version=VERSION)
    app.state.ctx = ctx
    for mod in (system_routes, scene_routes, job_routes, envmap_routes, object_routes):
        app.include_router(mod.build(ctx))
    app.state.unserved_queues = ctx.unserved_queues

    mount_dashboard(app)
    return app
