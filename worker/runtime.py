"""The job lifecycle every job type runs in: claim, heartbeat, progress, artifacts, settle, retry.

:func:`run_attempt` (called by the RQ entry point :func:`worker.jobs.run_job`):

1. claims the attempt with a compare-and-set (``queued`` -> ``running`` where ``attempts`` is
   this attempt), so a duplicate or stale RQ job does nothing;
2. starts a heartbeat thread that every ``heartbeat_s`` writes progress, ETA and a heartbeat to
   the database (and progress to the RQ job's ``meta``), and watches for cancellation: a job
   canceled in the database is interrupted in the job's main thread (SIGUSR1 -> JobCanceled);
3. on success registers the artifacts and sets ``done`` in one transaction; on a CoreError
   (bad input: retrying cannot help) or a timeout sets ``failed`` with the error; on any other
   exception queues the next attempt while attempts are left.

A job type (:class:`JobType`) is a name, a queue, the pydantic model of its parameters, its
stages and one function ``run(ctx, params)`` that gets a :class:`JobContext`; the job modules
(``worker/render.py``, ``reconstruct.py``, ``relight.py``, ``night.py``) each define one, and
:mod:`worker.registry` lists them. This module imports none of them.
"""

from __future__ import annotations

import logging
import math
import mimetypes
import os
import shutil
import signal
import socket
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Mapping

from pydantic import BaseModel
from sqlalchemy import delete, func, select, update

from core.bundle import ArchiveLimits, unpack_bundle
from core.errors import CoreError
from worker.db import (Artifact, Database, Job, JobStage, Scene, attempt_ended, attempt_started, get_database,
                       pending_stage_names, utcnow)
from worker.settings import Settings, get_settings
from worker.storage import ArtifactStore, get_store

log = logging.getLogger("brdf.jobs")

CONTENT_TYPES = {".exr": "image/x-exr", ".mp4": "video/mp4", ".png": "image/png", ".json": "application/json",
                 ".zip": "application/zip", ".gz": "application/gzip", ".hdr": "image/vnd.radiance"}


def content_type(name: str) -> str:
    ext = os.path.splitext(name)[1].lower()
    return CONTENT_TYPES.get(ext) or mimetypes.guess_type(name)[0] or "application/octet-stream"


def finite_metrics(metrics: dict, where: str) -> dict:
    """``metrics`` with every NaN or infinite number replaced by None (JSON has no NaN: the API,
    the database's JSON and the dashboard would get invalid documents), each replacement logged
    with its key. A curve keeps its finite points only."""
    out = {}
    for k, v in metrics.items():
        if isinstance(v, float) and not math.isfinite(v):
            log.warning("%s: metric %r is %s (e.g. no test frames to measure it on); stored as null", where, k, v)
            v = None
        elif isinstance(v, (list, tuple)):
            bad = [x for x in v if isinstance(x, float) and not math.isfinite(x)]
            if bad:
                log.warning("%s: curve %r has %d non-finite value(s); dropped", where, k, len(bad))
                v = [x for x in v if not (isinstance(x, float) and not math.isfinite(x))]
        out[k] = v
    return out


class JobCanceled(BaseException):
    """Raised in the job's main thread when the job was canceled (BaseException so that a job
    function's ``except Exception`` cannot swallow it)."""


@dataclass
class _Progress:
    stage: str | None = None
    fraction: float = 0.0
    dirty: bool = True
    stage_fraction: dict[str, float] = field(default_factory=dict)


class JobContext:
    """What a job function gets: its row, a scratch directory, the store, and progress calls."""

    def __init__(self, settings: Settings, db: Database, store: ArtifactStore, job: Job, workdir: Path,
                 chain: tuple[str, int, int] | None = None):
        self.settings = settings
        #: ``(stage, index, count)`` when this run is one stage of a chained job, else None.
        self.chain = chain
        #: Artifact keys of this run (a chain stage's outputs outlive a later stage's retry).
        self.key_prefix = (f"jobs/{job.id}/{chain[0]}.a{job.attempts}" if chain
                           else f"jobs/{job.id}/{job.attempts}")
        self.db = db
        self.store = store
        self.job = job
        self.workdir = workdir
        self.started = time.monotonic()
        self.canceled = threading.Event()
        self._p = _Progress()
        self._artifacts: list[tuple[str, str, int]] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.interrupt = threading.current_thread() is threading.main_thread()

    # -- called by job functions -----------------------------------------------------------
    def stage(self, name: str, weight_done: float | None = None) -> None:
        """Enter stage ``name``; the previous stage is marked done."""
        now = utcnow()
        with self.db.session() as s:
            if self._p.stage:
                s.execute(update(JobStage).where(JobStage.job_id == self.job.id, JobStage.name == self._p.stage)
                          .values(state="done", progress=1.0, finished_at=now))
            s.execute(update(JobStage).where(JobStage.job_id == self.job.id, JobStage.name == name)
                      .values(state="running", started_at=now, progress=0.0))
            s.execute(update(Job).where(Job.id == self.job.id, Job.state == "running").values(stage=name))
        with self._lock:
            self._p.stage = name
            self._p.dirty = True

    def progress(self, fraction: float, stage_fraction: float | None = None) -> None:
        """Report overall progress in [0, 1] (and optionally the current stage's)."""
        with self._lock:
            self._p.fraction = min(max(float(fraction), self._p.fraction), 1.0)
            if stage_fraction is not None and self._p.stage:
                self._p.stage_fraction[self._p.stage] = min(max(float(stage_fraction), 0.0), 1.0)
            self._p.dirty = True

    def stage_progress(self, fraction: float) -> None:
        """Report the current stage's progress in [0, 1]; the job's overall progress follows (a
        chain's stages count equally; otherwise the stage is the whole job)."""
        f = min(max(float(fraction), 0.0), 1.0)
        if self.chain:
            _, i, n = self.chain
            self.progress((i + f) / n, stage_fraction=f)
        else:
            self.progress(f, stage_fraction=f)

    def stage_metrics(self, metrics: dict, merge: bool = False) -> None:
        """Replace (or with ``merge``, update) the current stage's metrics (e.g. ``{"loss":
        [...]}``: lists are drawn as curves on the dashboard)."""
        if not self._p.stage:
            return
        metrics = finite_metrics(metrics, f"job {self.job.id} stage {self._p.stage}")
        where = (JobStage.job_id == self.job.id, JobStage.name == self._p.stage)
        with self.db.session() as s:
            old = s.scalar(select(JobStage.metrics).where(*where)) if merge else None
            s.execute(update(JobStage).where(*where).values(metrics={**(old or {}), **metrics}))

    def add_artifact(self, local_path: Path, name: str) -> None:
        """Upload a finished output file; it is listed once the job is done."""
        key = f"{self.key_prefix}/{name}"
        size = self.store.put_file(local_path, key)
        self._artifacts.append((name, key, size))

    def check_canceled(self) -> None:
        if self.canceled.is_set():
            raise JobCanceled()

    def scene_dir(self) -> Path:
        """The job's scene bundle, unpacked in this machine's scene cache (fetched from the
        artifact store the first time, so workers on other machines need no shared disk)."""
        with self.db.session() as s:
            scene = s.get(Scene, self.job.scene_id)
            if scene is None:
                raise LookupError(f"scene {self.job.scene_id} is gone")
            key, fmt = scene.storage_key, scene.archive_format
        cache = self.settings.data_dir / "cache" / "scenes" / self.job.scene_id
        marker = cache / ".complete"
        if marker.is_file():
            return Path(marker.read_text())
        tmp = self.workdir / f"bundle.{fmt}"
        self.store.get_file(key, tmp)
        staging = cache.parent / f".{self.job.scene_id}.{os.getpid()}.{time.time_ns()}"
        root = unpack_bundle(tmp, staging / "b", ArchiveLimits(
            max_entries=self.settings.archive_max_entries, max_total_bytes=self.settings.archive_max_total_bytes))
        rel = root.relative_to(staging)
        try:
            os.replace(staging, cache)
        except OSError:  # another worker cached it meanwhile
            shutil.rmtree(staging, ignore_errors=True)
        else:
            marker.write_text(str(cache / rel))
        tmp.unlink(missing_ok=True)
        return Path(marker.read_text())

    # -- heartbeat thread ------------------------------------------------------------------
    def _flush(self) -> None:
        with self._lock:
            p = self._p.fraction
            stage = self._p.stage
            stage_fracs = dict(self._p.stage_fraction)
            self._p.dirty = False
        elapsed = time.monotonic() - self.started
        if self.chain:  # a chain's ETA is that of the running stage (later stages not yet timed)
            f = stage_fracs.get(stage or "", 0.0)
            eta = elapsed * (1 - f) / f if f > 0.01 else None
        else:
            eta = elapsed * (1 - p) / p if p > 0.01 else None
        with self.db.session() as s:
            s.execute(update(Job).where(Job.id == self.job.id, Job.state == "running",
                                        Job.attempts == self.job.attempts)
                      .values(heartbeat_at=utcnow(), progress=p, eta_s=eta))
            for name, f in stage_fracs.items():
                s.execute(update(JobStage).where(JobStage.job_id == self.job.id, JobStage.name == name,
                                                 JobStage.state == "running").values(progress=f))
            state = s.execute(select(Job.state, Job.attempts).where(Job.id == self.job.id)).one_or_none()
        if state is None or state[0] == "canceled" or state[1] != self.job.attempts:
            if not self.canceled.is_set():
                self.canceled.set()
                if self.interrupt:
                    os.kill(os.getpid(), signal.SIGUSR1)
        try:
            from rq import get_current_job

            rj = get_current_job()
            if rj is not None:
                rj.meta.update({"progress": p, "stage": stage, "eta_s": eta})
                rj.save_meta()
        except Exception:  # noqa: BLE001 - Redis is not the truth; the DB row was written
            pass

    def _beat(self) -> None:
        while not self._stop.wait(self.settings.heartbeat_s):
            try:
                self._flush()
            except Exception as e:  # noqa: BLE001 - keep beating through a transient DB error
                log.warning("job %s heartbeat failed: %s", self.job.id, e)

    def start(self) -> None:
        self._thread = threading.Thread(target=self._beat, name=f"heartbeat-{self.job.id}", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=10)


@dataclass(frozen=True)
class JobType:
    name: str
    queue: str
    params: type[BaseModel]
    run: Callable[[JobContext, BaseModel], None]
    stages: tuple[str, ...]
    needs_scene: bool = True
    #: Returns why this build cannot serve a valid request (e.g. it asks for a stage that has not
    #: landed), or None; the gateway then answers 409 and queues nothing.
    unavailable: Callable[[BaseModel], str | None] | None = None
    #: ``(session, scene_id, tenant) -> reason or None``: what the scene must have before this job
    #: can run (e.g. a finished reconstruction); the gateway answers 409 with the reason.
    precondition: Callable[[object, str, str], str | None] | None = None
    #: A chained job type (the training stages): ``{stage name: run(ctx, params)}``. Each stage
    #: of a job is then its own RQ job, enqueued behind the previous one with ``depends_on``; the
    #: job's row in the database tracks the chain, and a retry resumes at the first stage that is
    #: not done. ``run`` is unused for such a type.
    stage_fns: Mapping[str, Callable[[JobContext, BaseModel], None]] | None = None
    #: The stages a request asks for (chained types: e.g. the requested subset of the chain, in
    #: chain order); default: all of :attr:`stages`.
    stages_for: Callable[[BaseModel], tuple[str, ...]] | None = None

    @property
    def chained(self) -> bool:
        return self.stage_fns is not None

    def stages_of(self, params: BaseModel) -> tuple[str, ...]:
        return tuple(self.stages_for(params)) if self.stages_for is not None else self.stages


def _claim(db: Database, job_id: str, attempt: int, stage: str | None = None) -> Job | None:
    """Compare-and-set ``queued`` -> ``running`` for this attempt (and, for a chain, only when
    ``stage`` is its first stage not done); None when the job is not this run's to take."""
    now = utcnow()
    worker = f"{socket.gethostname()}.{os.getpid()}"
    try:
        from rq import get_current_job

        rj = get_current_job()
        if rj is not None and rj.worker_name:
            worker = rj.worker_name
    except Exception:  # noqa: BLE001
        pass
    with db.session() as s:
        if stage is not None:
            rest = pending_stage_names(s, job_id)
            if not rest or rest[0] != stage:
                return None
        n = s.execute(update(Job).where(Job.id == job_id, Job.state == "queued", Job.attempts == attempt)
                      .values(state="running", started_at=func.coalesce(Job.started_at, now) if stage else now,
                              heartbeat_at=now, worker_name=worker, eta_s=None, finished_at=None,
                              **({} if stage else {"progress": 0.0}))).rowcount
        if not n:
            return None
        attempt_started(s, job_id, attempt, worker, now)
        reset = update(JobStage).where(JobStage.job_id == job_id)
        if stage is not None:
            reset = reset.where(JobStage.state != "done")
        s.execute(reset.values(state="queued", progress=0.0, started_at=None, finished_at=None))
        return s.get(Job, job_id)


def _settle(db: Database, job: Job, **values) -> bool:
    """End the running attempt with ``values`` (state, error); its attempt row records the same."""
    with db.session() as s:
        n = s.execute(update(Job).where(Job.id == job.id, Job.state == "running", Job.attempts == job.attempts)
                      .values(finished_at=utcnow(), eta_s=None, **values)).rowcount
        if n:
            attempt_ended(s, job.id, job.attempts, values.get("state", "failed"), values.get("error"))
        return bool(n)


def run_attempt(job_id: str, attempt: int, stage: str | None, job_type: Callable[[str], JobType | None],
                requeue: Callable[[Settings, Database, Job], object]) -> dict:
    """Run attempt ``attempt`` of job ``job_id`` (of its ``stage``, for a chained job): claim it,
    beat, run the type that ``job_type`` names, and settle the outcome; a retry is queued with
    ``requeue(settings, db, job)``. Returns a small JSON summary (the RQ job's result)."""
    settings = get_settings()
    db = get_database(settings.db_url)
    store = get_store(settings.store_url, settings.artifact_store_options)
    job = _claim(db, job_id, attempt, stage)
    if job is None:
        return {"job": job_id, "attempt": attempt, "stage": stage,
                "skipped": "not queued for this attempt and stage (stale or canceled)"}
    jt = job_type(job.type)
    chain = None
    if stage is not None:
        with db.session() as s:
            names = list(s.scalars(select(JobStage.name).where(JobStage.job_id == job.id).order_by(JobStage.id)))
        chain = (stage, names.index(stage), len(names))
    workdir = settings.data_dir / "work" / (f"{job.id}.{attempt}" + (f".{stage}" if stage else ""))
    shutil.rmtree(workdir, ignore_errors=True)
    workdir.mkdir(parents=True)
    ctx = JobContext(settings, db, store, job, workdir, chain)

    def on_cancel(signum, frame):
        if ctx.canceled.is_set():
            raise JobCanceled()

    main = threading.current_thread() is threading.main_thread()
    old = signal.signal(signal.SIGUSR1, on_cancel) if main else None
    ctx.start()
    outcome = "failed"
    try:
        if jt is None:
            raise CoreError(f"job type {job.type!r} is not available in this build")
        if (stage is not None) != jt.chained or (stage is not None and stage not in jt.stage_fns):
            raise CoreError(f"job type {job.type!r} has no stage {stage!r} in this build")
        params = jt.params.model_validate(job.params)
        if stage is not None:
            ctx.stage(stage)
            jt.stage_fns[stage](ctx, params)
        else:
            jt.run(ctx, params)
        ctx.check_canceled()
        ctx.stop()
        last = chain is None or chain[1] == chain[2] - 1
        now = utcnow()
        with db.session() as s:
            if last:
                values = dict(state="done", progress=1.0, finished_at=now, eta_s=None, error=None)
            else:  # the next stage's RQ job is released by RQ when this one returns
                values = dict(state="queued", progress=(chain[1] + 1) / chain[2], eta_s=None, worker_name=None,
                              enqueued_at=now, heartbeat_at=now)
            n = s.execute(update(Job).where(Job.id == job.id, Job.state == "running", Job.attempts == attempt)
                          .values(**values)).rowcount
            if n and last:
                attempt_ended(s, job.id, attempt, "done")
            if n:
                names = [name for name, _, _ in ctx._artifacts]
                if chain is None:
                    s.execute(delete(Artifact).where(Artifact.job_id == job.id))
                elif names:
                    s.execute(delete(Artifact).where(Artifact.job_id == job.id, Artifact.name.in_(names)))
                for name, key, size in ctx._artifacts:
                    s.add(Artifact(job_id=job.id, name=name, kind=os.path.splitext(name)[1].lstrip(".").lower(),
                                   content_type=content_type(name), size_bytes=size, storage_key=key))
                done = update(JobStage).where(JobStage.job_id == job.id, JobStage.state != "done")
                if chain is not None:
                    done = done.where(JobStage.name == stage)
                s.execute(done.values(state="done", progress=1.0, finished_at=now))
        outcome = ("done" if last else "stage_done") if n else "superseded"
    except JobCanceled:
        outcome = "canceled"
    except CoreError as e:
        _settle(db, job, state="failed", error=f"{type(e).__name__}: {e}")
    except Exception as e:  # noqa: BLE001 - anything else may be transient: retry
        from rq.timeouts import JobTimeoutException

        msg = f"{type(e).__name__}: {e}"
        if isinstance(e, JobTimeoutException):
            _settle(db, job, state="failed", error=f"timed out: {e}")
        elif attempt < job.max_attempts:
            with db.session() as s:
                n = s.execute(update(Job).where(Job.id == job.id, Job.state == "running", Job.attempts == attempt)
                              .values(state="queued", attempts=attempt + 1, eta_s=None, worker_name=None,
                                      enqueued_at=None, error=f"attempt {attempt} failed: {msg}")).rowcount
                if n:
                    attempt_ended(s, job.id, attempt, "retried", f"attempt {attempt} failed: {msg}",
                                  next_attempt=True)
            if n:
                job.attempts = attempt + 1
                requeue(settings, db, job)
            outcome = "retry"
        else:
            _settle(db, job, state="failed", error=f"attempt {attempt} of {job.max_attempts} failed: {msg}")
        log.exception("job %s attempt %d failed", job.id, attempt)
    finally:
        ctx.stop()
        _final_meta(outcome)
        if main:
            signal.signal(signal.SIGUSR1, old)
        shutil.rmtree(workdir, ignore_errors=True)
        if outcome not in ("done", "stage_done"):
            try:
                store.delete_prefix(ctx.key_prefix)
            except Exception as e:  # noqa: BLE001
                log.warning("job %s: could not remove partial outputs: %s", job.id, e)
    return {"job": job_id, "attempt": attempt, "stage": stage, "outcome": outcome}


def _final_meta(outcome: str) -> None:
    try:
        from rq import get_current_job

        rj = get_current_job()
        if rj is not None:
            rj.meta.update({"outcome": outcome, **({"progress": 1.0, "eta_s": 0.0} if outcome == "done" else {})})
            rj.save_meta()
    except Exception:  # noqa: BLE001 - Redis is not the truth
        pass
