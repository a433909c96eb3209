"""The worker entry point (``brdf worker``): an RQ worker on the ``render`` and/or ``train``
queues with the JSON serializer. It reconciles the queue with the database when it starts (so a
machine coming back recovers jobs lost with it) and keeps reconnecting while Redis is down.

Run separate workers per queue (``--queues render`` on some machines, ``--queues train`` on
others) so a long training never starves relight requests; ``--no-fork`` runs jobs in the
worker process itself (``rq.SimpleWorker``) so loaded models stay warm between jobs.
"""

from __future__ import annotations

import logging
import socket
import time
import uuid

import redis
from rq import SimpleWorker, Worker, worker_registration
from rq.serializers import JSONSerializer

from worker.db import get_database
from worker.queue import get_queue, reconcile, redis_conn
from worker.settings import QUEUES, Settings

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
    pass


class InProcessWorker(_Reregistering, SimpleWorker):
    pass


def run_worker(settings: Settings, queues: list[str], *, burst: bool = False, fork: bool = True,
               name: str | None = None, max_jobs: int | None = None) -> int:
    bad = [q for q in queues if q not in QUEUES]
    if bad:
        raise ValueError(f"--queues: unknown queue(s) {bad}; known: {list(QUEUES)}")
    from worker.registry import job_type

    job_type("render")  # import every job module before forking work horses
    from worker.settings import configure

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
            except Exception as e:  # noqa: BLE001 - a failed reconcile must not stop the worker
                log.warning("reconcile failed: %s", e)
            w = cls([get_queue(q, conn) for q in queues], connection=conn, serializer=JSONSerializer,
                    name=f"{name}.{int(time.time())}")
            w.work(burst=burst, max_jobs=max_jobs, logging_level="INFO", with_scheduler=False)
            return 0
        except (redis.ConnectionError, redis.TimeoutError) as e:
            log.error("Redis at %s unreachable (%s); retrying in %.0f s", settings.redis_url, e, delay)
            time.sleep(delay)
            delay = min(delay * 2, 30.0)
