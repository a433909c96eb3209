"""Operations in-process: readiness with waiting jobs and no live worker, the operations
metrics, retry and cancel through the API (and from a dashboard session with its CSRF token),
the clean-up of failed jobs' artifacts and dead attempts' work directories, and the location of
a malformed JSON body."""

from __future__ import annotations

import re
from datetime import timedelta

import pytest
from sqlalchemy import select, update

from conftest_shared import OPERATOR_KEY


@pytest.fixture
def scene_id(client, scene_zip):
    r = client.post("/scenes", content=scene_zip.read_bytes(), headers={"Content-Type": "application/zip"})
    assert r.status_code == 201, r.text
    return r.json()["id"]


def metric(text: str, name: str, **labels) -> float:
    lab = "{" + ",".join(f'{k}="{v}"' for k, v in labels.items()) + "}" if labels else ""
    m = re.search(rf"^{re.escape(name + lab)} (\S+)$", text, re.M)
    assert m, f"{name}{lab} missing from /metrics"
    return float(m.group(1))


def _live_worker(settings, queues):
    """A registered RQ worker with a fresh heartbeat (no process: readiness reads Redis only)."""
    from rq import Worker
    from rq.serializers import JSONSerializer

    from worker.queue import get_queue, redis_conn

    conn = redis_conn(settings.redis_url)
    w = Worker([get_queue(q, conn) for q in queues], connection=conn, serializer=JSONSerializer,
               name=f"probe-{'-'.join(queues)}")
    w.register_birth()
    return w


def test_readyz_503_when_jobs_wait_without_a_worker(client, settings, scene_id):
    assert client.get("/readyz").status_code == 200  # nothing waits: no worker needed
    jid = client.post(f"/scenes/{scene_id}/render", json={}).json()["id"]
    r = client.get("/readyz")
    assert r.status_code == 503, r.text
    why = r.json()["checks"]["workers"]
    assert why.startswith("queue 'render': 1 job(s) waiting (oldest ") and "no live worker serves it" in why
    text = client.get("/metrics").text
    assert metric(text, "brdf_jobs_waiting", queue="render") == 1
    assert metric(text, "brdf_oldest_waiting_job_seconds", queue="render") >= 0
    assert metric(text, "brdf_queue_workers", queue="render") == 0
    # a worker of the other queue does not serve it...
    _live_worker(settings, ["train"])
    assert client.get("/readyz").status_code == 503
    assert metric(client.get("/metrics").text, "brdf_queue_workers", queue="train") == 1
    # ...a live worker of this queue does
    w = _live_worker(settings, ["render"])
    r = client.get("/readyz")
    assert r.status_code == 200 and r.json()["checks"]["workers"] == "ok", r.text
    assert metric(client.get("/metrics").text, "brdf_queue_workers", queue="render") == 1
    # a worker whose heartbeat is older than worker_stale_s no longer counts
    from worker.queue import redis_conn

    old = (w.last_heartbeat - timedelta(seconds=settings.worker_stale_s + 5)).strftime("%Y-%m-%dT%H:%M:%S.%fZ")
    redis_conn(settings.redis_url).hset(w.key, "last_heartbeat", old)
    assert client.get("/readyz").status_code == 503
    assert client.delete(f"/jobs/{jid}").json()["state"] == "canceled"
    assert client.get("/readyz").status_code == 200


def test_retry_of_a_failed_job_is_a_new_attempt(client, app, scene_id):
    db = app.state.db
    from worker.db import Job

    jid = client.post(f"/scenes/{scene_id}/render", json={}).json()["id"]
    assert client.post(f"/jobs/{jid}/retry").status_code == 409  # queued: nothing to retry
    with db.session() as s:
        s.execute(update(Job).where(Job.id == jid).values(state="failed", error="RuntimeError: disk full"))
    r = client.post(f"/jobs/{jid}/retry")
    assert r.status_code == 202 and r.json()["state"] == "queued", r.text
    j = client.get(f"/jobs/{jid}").json()
    assert j["attempts"] == 2 and j["error"] is None and j["state"] == "queued"
    h = j["attempt_history"]
    assert [a["attempt"] for a in h] == [1, 2] and h[0]["outcome"] == "failed"
    assert h[0]["reason"].startswith("RuntimeError: disk full; then retried by request (operator key")
    assert metric(client.get("/metrics").text, "brdf_job_retries_total") == 1
    assert client.post("/jobs/nope/retry").status_code == 404
    # a retry has waited once already: it goes to the front of its queue, before a newer job
    other = client.post(f"/scenes/{scene_id}/render", json={"fps": 3}).json()["id"]
    with db.session() as s:
        s.execute(update(Job).where(Job.id == jid).values(state="failed"))
    assert client.post(f"/jobs/{jid}/retry").status_code == 202
    from worker.db import rq_job_id
    from worker.queue import get_queue

    ids = get_queue("render", app.state.rconn()).job_ids
    assert ids[0] == rq_job_id(jid, 3) and rq_job_id(other, 1) in ids[1:], ids


def test_client_cannot_retry_another_tenants_job(client, keys, scene_id, app):
    from worker.db import Job

    jid = client.post(f"/scenes/{scene_id}/render", json={}).json()["id"]
    with app.state.db.session() as s:
        s.execute(update(Job).where(Job.id == jid).values(state="failed"))
    r = client.post(f"/jobs/{jid}/retry", headers={"Authorization": f"Bearer {keys['acme']}"})
    assert r.status_code == 404


def test_dashboard_session_writes_only_with_its_csrf_token(client, scene_id):
    from services.auth import SESSION_COOKIE, csrf_token

    jid = client.post(f"/scenes/{scene_id}/render", json={}).json()["id"]
    r = client.post("/dashboard/login", data={"key": OPERATOR_KEY}, headers={"Authorization": ""},
                    follow_redirects=False)
    token = r.cookies.get(SESSION_COOKIE) or client.cookies.get(SESSION_COOKIE)
    anon = {"Authorization": ""}
    assert client.delete(f"/jobs/{jid}", headers=anon).status_code == 401
    assert client.delete(f"/jobs/{jid}", headers={**anon, "X-CSRF-Token": "0" * 64}).status_code == 401
    r = client.delete(f"/jobs/{jid}", headers={**anon, "X-CSRF-Token": csrf_token(token)})
    assert r.status_code == 200 and r.json()["state"] == "canceled"
    r = client.post(f"/jobs/{jid}/retry", headers={**anon, "X-CSRF-Token": csrf_token(token)})
    assert r.status_code == 202


def test_failed_jobs_artifacts_expire_after_the_ttl(app, settings, scene_id, client, tmp_path):
    from worker.db import Artifact, Job, utcnow
    from worker.queue import expire_failed_artifacts

    db, store = app.state.db, app.state.store
    src = tmp_path / "a.bin"
    src.write_bytes(b"x" * 100)
    jobs = {}
    for name, state, age_s in (("old_failed", "failed", settings.failed_artifact_ttl_s + 60),
                               ("new_failed", "failed", 10), ("old_done", "done", settings.failed_artifact_ttl_s + 60),
                               ("old_canceled", "canceled", settings.failed_artifact_ttl_s + 60)):
        jid = client.post(f"/scenes/{scene_id}/render", json={"fps": 5 + len(jobs)}).json()["id"]
        key = f"jobs/{jid}/volume.a1/x.bin"
        store.put_file(src, key)
        with db.session() as s:
            s.execute(update(Job).where(Job.id == jid).values(state=state,
                                                               finished_at=utcnow() - timedelta(seconds=age_s)))
            s.add(Artifact(job_id=jid, name="volume/x.bin", kind="bin", content_type="application/octet-stream",
                           size_bytes=100, storage_key=key))
        jobs[name] = (jid, key)
    assert expire_failed_artifacts(settings, db) == 2
    for name, (jid, key) in jobs.items():
        kept = name in ("new_failed", "old_done")
        assert store.exists(key) == kept, name
        with db.session() as s:
            assert (s.scalar(select(Artifact.id).where(Artifact.job_id == jid)) is not None) == kept, name
    assert expire_failed_artifacts(settings, db) == 0


def test_ttl_setting_from_the_environment(monkeypatch):
    from pydantic import ValidationError

    from worker.settings import Settings

    monkeypatch.setenv("BRDF_FAILED_ARTIFACT_TTL_S", "3600")
    assert Settings().failed_artifact_ttl_s == 3600
    monkeypatch.setenv("BRDF_FAILED_ARTIFACT_TTL_S", "-1")
    with pytest.raises(ValidationError, match="failed_artifact_ttl_s"):
        Settings()


def test_dead_attempts_work_dirs_are_swept(app, settings, client, scene_id):
    from worker.db import Job
    from worker.queue import sweep_work_dirs

    db = app.state.db
    running = client.post(f"/scenes/{scene_id}/render", json={}).json()["id"]
    dead = client.post(f"/scenes/{scene_id}/render", json={"fps": 3}).json()["id"]
    with db.session() as s:
        s.execute(update(Job).where(Job.id == running).values(state="running"))
        s.execute(update(Job).where(Job.id == dead).values(state="queued", attempts=2))
    work = settings.data_dir / "work"
    keep = [work / f"{running}.1", work / f"{dead}.2"]
    gone = [work / f"{dead}.1", work / f"{dead}.1.volume", work / "0123456789abcdef.1"]
    for d in keep + gone:
        (d / "out").mkdir(parents=True)
    assert sweep_work_dirs(settings, db) == len(gone)
    assert all(d.is_dir() for d in keep) and not any(d.exists() for d in gone)


def test_malformed_json_names_line_and_column(client, scene_id):
    r = client.post(f"/scenes/{scene_id}/render", content=b'{"split": "test",\n "fps": }',
                    headers={"Content-Type": "application/json"})
    assert r.status_code == 422
    err = r.json()["errors"][0]
    assert err.startswith("body: malformed JSON at line 2, column 9 (character 26): "), err
    assert "body.26" not in r.text and "body.25" not in r.text


def test_a_job_taken_but_not_started_by_a_dead_worker_is_retried(app, settings, client, scene_id, monkeypatch):
    """A worker (or its work horse) that dies after taking a job from the queue but before the job
    function claimed it leaves the job queued in the database with its RQ job gone: it is retried
    (by the supervisor or the horse handler at once, by the reconcile loop when RQ reports the
    job abandoned), never failed as 'failed before it ran'."""
    import worker.queue as Q
    from worker.db import Job, utcnow

    db = app.state.db
    jid = client.post(f"/scenes/{scene_id}/render", json={}).json()["id"]
    assert Q.retry_dead_attempt(settings, db, None, jid, 1, "horse died") is None  # not running: not by default
    assert Q.retry_dead_attempt(settings, db, None, jid, 1, "worker w died holding it", unclaimed=True) == "retried"
    j = client.get(f"/jobs/{jid}").json()
    assert j["state"] == "queued" and j["attempts"] == 2
    assert [(a["attempt"], a["outcome"], a["reason"]) for a in j["attempt_history"]] == [
        (1, "retried", "worker w died holding it"), (2, "queued", None)]
    assert Q.retry_dead_attempt(settings, db, None, jid, 1, "again", unclaimed=True) is None  # stale attempt

    # the reconcile loop: RQ moved the attempt's job to its failed registry as abandoned
    with db.session() as s:
        s.execute(update(Job).where(Job.id == jid).values(enqueued_at=None, created_at=utcnow() - timedelta(seconds=60)))
    monkeypatch.setattr(Q, "_rq_status", lambda conn, rq_id: (
        "failed", "Moved to FailedJobRegistry, due to AbandonedJobError, at 2026-01-01 00:00:00"))
    out = Q.reconcile(settings, db, app.state.rconn())
    assert out["retried"] == 1 and out["rq_failed"] == 0, out
    j = client.get(f"/jobs/{jid}").json()
    assert j["state"] == "queued" and j["attempts"] == 3 and "AbandonedJobError" in j["attempt_history"][1]["reason"]
    # any other failure of RQ's before the job ran still fails the job
    with db.session() as s:
        s.execute(update(Job).where(Job.id == jid).values(enqueued_at=None))
    monkeypatch.setattr(Q, "_rq_status", lambda conn, rq_id: ("failed", "DeserializationError: bad payload"))
    assert Q.reconcile(settings, db, app.state.rconn())["rq_failed"] == 1
    assert client.get(f"/jobs/{jid}").json()["state"] == "failed"


def test_cancel_against_a_locked_database_is_503_and_changes_nothing(client, app, scene_id, tmp_path, monkeypatch):
    """A worker frozen inside a SQLite write transaction holds the lock past the busy timeout:
    the cancel gets the database's own "database is locked" error. The gateway answers 503 with
    Retry-After and the reason (it was a bare 500), and the job is still queued."""
    import sqlite3

    import sqlalchemy.exc

    import services.routes.jobs as job_routes
    from worker.db import Job

    r = client.post(f"/scenes/{scene_id}/reconstruct", json={})
    assert r.status_code == 202, r.text
    jid = r.json()["id"]

    # the genuine error: a second connection with no busy timeout against a held write lock
    path = tmp_path / "locked.db"
    holder = sqlite3.connect(path, isolation_level=None)
    holder.execute("CREATE TABLE t (x)")
    holder.execute("BEGIN EXCLUSIVE")
    try:
        sqlite3.connect(path, timeout=0).execute("INSERT INTO t VALUES (1)")
    except sqlite3.OperationalError as e:
        locked = sqlalchemy.exc.OperationalError("UPDATE jobs SET state=?", ("canceled",), e)
    finally:
        holder.close()
    assert "database is locked" in str(locked.orig)

    def cancel_while_locked(db, conn, job_id):
        raise locked
    monkeypatch.setattr(job_routes, "request_cancel", cancel_while_locked)
    r = client.delete(f"/jobs/{jid}")
    assert r.status_code == 503, r.text
    assert r.headers["Retry-After"] == "5"
    assert "database is locked" in r.json()["detail"] and "nothing was changed" in r.json()["detail"]
    with app.state.db.session() as s:
        assert s.get(Job, jid).state == "queued"

    monkeypatch.undo()
    r = client.delete(f"/jobs/{jid}")
    assert r.status_code == 200 and r.json()["state"] == "canceled", r.text
