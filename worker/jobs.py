"""The RQ entry point: ``worker.jobs.run_job(job_id, attempt[, stage])`` is the only function
ever enqueued (JSON arguments; :data:`worker.queue.JOB_FUNC`). It runs the attempt through the job
lifecycle (:func:`worker.runtime.run_attempt`) with the registered job types
(:mod:`worker.registry`) and, for a retry, the queue (:func:`worker.queue.try_enqueue`)."""

from __future__ import annotations

from worker.db import Database, Job
from worker.queue import redis_conn, try_enqueue
from worker.registry import job_type
from worker.runtime import run_attempt
from worker.settings import Settings


def _requeue(settings: Settings, db: Database, job: Job) -> None:
    try_enqueue(settings, db, redis_conn(settings.redis_url), job)


def run_job(job_id: str, attempt: int, stage: str | None = None) -> dict:
    """The RQ entry point (arguments are JSON). Returns a small JSON summary. ``stage``: the
    stage to run of a chained job (each stage is its own RQ job; see :func:`worker.queue.enqueue`)."""
    return run_attempt(job_id, attempt, stage, job_type, _requeue)
