"""Enqueue helpers shared by the gateway and the workers, and the reconcile loop that makes the
database the truth: a job accepted into the ``jobs`` table reaches a worker even if Redis lost
it (restart without persistence, failed enqueue) or its worker died (kill -9, machine lost).

RQ payloads are JSON (``rq.serializers.JSONSerializer``, never pickle) and hold only the job id
and the attempt number; the worker reads the validated parameters from the database.
"""

from __future__ import annotations

import logging
import os
from datetime import timedelta

import redis
from rq import Queue, Worker
from rq.job import Dependency
from rq.job import Job as RQJob
from rq.job import JobStatus
from rq.serializers import JSONSerializer
from sqlalchemy import select, update

from worker.db import Database, Job, JobStage, pending_stage_names, rq_job_id, utcnow
from worker.settings import QUEUES, Settings

log = logging.getLogger("brdf.queue")
JOB_FUNC = "worker.jobs.run_job"

_conns: dict[tuple[str, int], redis.Redis] = {}


def redis_conn(url: str) -> redis.Redis:
    """One client per URL and process; short timeouts so a dead Redis fails fast."""
    k = (url, os.getpid())
    if k not in _conns:
        _conns[k] = redis.Redis.from_url(url, socket_connect_timeout=2, socket_timeout=5,
                                         health_check_interval=10)
    return _conns[k]


def get_queue(name: str, conn: redis.Redis) -> Queue:
    return Queue(name, connection=conn, serializer=JSONSerializer)


def pending_stages(db: Database, job_id: str) -> list[str]:
    """The stages of a job that are not done, in chain order."""
    with db.session() as s:
        return pending_stage_names(s, job_id)


def is_chained(job: Job) -> bool:
    from worker.registry import job_type

    jt = job_type(job.type)
    return jt is not None and jt.chained


def current_rq_id(db: Database, job: Job) -> str:
    """The RQ job that runs (or will run next) for ``job``'s current attempt: for a chained job,
    the one of its first stage that is not done."""
    if is_chained(job):
        rest = pending_stages(db, job.id)
        return rq_job_id(job.id, job.attempts, rest[0] if rest else None)
    return job.rq_job_id


def enqueue(settings: Settings, conn: redis.Redis, job: Job, db: Database) -> None:
    """Put attempt ``job.attempts`` of ``job`` on its queue (raises redis errors). A chained job
    (the training stages) becomes one RQ job per stage that is not done yet, each depending on
    the previous one (``depends_on``; a dependent goes to the front of the queue when its
    predecessor finishes, so another job's stages cannot slip between two stages of this one)."""
    q = get_queue(job.queue, conn)
    common = dict(timeout=settings.job_timeout(job.queue), result_ttl=settings.result_ttl_s,
                  failure_ttl=settings.failure_ttl_s)
    if not is_chained(job):
        q.enqueue_call(JOB_FUNC, args=(job.id, job.attempts), job_id=rq_job_id(job.id, job.attempts),
                       description=f"{job.type} {job.id} attempt {job.attempts}", **common)
        return
    prev = None
    stages = pending_stages(db, job.id)
    for st in stages:
        rid = rq_job_id(job.id, job.attempts, st)
        dep = Dependency(jobs=[prev], enqueue_at_front=True) if prev else None
        q.enqueue_call(JOB_FUNC, args=(job.id, job.attempts, st), job_id=rid, depends_on=dep,
                       description=f"{job.type} {job.id} stage {st} attempt {job.attempts}", **common)
        prev = rid


def try_enqueue(settings: Settings, db: Database, conn: redis.Redis, job: Job) -> bool:
    """Enqueue and record ``enqueued_at``; on a Redis error leave the job queued in the database
    (the reconcile loop enqueues it later) and return False."""
    try:
        enqueue(settings, conn, job, db)
    except redis.RedisError as e:
        log.warning("enqueue of job %s failed (%s); the reconcile loop will retry", job.id, e)
        return False
    with db.session() as s:
        s.execute(update(Job).where(Job.id == job.id, Job.attempts == job.attempts)
                  .values(enqueued_at=utcnow()))
    return True


def request_cancel(db: Database, conn: redis.Redis, job_id: str) -> str:
    """Cancel a queued or running job; returns its state afterwards. A queued job is removed
    from its queue; a running job sees the state in the database at its next heartbeat and
    stops (its worker interrupts the job function)."""
    with db.session() as s:
        job = s.get(Job, job_id)
        if job is None:
            raise KeyError(job_id)
        if job.state in ("done", "failed", "canceled"):
            return job.state
        chained = is_chained(job)
        rest = [s_.name for s_ in job.stages if s_.state != "done"] if chained else []
        n = s.execute(update(Job).where(Job.id == job_id, Job.state.in_(("queued", "running")))
                      .values(state="canceled", finished_at=utcnow(), error="canceled by request",
                              eta_s=None)).rowcount
        rq_ids = [rq_job_id(job.id, job.attempts, st) for st in rest] if chained else [job.rq_job_id]
    if n:
        for rq_id in rq_ids:  # a chain: its deferred stages too, so none is left waiting in Redis
            try:
                rj = RQJob.fetch(rq_id, connection=conn, serializer=JSONSerializer)
                if rj.get_status() in (JobStatus.QUEUED, JobStatus.DEFERRED, JobStatus.SCHEDULED):
                    rj.cancel()
            except Exception as e:  # noqa: BLE001 - Redis may be down or the job gone; the DB decides
                log.info("cancel of job %s (%s): RQ side not updated (%s)", job_id, rq_id, e)
    with db.session() as s:
        return s.get(Job, job_id).state


def _rq_status(conn: redis.Redis, rq_id: str) -> tuple[str | None, str | None]:
    try:
        rj = RQJob.fetch(rq_id, connection=conn, serializer=JSONSerializer)
    except Exception:  # noqa: BLE001 - NoSuchJobError or undecodable: treat as missing
        return None, None
    st = rj.get_status(refresh=False)
    err = None
    if st == JobStatus.FAILED:
        try:
            err = (rj.latest_result().exc_string or "").strip().splitlines()[-1:]
            err = err[0] if err else None
        except Exception:  # noqa: BLE001
            err = None
    return (st.value if hasattr(st, "value") else str(st)), err


def reconcile(settings: Settings, db: Database, conn: redis.Redis) -> dict[str, int]:
    """Bring Redis in line with the database. Returns counts of what was done:

    - ``requeued``: queued jobs whose RQ job is missing (Redis restarted or the enqueue failed);
    - ``retried``: running jobs with a stale heartbeat (their worker died) with attempts left,
      queued again as a new attempt;
    - ``lost``: such jobs out of attempts, marked failed;
    - ``rq_failed``: queued jobs RQ itself failed before the job function ran, marked failed.
    """
    now = utcnow()
    out = {"requeued": 0, "retried": 0, "lost": 0, "rq_failed": 0}
    grace = now - timedelta(seconds=settings.requeue_grace_s)
    stale = now - timedelta(seconds=settings.stale_after_s)
    with db.session() as s:
        queued = s.scalars(select(Job).where(Job.state == "queued", Job.created_at < grace)).all()
        running = s.scalars(select(Job).where(Job.state == "running", Job.heartbeat_at < stale)).all()
    for job in queued:
        if job.enqueued_at is not None and job.enqueued_at > grace:
            continue
        status, err = _rq_status(conn, current_rq_id(db, job))
        if status is None or status in ("canceled", "stopped"):
            enqueue(settings, conn, job, db)
            with db.session() as s:
                s.execute(update(Job).where(Job.id == job.id, Job.attempts == job.attempts)
                          .values(enqueued_at=utcnow()))
            out["requeued"] += 1
            log.info("re-enqueued job %s attempt %d (missing from Redis)", job.id, job.attempts)
        elif status == "failed":
            with db.session() as s:
                n = s.execute(update(Job).where(Job.id == job.id, Job.state == "queued",
                                                Job.attempts == job.attempts)
                              .values(state="failed", finished_at=utcnow(),
                                      error=f"the queue failed the job before it ran: {err or 'unknown error'}")
                              ).rowcount
            out["rq_failed"] += n
    for job in running:
        age = (now - job.heartbeat_at).total_seconds()
        why = (f"worker {job.worker_name or '?'} lost: no heartbeat for {age:.0f} s "
               f"(attempt {job.attempts} of {job.max_attempts})")
        if job.attempts < job.max_attempts:
            with db.session() as s:
                n = s.execute(update(Job).where(Job.id == job.id, Job.state == "running",
                                                Job.attempts == job.attempts)
                              .values(state="queued", attempts=job.attempts + 1, error=why,
                                      enqueued_at=None, worker_name=None, eta_s=None)).rowcount
            if n:
                job.attempts += 1
                try_enqueue(settings, db, conn, job)
                out["retried"] += 1
                log.warning("job %s: %s; retrying as attempt %d", job.id, why, job.attempts)
        else:
            with db.session() as s:
                n = s.execute(update(Job).where(Job.id == job.id, Job.state == "running",
                                                Job.attempts == job.attempts)
                              .values(state="failed", finished_at=utcnow(), error=why, eta_s=None)).rowcount
            out["lost"] += n
    return out


def queue_stats(conn: redis.Redis) -> list[dict]:
    out = []
    for name in QUEUES:
        q = get_queue(name, conn)
        out.append({"name": name, "queued": q.count, "started": q.started_job_registry.count,
                    "failed": q.failed_job_registry.count})
    return out


def list_workers(conn: redis.Redis) -> list[dict]:
    now = utcnow()
    out = []
    for w in Worker.all(connection=conn):
        hb = w.last_heartbeat
        if hb is not None and hb.tzinfo is None:
            from datetime import timezone

            hb = hb.replace(tzinfo=timezone.utc)
        out.append({"name": w.name, "state": str(getattr(w.get_state(), "value", w.get_state())),
                    "queues": w.queue_names(), "current_job": w.get_current_job_id(),
                    "last_heartbeat": hb, "heartbeat_age_s": (now - hb).total_seconds() if hb else None})
    return sorted(out, key=lambda d: d["name"])
