"""Enqueue helpers shared by the gateway and the workers, and the reconcile loop that makes the
database the truth: a job accepted into the ``jobs`` table reaches a worker even if Redis lost
it (restart without persistence, failed enqueue) or its worker died (kill -9, machine lost).

RQ payloads are JSON (``rq.serializers.JSONSerializer``, never pickle) and hold only the job id
and the attempt number; the worker reads the validated parameters from the database.
"""

from __future__ import annotations

import logging
import os
import re
import shutil
from datetime import timedelta, timezone

import redis
from rq import Queue, Worker
from rq.job import Dependency, JobStatus
from rq.job import Job as RQJob
from rq.serializers import JSONSerializer
from sqlalchemy import select, update

from worker.db import Artifact, Database, Job, JobStage, attempt_ended, pending_stage_names, rq_job_id, utcnow
from worker.registry import job_type
from worker.settings import QUEUES, Settings
from worker.storage import get_store

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
    # a retry has waited once already: it goes to the front of its queue
    front = job.attempts > 1
    if not is_chained(job):
        q.enqueue_call(JOB_FUNC, args=(job.id, job.attempts), job_id=rq_job_id(job.id, job.attempts),
                       description=f"{job.type} {job.id} attempt {job.attempts}", at_front=front, **common)
        return
    prev = None
    stages = pending_stages(db, job.id)
    for st in stages:
        rid = rq_job_id(job.id, job.attempts, st)
        dep = Dependency(jobs=[prev], enqueue_at_front=True) if prev else None
        q.enqueue_call(JOB_FUNC, args=(job.id, job.attempts, st), job_id=rid, depends_on=dep,
                       description=f"{job.type} {job.id} stage {st} attempt {job.attempts}",
                       at_front=front and prev is None, **common)
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
        if n:
            attempt_ended(s, job.id, job.attempts, "canceled", "canceled by request")
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
        elif status == "failed" and err and any(m in err for m in DIED_MARKERS):
            res = retry_dead_attempt(settings, db, conn, job.id, job.attempts,
                                     f"the worker holding attempt {job.attempts} died before it started ({err})",
                                     unclaimed=True)
            if res == "retried":
                out["retried"] += 1
            elif res == "failed":
                out["lost"] += 1
        elif status == "failed":
            with db.session() as s:
                n = s.execute(update(Job).where(Job.id == job.id, Job.state == "queued",
                                                Job.attempts == job.attempts)
                              .values(state="failed", finished_at=utcnow(),
                                      error=f"the queue failed the job before it ran: {err or 'unknown error'}")
                              ).rowcount
                if n:
                    attempt_ended(s, job.id, job.attempts, "failed",
                                  f"the queue failed the job before it ran: {err or 'unknown error'}")
            out["rq_failed"] += n
    for job in running:
        age = (now - job.heartbeat_at).total_seconds()
        why = (f"worker {job.worker_name or '?'} lost: no heartbeat for {age:.0f} s "
               f"(attempt {job.attempts} of {job.max_attempts})")
        res = retry_dead_attempt(settings, db, conn, job.id, job.attempts, why)
        if res == "retried":
            out["retried"] += 1
        elif res == "failed":
            out["lost"] += 1
    return out


def retry_dead_attempt(settings: Settings, db: Database, conn: redis.Redis | None, job_id: str, attempt: int,
                       why: str, unclaimed: bool = False, drop_rq_job: bool = True) -> str | None:
    """The process running attempt ``attempt`` of ``job_id`` died (its work horse was killed,
    its worker was lost): end the attempt now with ``why``, queue the next attempt while attempts
    are left (else fail the job), and remove what the dead attempt left behind: its scratch
    directory on this machine and its unregistered partial outputs in the store. Returns
    "retried", "failed", or None when the attempt was no longer running (it had settled itself,
    or a cancel or another retry came first).

    ``unclaimed``: the process died holding the attempt's RQ job before the job function claimed
    it (the database still says queued): the attempt is retried the same way, since that RQ job
    is gone (RQ would only mark it abandoned, minutes later).

    ``drop_rq_job``: also remove the dead attempt's RQ job from Redis (its started registry), so
    RQ does not list it as failed later beside a job that finished on its retry; False where RQ
    settles it itself (a worker's own work-horse handler)."""
    with db.session() as s:
        job = s.get(Job, job_id)
        if job is None or job.attempts != attempt or job.state not in (("running", "queued") if unclaimed
                                                                       else ("running",)):
            return None
        prev_state = job.state
        chained = is_chained(job)
        stage = job.stage if chained else None
        # a chain's later stages of the dead attempt wait in Redis behind the dead stage: drop them
        stale_rq = [rq_job_id(job_id, attempt, st) for st in pending_stage_names(s, job_id) if st != stage] \
            if chained else []
        retry = attempt < job.max_attempts
        q = update(Job).where(Job.id == job_id, Job.state == prev_state, Job.attempts == attempt)
        if retry:
            n = s.execute(q.values(state="queued", attempts=attempt + 1, error=why, enqueued_at=None,
                                   worker_name=None, eta_s=None)).rowcount
        else:
            n = s.execute(q.values(state="failed", finished_at=utcnow(), error=why, eta_s=None)).rowcount
        if n:
            attempt_ended(s, job_id, attempt, "retried" if retry else "failed", why, next_attempt=retry)
    if not n:
        return None
    cleanup_attempt(settings, job_id, attempt, stage)
    if conn is not None and drop_rq_job:
        _drop_started(conn, job.queue, rq_job_id(job_id, attempt, stage))
    if conn is not None:
        for rq_id in stale_rq:
            try:
                rj = RQJob.fetch(rq_id, connection=conn, serializer=JSONSerializer)
                if rj.get_status() in (JobStatus.QUEUED, JobStatus.DEFERRED, JobStatus.SCHEDULED):
                    rj.cancel()
            except Exception:  # noqa: BLE001 - gone already, or Redis down: a stale attempt's job is skipped anyway
                pass
    if retry:
        job.attempts = attempt + 1
        job.state = "queued"
        if conn is not None:
            try_enqueue(settings, db, conn, job)
        log.warning("job %s: %s; retrying as attempt %d", job_id, why, attempt + 1)
        return "retried"
    log.warning("job %s: %s; no attempts left, failed", job_id, why)
    return "failed"


def _drop_started(conn: redis.Redis, queue: str, rq_id: str) -> None:
    """Remove a dead attempt's RQ job (and its executions in the started registry)."""
    try:
        rj = RQJob.fetch(rq_id, connection=conn, serializer=JSONSerializer)
    except Exception:  # noqa: BLE001 - gone already (e.g. Redis restarted)
        return
    try:
        get_queue(queue, conn).started_job_registry.remove_executions(rj)
        rj.delete()
    except Exception as e:  # noqa: BLE001 - cosmetic: RQ lists it as abandoned later
        log.info("could not drop the dead RQ job %s: %s", rq_id, e)


def parse_rq_id(rq_id: str) -> tuple[str, int, str | None] | None:
    """``(job id, attempt, stage)`` of an RQ job id made by :func:`worker.db.rq_job_id`."""
    m = re.fullmatch(r"([A-Za-z0-9]+)-a(\d+)(?:-(.+))?", rq_id or "")
    return (m.group(1), int(m.group(2)), m.group(3)) if m else None


#: How RQ words the failure of a job whose worker or work horse died (the job function may never
#: have run, so the job is retried, not failed).
DIED_MARKERS = ("AbandonedJobError", "Work-horse terminated", "work-horse terminated")


def attempt_prefix(job_id: str, attempt: int, stage: str | None) -> str:
    """The store prefix of one attempt's outputs (of one stage, for a chain); mirrors
    :attr:`worker.runtime.JobContext.key_prefix`."""
    return f"jobs/{job_id}/{stage}.a{attempt}" if stage else f"jobs/{job_id}/{attempt}"


def cleanup_attempt(settings: Settings, job_id: str, attempt: int, stage: str | None) -> None:
    """Remove a dead attempt's scratch directories (``work/<job>.<attempt>[.<stage>]`` on this
    machine) and its outputs in the store (none of them registered: a stage registers its
    artifacts only when it succeeds). A reconstruct job's run directory is kept: the retry
    resumes from its checkpoint."""
    work = settings.data_dir / "work"
    for d in [work / f"{job_id}.{attempt}", *work.glob(f"{job_id}.{attempt}.*")]:
        shutil.rmtree(d, ignore_errors=True)
    try:
        get_store(settings.store_url, settings.artifact_store_options).delete_prefix(
            attempt_prefix(job_id, attempt, stage))
    except Exception as e:  # noqa: BLE001 - the store may be briefly unreachable; the TTL sweep retries
        log.warning("job %s attempt %d: could not remove its partial outputs: %s", job_id, attempt, e)


def sweep_work_dirs(settings: Settings, db: Database) -> int:
    """Remove scratch directories (``work/<job>.<attempt>...``) of attempts that are not running
    (left by a worker killed with its work horse). Returns how many were removed."""
    work = settings.data_dir / "work"
    if not work.is_dir():
        return 0
    by_job: dict[str, list] = {}
    for d in work.iterdir():
        parts = d.name.split(".")
        if len(parts) >= 2 and parts[1].isdigit():
            by_job.setdefault(parts[0], []).append((int(parts[1]), d))
    if not by_job:
        return 0
    with db.session() as s:
        live = {(i, a) for i, a in s.execute(select(Job.id, Job.attempts).where(
            Job.id.in_(list(by_job)), Job.state.in_(("running", "queued")))).all()}
    n = 0
    for jid, dirs in by_job.items():
        for attempt, d in dirs:
            if (jid, attempt) not in live:
                shutil.rmtree(d, ignore_errors=True)
                n += 1
    return n


def expire_failed_artifacts(settings: Settings, db: Database) -> int:
    """Delete the artifacts of jobs that failed or were canceled more than
    ``failed_artifact_ttl_s`` ago (e.g. the finished stages of a chain whose later stage failed):
    the store objects and their rows. Returns how many artifacts were removed."""
    cutoff = utcnow() - timedelta(seconds=settings.failed_artifact_ttl_s)
    with db.session() as s:
        rows = s.execute(select(Artifact.id, Artifact.job_id, Artifact.storage_key).join(Job, Job.id == Artifact.job_id)
                         .where(Job.state.in_(("failed", "canceled")), Job.finished_at < cutoff).limit(1000)).all()
    if not rows:
        return 0
    store = get_store(settings.store_url, settings.artifact_store_options)
    gone = []
    for aid, jid, key in rows:
        try:
            if store.exists(key):
                store.delete_prefix(key)
            gone.append(aid)
        except Exception as e:  # noqa: BLE001 - try again next sweep
            log.warning("job %s: could not expire artifact %s: %s", jid, key, e)
    with db.session() as s:
        from sqlalchemy import delete

        s.execute(delete(Artifact).where(Artifact.id.in_(gone)))
    return len(gone)


def waiting_jobs(db: Database) -> dict[str, dict]:
    """Per queue, the jobs waiting for a worker in the database (the truth): ``{queue: {"count":
    n, "oldest_s": age of the oldest}}``. A retry waits since it was queued again."""
    from sqlalchemy import func

    now = utcnow()
    out = {q: {"count": 0, "oldest_s": 0.0} for q in QUEUES}
    with db.read() as c:
        rows = c.execute(select(Job.queue, func.count(), func.min(func.coalesce(Job.enqueued_at, Job.created_at)))
                         .where(Job.state == "queued").group_by(Job.queue)).all()
    for q, n, oldest in rows:
        if oldest is not None and oldest.tzinfo is None:
            oldest = oldest.replace(tzinfo=timezone.utc)
        out[q] = {"count": int(n), "oldest_s": max((now - oldest).total_seconds(), 0.0) if oldest else 0.0}
    return out


def live_workers(workers: list[dict], settings: Settings) -> dict[str, int]:
    """Per queue, the workers whose RQ heartbeat is fresher than ``worker_stale_s``."""
    out = {q: 0 for q in QUEUES}
    for w in workers:
        age = w["heartbeat_age_s"]
        if age is not None and age <= settings.worker_stale_s and w["state"] != "suspended":
            for q in w["queues"]:
                out[q] = out.get(q, 0) + 1
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
            hb = hb.replace(tzinfo=timezone.utc)
        out.append({"name": w.name, "state": str(getattr(w.get_state(), "value", w.get_state())),
                    "queues": w.queue_names(), "current_job": w.get_current_job_id(),
                    "last_heartbeat": hb, "heartbeat_age_s": (now - hb).total_seconds() if hb else None})
    return sorted(out, key=lambda d: d["name"])
