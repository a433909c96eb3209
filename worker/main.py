"""The worker entry point (``brdf worker``): an RQ worker on the ``render`` and/or ``train``
queues with the JSON serializer. It reconciles the queue with the database when it starts (so a
machine coming back recovers jobs lost with it) and keeps reconnecting while Redis is down.

Run separate workers per queue (``--queues render`` on some machines, ``--queues train`` on
others) so a long training never starves relight requests; ``--no-fork`` runs jobs in the
worker process itself (``rq.SimpleWorker``) so loaded models stay warm between jobs.
"""

from __future__ import annotations

import logging
import os
import signal
import socket
import time
import uuid

import redis
from rq import SimpleWorker, Worker, worker_registration
from rq.serializers import JSONSerializer

from worker import jobs  # noqa: F401  (the RQ entry point and every job module, imported before work horses fork)
from worker.db import get_database
from worker.queue import get_queue, reconcile, redis_conn, retry_dead_attempt, sweep_work_dirs
from worker.settings import QUEUES, Settings, configure

log = logging.getLogger("brdf.worker")


class _Reregistering:
    """A worker that registers itself again when Redis lost its registration (a restart without
    persistence), so dashboards and ``/system`` list it again once Redis is back."""

    def heartbeat(self, timeout=None, pipeline=None):
        super().heartbeat(timeout, pipeline)
        if pipeline is not None:
            return
        try:
            if not self.connection.sismember(worker_registration.REDIS_WORKER_KEYS, self.key):
                with self.connection.pipeline() as p:
                    p.hset(self.key, mapping=self.serialize())
                    worker_registration.register(self, p)
                    p.expire(self.key, self.worker_ttl + 60)
                    p.execute()
                log.info("worker %s registered again (Redis had lost it)", self.name)
        except redis.RedisError:
            pass


class ForkingWorker(_Reregistering, Worker):
    """Forks a work horse per job. When the horse dies (killed, out of memory, a crash in native
    code), its attempt is failed at once and the retry queued (:func:`worker.queue.retry_dead_attempt`)
    instead of waiting for the heartbeat check; the dead attempt's RQ entry is not left in the
    failed registry (the job's attempt history in the database records it)."""

    brdf_settings: Settings | None = None
    _horse_handled: str | None = None

    def handle_work_horse_killed(self, job, retpid, ret_val, rusage):
        super().handle_work_horse_killed(job, retpid, ret_val, rusage)
        self._horse_handled = None
        try:
            job_id, attempt = str(job.args[0]), int(job.args[1])
        except (IndexError, TypeError, ValueError):
            return
        if ret_val is not None and os.WIFSIGNALED(ret_val):
            how = f"killed by signal {os.WTERMSIG(ret_val)} ({signal.Signals(os.WTERMSIG(ret_val)).name})"
        else:
            how = f"exited with status {os.waitstatus_to_exitcode(ret_val) if ret_val is not None else '?'}"
        why = f"work horse {retpid} of worker {self.name} {how} during attempt {attempt}"
        try:
            settings = self.brdf_settings
            res = retry_dead_attempt(settings, get_database(settings.db_url), self.connection, job_id, attempt, why,
                                     unclaimed=True, drop_rq_job=False)
        except Exception as e:  # noqa: BLE001 - the heartbeat check retries the job later
            log.warning("job %s: could not settle the dead attempt %d now (%s)", job_id, attempt, e)
            return
        if res is not None:
            self._horse_handled = job.id
            log.warning("job %s: %s -> %s", job_id, why, res)

    def handle_job_failure(self, job, queue, started_job_registry=None, exc_string="", execution=None):
        super().handle_job_failure(job, queue, started_job_registry=started_job_registry, exc_string=exc_string,
                                   execution=execution)
        if self._horse_handled == job.id:
            self._horse_handled = None
            try:
                queue.failed_job_registry.remove(job)
            except Exception:  # noqa: BLE001 - cosmetic
                pass


class InProcessWorker(_Reregistering, SimpleWorker):
    pass


def run_worker(settings: Settings, queues: list[str], *, burst: bool = False, fork: bool = True,
               name: str | None = None, max_jobs: int | None = None) -> int:
    bad = [q for q in queues if q not in QUEUES]
    if bad:
        raise ValueError(f"--queues: unknown queue(s) {bad}; known: {list(QUEUES)}")

    configure(settings)

    db = get_database(settings.db_url)
    name = name or f"{socket.gethostname()}-{uuid.uuid4().hex[:6]}"
    cls = ForkingWorker if fork else InProcessWorker
    delay = 1.0
    while True:
        conn = redis_conn(settings.redis_url)
        try:
            conn.ping()
            try:
                done = reconcile(settings, db, conn)
                if any(done.values()):
                    log.info("reconcile at start: %s", done)
                swept = sweep_work_dirs(settings, db)
                if swept:
                    log.info("removed %d work directories of attempts no longer running", swept)
            except Exception as e:  # noqa: BLE001 - a failed reconcile must not stop the worker
                log.warning("reconcile failed: %s", e)
            w = cls([get_queue(q, conn) for q in queues], connection=conn, serializer=JSONSerializer,
                    name=f"{name}.{int(time.time())}", worker_ttl=settings.worker_ttl_s,
                    job_monitoring_interval=5)
            w.brdf_settings = settings
            w.work(burst=burst, max_jobs=max_jobs, logging_level="INFO", with_scheduler=False)
            return 0
        except (redis.ConnectionError, redis.TimeoutError) as e:
            log.error("Redis at %s unreachable (%s); retrying in %.0f s", settings.redis_url, e, delay)
            time.sleep(delay)
            delay = min(delay * 2, 30.0)
