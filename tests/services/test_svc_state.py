"""The state layer: SQL models on SQLite and on the machine's PostgreSQL, artifact stores
(local directory and an fsspec object store), settings from the environment, Range parsing, and
the rule that ``core`` imports no server code."""

from __future__ import annotations

import ast
import threading

import pytest
from fastapi import HTTPException
from sqlalchemy import select, update
from sqlalchemy.exc import IntegrityError

from svc_support import REPO, postgres_database
from services.db import ApiKey, IdempotencyKey
from worker.db import Artifact, Database, Job, JobStage, Scene, utcnow


def _scene(tenant="acme", **kw) -> Scene:
    d = dict(tenant=tenant, name="s", storage_key="scenes/x/bundle.zip", archive_format="zip", size_bytes=10,
             frames=2, train_frames=1, test_frames=1, cameras=["front"], times=2, objects=0, lidar_sweeps=0,
             has_ground_truth=False)
    d.update(kw)
    return Scene(**d)


def exercise_database(db: Database) -> None:
    db.create_all()
    with db.session() as s:
        sc = _scene()
        s.add(sc)
        s.flush()
        j = Job(tenant="acme", scene_id=sc.id, type="render", queue="render", params={"split": "all"})
        s.add(j)
        s.flush()
        s.add_all([JobStage(job_id=j.id, name="export"), Artifact(job_id=j.id, name="preview.png", kind="png",
                                                                      content_type="image/png", size_bytes=3,
                                                                      storage_key="jobs/x/1/preview.png")])
        jid, sid = j.id, sc.id
    with db.session() as s:
        j = s.get(Job, jid)
        assert j.created_at.tzinfo is not None and abs((utcnow() - j.created_at).total_seconds()) < 60
        assert j.params == {"split": "all"} and [st.name for st in j.stages] == ["export"]
        assert s.get(Scene, sid).cameras == ["front"]
    # idempotency keys are unique per tenant
    with db.session() as s:
        s.add(IdempotencyKey(tenant="acme", key="k", request_hash="h", resource="job", resource_id=jid))
    with pytest.raises(IntegrityError):
        with db.session() as s:
            s.add(IdempotencyKey(tenant="acme", key="k", request_hash="h2", resource="job", resource_id="other"))
    with db.session() as s:
        s.add(IdempotencyKey(tenant="globex", key="k", request_hash="h", resource="job", resource_id=jid))
    # the compare-and-set claim lets exactly one of many concurrent claimers win
    wins = []

    def claim():
        with db.session() as s:
            n = s.execute(update(Job).where(Job.id == jid, Job.state == "queued", Job.attempts == 1)
                          .values(state="running", started_at=utcnow())).rowcount
            wins.append(n)

    ts = [threading.Thread(target=claim) for _ in range(8)]
    [t.start() for t in ts]
    [t.join() for t in ts]
    assert sorted(wins) == [0] * 7 + [1]
    with db.session() as s:
        assert s.scalar(select(Job.state).where(Job.id == jid)) == "running"


def test_sqlite_database(tmp_path):
    db = Database(f"sqlite:///{tmp_path / 'x.db'}")
    exercise_database(db)
    with db.engine.connect() as c:
        assert c.exec_driver_sql("PRAGMA journal_mode").scalar() == "wal"


def test_postgresql_database():
    with postgres_database() as url:
        db = Database(url)
        try:
            exercise_database(db)
            assert db.engine.dialect.name == "postgresql"
        finally:
            db.dispose()


def test_naive_datetimes_are_refused(tmp_path):
    from datetime import datetime

    db = Database(f"sqlite:///{tmp_path / 'x.db'}")
    db.create_all()
    with pytest.raises(Exception, match="naive datetime"):
        with db.session() as s:
            s.add(ApiKey(tenant="t", scope="client", key_hash="h", created_at=datetime.now()))


@pytest.mark.parametrize("kind", ["local", "memory"])
def test_artifact_store(tmp_path, kind):
    from worker.storage import ArtifactStore, StorageError

    url = (tmp_path / "store").as_uri() if kind == "local" else f"memory://brdf-test-{tmp_path.name}"
    st = ArtifactStore(url)
    src = tmp_path / "src.bin"
    src.write_bytes(bytes(range(256)) * 10)
    assert st.put_file(src, "jobs/j1/1/frames/a.exr") == 2560
    assert st.size("jobs/j1/1/frames/a.exr") == 2560 and st.exists("jobs/j1/1/frames/a.exr")
    with st.open("jobs/j1/1/frames/a.exr") as fh:
        fh.seek(300)
        assert fh.read(4) == bytes([44, 45, 46, 47])
    st.get_file("jobs/j1/1/frames/a.exr", tmp_path / "back.bin")
    assert (tmp_path / "back.bin").read_bytes() == src.read_bytes()
    assert st.list("jobs/j1") == ["jobs/j1/1/frames/a.exr"]
    st.delete_prefix("jobs/j1")
    assert not st.exists("jobs/j1/1/frames/a.exr") and st.list("jobs/j1") == []
    for bad in ("../etc/passwd", "/abs", "a//b", "a/../b", ""):
        with pytest.raises(StorageError, match="invalid storage key"):
            st.size(bad)
    with pytest.raises(StorageError, match="no such artifact"):
        st.open("missing/file")
    if kind == "local":
        assert (tmp_path / "store" / "jobs").is_dir()


def test_settings_from_environment(monkeypatch, tmp_path):
    from pydantic import ValidationError

    from worker.settings import Settings

    monkeypatch.setenv("BRDF_DATA_DIR", str(tmp_path))
    monkeypatch.setenv("BRDF_REDIS_URL", "redis://example:6380/2")
    monkeypatch.setenv("BRDF_MAX_UPLOAD_BYTES", "1234")
    monkeypatch.setenv("BRDF_ARTIFACT_STORE", "s3://bucket/prefix")
    monkeypatch.setenv("BRDF_ARTIFACT_STORE_OPTIONS", '{"endpoint_url": "http://127.0.0.1:9000"}')
    s = Settings()
    assert s.redis_url == "redis://example:6380/2" and s.max_upload_bytes == 1234
    assert s.db_url == f"sqlite:///{tmp_path / 'brdf.db'}"
    assert s.store_url == "s3://bucket/prefix" and s.artifact_store_options["endpoint_url"].endswith(":9000")
    monkeypatch.setenv("BRDF_MAX_ATTEMPTS", "0")
    with pytest.raises(ValidationError, match="max_attempts"):
        Settings()


@pytest.mark.parametrize("header,size,expect", [
    (None, 100, None), ("bytes=0-9", 100, (0, 9)), ("bytes=90-", 100, (90, 99)), ("bytes=-10", 100, (90, 99)),
    ("bytes=-1000", 100, (0, 99)), ("bytes=95-200", 100, (95, 99)), ("bytes=0-1,5-6", 100, None),
    ("items=0-1", 100, None), ("bytes=-", 100, None),
])
def test_parse_range(header, size, expect):
    from services.ranges import parse_range

    assert parse_range(header, size) == expect


@pytest.mark.parametrize("header", ["bytes=100-", "bytes=5-2", "bytes=-0"])
def test_unsatisfiable_range(header):
    from services.ranges import parse_range

    with pytest.raises(HTTPException) as e:
        parse_range(header, 100)
    assert e.value.status_code == 416 and e.value.headers["Content-Range"] == "bytes */100"


def test_core_never_imports_server_packages():
    forbidden = {"fastapi", "redis", "rq", "api_schemas", "starlette", "uvicorn", "sqlalchemy", "worker"}
    hits = []
    for p in (REPO / "core").rglob("*.py"):
        for node in ast.walk(ast.parse(p.read_text(), str(p))):
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                names = [node.module]
            hits += [f"{p.relative_to(REPO)}:{node.lineno} imports {n}" for n in names
                     if n.split(".")[0] in forbidden]
    assert hits == [], hits

