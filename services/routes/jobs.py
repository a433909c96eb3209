"""Job submission (render, relight, night, reconstruct), status, listing, cancel, retry and artifacts (HTTP Range)."""

from __future__ import annotations

import logging
import os
from typing import Annotated

from fastapi import APIRouter, Path as PathParam, Query, Request
from fastapi.responses import JSONResponse
from sqlalchemy import select, update
from sqlalchemy.exc import IntegrityError

import api_schemas as S
from services.auth import Principal
from services.ranges import file_response
from services.routes.common import (E, Ctx, IdemKey, IdPath, P, _err, _fingerprint, ok, ok_json, page_total,
                                    route_context, visible)
from services.routes.objects import check_scene_request
from services.db import IdempotencyKey
from worker.db import Artifact, Envmap, Job, JobAttempt, JobStage, attempt_ended, new_id, utcnow
from worker.queue import request_cancel, try_enqueue
from worker.registry import job_type
from worker.storage import StorageError

log = logging.getLogger("brdf.gateway")


def build(ctx: Ctx) -> APIRouter:
    """The routes, bound to the app's context (settings, database, store, Redis)."""
    router, settings, db, store = route_context(ctx)
    rconn, idem_lookup, jobs_t, artifacts_t = ctx.rconn, ctx.idem_lookup, ctx.jobs_t, Artifact.__table__
    get_scene, get_job, job_rows, read_job_out = ctx.get_scene, ctx.get_job, ctx.job_rows, ctx.read_job_out

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
                    s.add(JobAttempt(job_id=jid, attempt=1, queued_at=utcnow()))
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

    @router.post("/scenes/{scene_id}/render", status_code=202, response_model=S.JobAccepted, tags=["jobs"],
              responses=R202)
    def render(scene_id: IdPath, body: S.RenderRequest, p: P, idem: IdemKey = None):
        """Queue a render of the scene's frames: multi-layer EXR per frame, MP4 and a PNG preview."""
        return submit(p, scene_id, "render", body, idem)

    @router.post("/scenes/{scene_id}/relight", status_code=202, response_model=S.JobAccepted, tags=["jobs"],
              responses=R409)
    def relight(scene_id: IdPath, body: S.RelightRequest, p: P, idem: IdemKey = None):
        """Relight the reconstructed scene (its latest finished reconstruct job) under another
        environment map, with local lights and object edits: EXR frames, MP4 and a PNG preview.
        409 while the scene has no finished reconstruction."""
        if body.envmap_id is not None:
            with db.session() as s:
                if s.scalar(visible(select(Envmap).where(Envmap.id == body.envmap_id), Envmap, p)) is None:
                    raise _err(404, f"envmap {body.envmap_id!r} not found")
        check_scene_request(ctx, p, scene_id, body)  # 422: unknown objects, cameras, envmap name, empty range
        return submit(p, scene_id, "relight", body, idem)

    @router.post("/scenes/{scene_id}/night", status_code=202, response_model=S.JobAccepted, tags=["jobs"],
              responses=R409)
    def night(scene_id: IdPath, body: S.NightRequest, p: P, idem: IdemKey = None):
        """Night scenario: the scene's sky dimmed, street lamps (detected as poles in the LiDAR,
        spaced along the road, or at given positions; listed in the job's stage metrics and
        ``street_lights.json``), head and tail lights on every vehicle (``vehicle_lights_off``
        switches some off), automatic exposure. 422 for an object, camera or frame range the
        scene does not have (``GET /scenes/{id}/objects``); 409 while the scene has no finished
        reconstruction."""
        check_scene_request(ctx, p, scene_id, body)  # 422: unknown objects, cameras, empty range
        return submit(p, scene_id, "night", body, idem)

    @router.post("/scenes/{scene_id}/reconstruct", status_code=202, response_model=S.JobAccepted, tags=["jobs"],
              responses=R409)
    def reconstruct(scene_id: IdPath, body: S.ReconstructRequest, p: P, idem: IdemKey = None):
        """Queue the optimization stage chain (409 until the training stages exist)."""
        return submit(p, scene_id, "reconstruct", body, idem)

    # --- jobs ---------------------------------------------------------------------------------
    @router.get("/jobs", response_model=S.JobList, tags=["jobs"], responses=E)
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

    @router.get("/jobs/{job_id}", response_model=S.JobOut, tags=["jobs"], responses=E)
    async def read_job(job_id: IdPath, p: P):
        with db.read() as c:
            return ok_json(read_job_out(c, job_id, p))

    @router.delete("/jobs/{job_id}", response_model=S.JobOut, tags=["jobs"], responses=E)
    def cancel_job(job_id: IdPath, p: P):
        """Cancel a queued or running job (a running one stops within a heartbeat). A finished job
        is returned unchanged."""
        with db.session() as s:
            get_job(s, job_id, p)
        request_cancel(db, rconn(), job_id)
        with db.read() as c:
            return ok_json(read_job_out(c, job_id, p))

    @router.post("/jobs/{job_id}/retry", status_code=202, response_model=S.JobAccepted, tags=["jobs"],
              responses={**E, 409: {"model": S.ErrorOut, "description": "the job is not failed or canceled"}})
    def retry_job(job_id: IdPath, p: P):
        """Run a failed or canceled job again as a new attempt (a reconstruct chain resumes at its
        first stage that is not done). 409 for a job that is queued, running or done."""
        with db.session() as s:
            j = get_job(s, job_id, p)
            if j.state not in ("failed", "canceled"):
                raise _err(409, f"job {job_id!r} is {j.state}: only a failed or canceled job can be retried")
            attempt, prev_state, prev_error = j.attempts, j.state, j.error
            why = f"retried by request ({'operator' if p.operator else 'client'} key {p.key_id})"
            n = s.execute(update(Job).where(Job.id == job_id, Job.state == prev_state, Job.attempts == attempt)
                          .values(state="queued", attempts=attempt + 1, max_attempts=max(j.max_attempts, attempt + 1),
                                  error=None, finished_at=None, enqueued_at=None, worker_name=None, eta_s=None,
                                  progress=0.0)).rowcount
            if not n:
                raise _err(409, f"job {job_id!r} changed meanwhile; try again")
            s.execute(update(JobStage).where(JobStage.job_id == job_id, JobStage.state != "done")
                      .values(state="queued", progress=0.0, started_at=None, finished_at=None))
            old = s.scalar(select(JobAttempt).where(JobAttempt.job_id == job_id, JobAttempt.attempt == attempt))
            if old is None or old.finished_at is None:  # ended without its attempt row (an older build)
                attempt_ended(s, job_id, attempt, prev_state, prev_error)
                old = s.scalar(select(JobAttempt).where(JobAttempt.job_id == job_id, JobAttempt.attempt == attempt))
            old.reason = f"{old.reason or prev_error or prev_state}; then {why}"
            s.add(JobAttempt(job_id=job_id, attempt=attempt + 1, queued_at=utcnow()))
        with db.session() as s:
            job = s.get(Job, job_id)
        try_enqueue(settings, db, rconn(), job)
        body = S.JobAccepted(id=job.id, state=S.JobState(job.state), status_url=f"/jobs/{job.id}")
        return JSONResponse(body.model_dump(mode="json"), status_code=202, headers={"Location": f"/jobs/{job.id}"})

    @router.get("/jobs/{job_id}/artifacts", response_model=S.ArtifactList, tags=["artifacts"], responses=E)
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

    @router.get("/jobs/{job_id}/artifacts/{name:path}", tags=["artifacts"],
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

    router.add_api_route("/jobs/{job_id}/artifacts/{name:path}", get_artifact, methods=["HEAD"], include_in_schema=False)

    return router
