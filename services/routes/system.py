"""Health, readiness, Prometheus metrics, API keys and the system status (operator)."""

from __future__ import annotations

import logging

import redis
from fastapi import APIRouter, Request
from fastapi.responses import JSONResponse, PlainTextResponse
from sqlalchemy import func, select

import api_schemas as S
from services.auth import create_key
from services.routes.common import E, Ctx, Operator, route_context
from worker.db import Job, JobAttempt, Scene
from worker.queue import list_workers, live_workers, queue_stats, waiting_jobs

log = logging.getLogger("brdf.gateway")


def build(ctx: Ctx) -> APIRouter:
    """The routes, bound to the app's context (settings, database, store, Redis)."""
    router, settings, db, store = route_context(ctx)
    rconn, registry = ctx.rconn, ctx.registry

    # --- health -----------------------------------------------------------------------------
    @router.get("/healthz", response_model=S.Health, tags=["system"])
    def healthz():
        """The process is up (no dependency checked)."""
        return S.Health(status="ok", version=ctx.version)

    def unserved_queues() -> list[str]:
        """Why a queue cannot make progress: waiting jobs and no live worker serving it."""
        waiting = waiting_jobs(db)
        live = live_workers(list_workers(rconn()), settings)
        return [f"queue {q!r}: {w['count']} job(s) waiting (oldest {w['oldest_s']:.0f} s) and no live worker "
                f"serves it" for q, w in waiting.items() if w["count"] and not live.get(q)]

    ctx.unserved_queues = unserved_queues

    @router.get("/readyz", response_model=S.Ready, tags=["system"], responses={503: {"model": S.Ready}})
    def readyz():
        """Database, Redis and the artifact store answer, and every queue with waiting jobs has a
        live worker; 503 naming what failed otherwise (``checks.workers``: e.g. "queue 'train':
        2 job(s) waiting (oldest 40 s) and no live worker serves it")."""
        checks = {}
        for name, fn in (("database", db.ping), ("redis", lambda: rconn().ping()), ("artifact_store", store.ping)):
            try:
                fn()
                checks[name] = "ok"
            except Exception as e:  # noqa: BLE001
                checks[name] = f"{type(e).__name__}: {e}"[:300]
        if checks["database"] == "ok" and checks["redis"] == "ok":
            checks["workers"] = "; ".join(unserved_queues()) or "ok"
        ok = all(v == "ok" for v in checks.values())
        return JSONResponse(S.Ready(ready=ok, checks=checks).model_dump(), status_code=200 if ok else 503)

    @router.get("/metrics", response_class=PlainTextResponse, tags=["system"])
    def metrics(request: Request):
        """Prometheus text format."""
        gauges = []
        with db.session() as s:
            rows = s.execute(select(Job.state, func.count()).group_by(Job.state)).all()
            counts = {st: 0 for st in ("queued", "running", "done", "failed", "canceled")}
            counts.update({k: v for k, v in rows})
            gauges.append(("brdf_jobs", "Jobs by state.", [({"state": k}, v) for k, v in sorted(counts.items())]))
            gauges.append(("brdf_scenes", "Stored scenes.", [({}, s.scalar(select(func.count()).select_from(Scene)))]))
            retries = s.scalar(select(func.coalesce(func.sum(Job.attempts - 1), 0))) or 0
            by_reason = dict(s.execute(select(JobAttempt.outcome, func.count()).where(
                JobAttempt.outcome.in_(("retried", "failed"))).group_by(JobAttempt.outcome)).all())
        gauges.append(("brdf_job_retries_total", "Retries queued (attempts after a job's first).",
                       [({}, retries)], "counter"))
        gauges.append(("brdf_job_attempts_ended_total", "Attempts that ended in a retry or a failure.",
                       [({"outcome": k}, by_reason.get(k, 0)) for k in ("retried", "failed")], "counter"))
        waiting = waiting_jobs(db)
        gauges.append(("brdf_jobs_waiting", "Jobs waiting for a worker, per queue (database).",
                       [({"queue": q}, w["count"]) for q, w in sorted(waiting.items())]))
        gauges.append(("brdf_oldest_waiting_job_seconds", "Age of the oldest job waiting for a worker, per queue.",
                       [({"queue": q}, round(w["oldest_s"], 3)) for q, w in sorted(waiting.items())]))
        sup = getattr(request.app.state, "supervisor", None)
        gauges.append(("brdf_worker_restarts_total", "Workers restarted by the brdf up supervisor.",
                       [({}, sup.restarts if sup is not None else 0)], "counter"))
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
            gauges.append(("brdf_queue_workers", "Live workers (fresh RQ heartbeat) serving each queue.",
                           [({"queue": q}, n) for q, n in sorted(live_workers(ws, settings).items())]))
        except redis.RedisError:
            gauges.append(("brdf_redis_up", "Redis answers.", [({}, 0)]))
        return PlainTextResponse(registry.render(gauges), media_type="text/plain; version=0.0.4")

    # --- keys and system ----------------------------------------------------------------------
    @router.post("/keys", response_model=S.ApiKeyCreated, status_code=201, tags=["admin"], responses=E)
    def create_api_key(body: S.ApiKeyCreate, p: Operator):
        """Create an API key for a tenant (operator only). The secret is returned once."""
        secret, row = create_key(db, body.tenant, body.scope.value, body.name)
        return S.ApiKeyCreated(id=row.id, tenant=row.tenant, scope=S.Scope(row.scope), key=secret)

    @router.get("/system", response_model=S.SystemStatus, tags=["admin"], responses=E)
    def system(p: Operator):
        """Queue depths and workers with their heartbeats (operator only)."""
        try:
            c = rconn()
            return S.SystemStatus(queues=[S.QueueStats(**q) for q in queue_stats(c)],
                                  workers=[S.WorkerOut(**w) for w in list_workers(c)], redis="ok")
        except redis.RedisError as e:
            return S.SystemStatus(queues=[], workers=[], redis=f"unreachable: {e}")

    return router
