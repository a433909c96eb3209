"""Worker supervision for ``brdf up``: the workers are child processes watched by a thread of
the gateway process. A worker that exits (killed, crashed, out of memory) is restarted after a
backoff (1 s, doubling while it keeps dying within 10 s of its start, at most
``restart_backoff_max_s``); each restart is logged and counted (``/metrics``:
``brdf_worker_restarts_total``).

When a worker dies, the jobs it was running are settled at once instead of at the next
heartbeat check: if its work horse died with it, each running attempt is failed and retried
(:func:`worker.queue.retry_dead_attempt`); a work horse that outlived its parent keeps running
and finishes (or, if it dies later, the heartbeat check retries it). The dead worker's RQ
registration is removed so readiness and the dashboard stop counting it.
"""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import threading
import time
import uuid
from dataclasses import dataclass, field

from worker.db import Job, get_database
from worker.queue import parse_rq_id, redis_conn, retry_dead_attempt

log = logging.getLogger("brdf.supervisor")

#: A worker that ran at least this long before exiting restarts after the shortest backoff (a
#: crash loop, e.g. a bad setting or a missing module, dies within a second or two of its start).
HEALTHY_AFTER_S = 10.0


def _children_map() -> dict[int, list[int]]:
    out: dict[int, list[int]] = {}
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                with open(f"/proc/{d}/stat") as fh:
                    ppid = int(fh.read().rsplit(")", 1)[1].split()[1])
            except (OSError, ValueError, IndexError):
                continue
            out.setdefault(ppid, []).append(int(d))
    return out


def children(pid: int) -> list[int]:
    """The live processes whose parent is ``pid``."""
    return _children_map().get(pid, [])


def descendants(pid: int) -> list[int]:
    """Every live process below ``pid`` (an RQ work horse calls setpgrp but stays a child)."""
    tree = _children_map()
    out, todo = [], [pid]
    while todo:
        for c in tree.get(todo.pop(), []):
            out.append(c)
            todo.append(c)
    return out


def alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as fh:
            return fh.read().rsplit(")", 1)[1].split()[0] not in ("Z", "X")
    except OSError:
        return False


@dataclass
class Slot:
    index: int
    proc: subprocess.Popen | None = None
    name: str = ""
    started: float = 0.0
    restarts: int = 0
    backoff: float = 0.0
    restart_at: float | None = None
    horses: list[int] = field(default_factory=list)
    last_exit: str = ""


class WorkerSupervisor:
    """Runs ``n`` workers (``cmd`` + ``--name <slot name>``) and keeps them running."""

    def __init__(self, settings, cmd: list[str], n: int, env: dict | None = None, poll_s: float = 0.25):
        self.settings = settings
        self.cmd = cmd
        self.env = env
        self.poll_s = poll_s
        self.slots = [Slot(i) for i in range(n)]
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self.host = os.uname().nodename

    # -- the counters ------------------------------------------------------------------------
    @property
    def restarts(self) -> int:
        with self._lock:
            return sum(s.restarts for s in self.slots)

    def status(self) -> list[dict]:
        with self._lock:
            return [{"slot": s.index, "name": s.name, "pid": s.proc.pid if s.proc else None,
                     "running": bool(s.proc and s.proc.poll() is None), "restarts": s.restarts,
                     "last_exit": s.last_exit} for s in self.slots]

    # -- lifecycle ---------------------------------------------------------------------------
    def _spawn(self, s: Slot) -> None:
        s.name = f"up-{self.host}-w{s.index}-{uuid.uuid4().hex[:6]}"
        s.proc = subprocess.Popen(self.cmd + ["--name", s.name], env=self.env)
        s.started = time.monotonic()
        s.restart_at = None
        s.horses = []

    def start(self) -> None:
        with self._lock:
            for s in self.slots:
                self._spawn(s)
        self._thread = threading.Thread(target=self._loop, name="worker-supervisor", daemon=True)
        self._thread.start()

    def stop(self, timeout: float = 20.0) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5)
        procs = [s.proc for s in self.slots if s.proc is not None]
        for p in procs:
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
        for p in procs:
            try:
                p.wait(timeout=timeout)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait(5)

    def _loop(self) -> None:
        while not self._stop.wait(self.poll_s):
            for s in self.slots:
                try:
                    self._check(s)
                except Exception as e:  # noqa: BLE001 - the supervisor must keep watching
                    log.exception("supervising worker slot %d failed: %s", s.index, e)

    def _check(self, s: Slot) -> None:
        now = time.monotonic()
        if s.restart_at is not None:
            if now >= s.restart_at and not self._stop.is_set():
                with self._lock:
                    s.restarts += 1
                    self._spawn(s)
                log.warning("worker slot %d restarted as %s (pid %d; restart #%d of this slot, %d in all)",
                            s.index, s.name, s.proc.pid, s.restarts, self.restarts)
            return
        if s.proc is None:
            return
        code = s.proc.poll()
        if code is None:
            s.horses = descendants(s.proc.pid)  # remembered: after the worker's death they are orphans
            return
        ran = now - s.started
        s.backoff = 1.0 if ran >= HEALTHY_AFTER_S or s.backoff == 0 else min(
            2 * s.backoff, self.settings.restart_backoff_max_s)
        how = f"killed by signal {-code}" if code < 0 else f"exited with status {code}"
        s.last_exit = how
        log.warning("worker %s (pid %d) %s after %.0f s; restarting in %.0f s", s.name, s.proc.pid, how, ran,
                    s.backoff)
        s.restart_at = now + s.backoff
        self._worker_lost(s, how)

    def _worker_lost(self, s: Slot, how: str) -> None:
        """Unregister the dead worker from RQ and retry the attempts it was running whose work
        horse died with it."""
        from sqlalchemy import select

        st = self.settings
        conn = None
        held: list[str] = []  # the RQ jobs the dead worker had taken
        try:
            from rq import Worker
            from rq.serializers import JSONSerializer

            conn = redis_conn(st.redis_url)
            for w in Worker.all(connection=conn, serializer=JSONSerializer):
                if w.name.startswith(s.name + "."):
                    cur = w.get_current_job_id()
                    if cur:
                        held.append(cur)
                    w.register_death()
        except Exception as e:  # noqa: BLE001 - Redis may be down; its TTL removes the entry
            log.info("could not unregister worker %s: %s", s.name, e)
        horse_alive = [p for p in s.horses if alive(p)]
        if horse_alive:
            log.warning("worker %s died but its work horse(s) %s still run: their jobs go on", s.name, horse_alive)
            return
        db = get_database(st.db_url)
        with db.session() as ss:
            rows = ss.execute(select(Job.id, Job.attempts).where(Job.state == "running",
                                                                 Job.worker_name.like(f"{s.name}.%"))).all()
        for jid, attempt in rows:
            why = f"worker {s.name} {how} during attempt {attempt} (its work horse died with it)"
            res = retry_dead_attempt(st, db, conn, jid, attempt, why)
            log.warning("job %s: %s -> %s", jid, why, res)
        for rq_id in held:  # taken from the queue but not yet claimed in the database
            parsed = parse_rq_id(rq_id)
            if parsed is None or parsed[0] in {jid for jid, _ in rows}:
                continue
            why = f"worker {s.name} {how} holding attempt {parsed[1]} before it started"
            res = retry_dead_attempt(st, db, conn, parsed[0], parsed[1], why, unclaimed=True)
            if res is not None:
                log.warning("job %s: %s -> %s", parsed[0], why, res)
