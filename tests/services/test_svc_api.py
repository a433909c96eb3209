"""The gateway in-process (FastAPI TestClient) against a real Redis: uploads and their
rejections, auth and tenant isolation, job submission, idempotency, cancel, the job types not
in this build (409),
envmaps, metrics and health."""

from __future__ import annotations

import io
import json
import stat
import struct
import zipfile
from pathlib import Path

import numpy as np
import pytest
import redis
from sqlalchemy import func, select

from conftest_shared import OPERATOR_KEY
from svc_support import make_bundle
from worker.db import Envmap, Job, Scene

ZIP = {"Content-Type": "application/zip"}


def upload(client, data: bytes, **headers):
    return client.post("/scenes", content=data, headers={**ZIP, **headers})


def assert_nothing_written(app):
    s = app.state.settings
    up = s.data_dir / "uploads"
    assert not up.exists() or list(up.iterdir()) == [], list(up.iterdir())
    with app.state.db.session() as ss:
        assert ss.scalar(select(func.count()).select_from(Scene)) == 0
        assert ss.scalar(select(func.count()).select_from(Envmap)) == 0
    assert app.state.store.list("scenes") == [] and app.state.store.list("envmaps") == []
    cache = s.data_dir / "cache" / "scenes"
    assert not cache.exists() or list(cache.iterdir()) == []


def bundle_members(scene_zip: Path) -> dict[str, bytes]:
    with zipfile.ZipFile(scene_zip) as z:
        return {n: z.read(n) for n in z.namelist()}


def make_zip(members: dict[str, bytes], symlinks: dict[str, str] | None = None) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as z:
        for n, b in members.items():
            z.writestr(n, b)
        for n, target in (symlinks or {}).items():
            info = zipfile.ZipInfo(n)
            info.external_attr = (stat.S_IFLNK | 0o777) << 16
            z.writestr(info, target)
    return buf.getvalue()


# --- health, auth ------------------------------------------------------------------------------

def test_health_ready_and_openapi(client):
    assert client.get("/healthz").json()["status"] == "ok"
    r = client.get("/readyz")
    assert r.status_code == 200 and r.json() == {"ready": True, "checks": {
        "database": "ok", "redis": "ok", "artifact_store": "ok", "workers": "ok"}}
    doc = client.get("/openapi.json").json()
    for path in ("/scenes", "/scenes/{scene_id}/relight", "/scenes/{scene_id}/night", "/envmaps", "/jobs/{job_id}",
                 "/jobs/{job_id}/artifacts/{name}", "/metrics"):
        assert path in doc["paths"], path
    assert doc["components"]["schemas"]["RelightRequest"]["examples"][0]["lights"][0]["kind"] == "spot"


def test_readyz_names_a_dead_redis(settings):
    from fastapi.testclient import TestClient

    from services.app import create_app
    from svc_support import free_port

    app = create_app(settings.model_copy(update={"redis_url": f"redis://127.0.0.1:{free_port()}/0"}))
    with TestClient(app) as c:
        r = c.get("/readyz")
    assert r.status_code == 503 and r.json()["checks"]["redis"].startswith("ConnectionError")
    assert r.json()["checks"]["database"] == "ok"


def test_auth_required_and_bad_keys_rejected(client):
    for h in ({}, {"Authorization": "Bearer nope"}, {"X-API-Key": "brdf_wrong"}):
        r = client.get("/scenes", headers={"Authorization": ""} | h)
        assert r.status_code == 401, h
        assert "API key" in r.json()["detail"]
    assert client.get("/scenes", headers={"Authorization": "", "X-API-Key": OPERATOR_KEY}).status_code == 200


def test_tenant_isolation_is_404(client, keys, scene_zip):
    acme = {"Authorization": f"Bearer {keys['acme']}"}
    globex = {"Authorization": f"Bearer {keys['globex']}"}
    r = upload(client, scene_zip.read_bytes(), **acme)
    assert r.status_code == 201, r.text
    sid = r.json()["id"]
    job = client.post(f"/scenes/{sid}/render", json={}, headers=acme).json()["id"]
    for path in (f"/scenes/{sid}", f"/jobs/{job}", f"/jobs/{job}/artifacts", f"/jobs/{job}/artifacts/preview.png"):
        r = client.get(path, headers=globex)
        assert r.status_code == 404 and "not found" in r.json()["detail"], path
        assert client.get(path, headers=acme).status_code in (200, 404 if "preview" in path else 200)
    assert client.post(f"/scenes/{sid}/render", json={}, headers=globex).status_code == 404
    assert client.delete(f"/jobs/{job}", headers=globex).status_code == 404
    assert client.get("/scenes", headers=globex).json()["total"] == 0
    assert client.get("/jobs", headers=globex).json()["total"] == 0
    assert client.get("/scenes", headers=acme).json()["total"] == 1
    assert client.get("/scenes").json()["total"] == 1  # the operator sees every tenant
    # client keys cannot use operator endpoints (and do not learn they exist)
    assert client.post("/keys", json={"tenant": "x"}, headers=acme).status_code == 404
    assert client.get("/system", headers=acme).status_code == 404


def test_operator_creates_keys_stored_hashed(client, app):
    r = client.post("/keys", json={"tenant": "initech", "scope": "client", "name": "ci"})
    assert r.status_code == 201
    key = r.json()["key"]
    assert client.get("/scenes", headers={"Authorization": f"Bearer {key}"}).status_code == 200
    from services.db import ApiKey

    with app.state.db.session() as s:
        stored = [k.key_hash for k in s.scalars(select(ApiKey)).all()]
    assert key not in stored and all(len(h) == 64 for h in stored)


# --- scene uploads ------------------------------------------------------------------------------

def test_upload_list_and_read_scene(client, scene_zip, app):
    r = upload(client, scene_zip.read_bytes())
    assert r.status_code == 201, r.text
    body = r.json()
    assert r.headers["location"] == f"/scenes/{body['id']}"
    assert body["frames"] == 3 and body["train_frames"] == 2 and body["test_frames"] == 1
    assert body["cameras"] == ["front"] and body["has_ground_truth"] is True
    assert client.get(f"/scenes/{body['id']}").json() == body
    lst = client.get("/scenes").json()
    assert lst["total"] == 1 and lst["items"][0]["id"] == body["id"]
    assert app.state.store.list(f"scenes/{body['id']}") == [f"scenes/{body['id']}/bundle.zip"]
    assert list((app.state.settings.data_dir / "uploads").iterdir()) == []


def test_upload_tar_gz(client, tmp_path):
    from core.bundle import pack_bundle

    tgz = pack_bundle(make_bundle(tmp_path / "b", frames=2), tmp_path / "s.tar.gz")
    r = client.post("/scenes?name=tarred", content=tgz.read_bytes(), headers={"Content-Type": "application/gzip"})
    assert r.status_code == 201, r.text
    assert r.json()["name"] == "tarred" and r.json()["frames"] == 2


def test_scene_upload_idempotency(client, scene_zip):
    a = upload(client, scene_zip.read_bytes(), **{"Idempotency-Key": "up-1"})
    b = upload(client, scene_zip.read_bytes(), **{"Idempotency-Key": "up-1"})
    assert a.status_code == 201 and b.status_code == 200 and a.json()["id"] == b.json()["id"]
    assert client.get("/scenes").json()["total"] == 1


@pytest.fixture
def small_limits_app(settings):
    from fastapi.testclient import TestClient

    from services.app import create_app

    app = create_app(settings.model_copy(update={"max_upload_bytes": 60_000, "archive_max_entries": 40,
                                                 "max_request_json_bytes": 2000}))
    with TestClient(app) as c:
        c.headers["Authorization"] = f"Bearer {OPERATOR_KEY}"
        yield app, c


def test_oversize_upload_413_nothing_written(small_limits_app):
    app, c = small_limits_app
    r = upload(c, b"\0" * 70_000)
    assert r.status_code == 413 and "upload limit of 60000 bytes" in r.json()["detail"]

    def chunks():  # no Content-Length: the cap is enforced while streaming
        for _ in range(10):
            yield b"PK\x03\x04" + b"\0" * 9996

    r = c.post("/scenes", content=chunks(), headers=ZIP)
    assert r.status_code == 413 and "exceeds the upload limit" in r.json()["detail"]
    assert_nothing_written(app)


def test_too_many_entries_and_json_body_limit(small_limits_app):
    app, c = small_limits_app
    r = upload(c, make_zip({f"f{i}.txt": b"x" for i in range(50)}))
    assert r.status_code == 422 and "50 entries, more than the limit 40" in r.json()["detail"]
    r = c.post("/scenes/abc/render", content=b'{"split": "all"' + b" " * 3000 + b"}",
               headers={"Content-Type": "application/json"})
    assert r.status_code == 413 and "exceeds the limit of 2000 bytes" in r.json()["detail"]
    assert_nothing_written(app)


@pytest.mark.parametrize("case", ["zip_slip", "absolute", "symlink", "zip_bomb", "not_archive", "corrupt_zip",
                                  "invalid_bundle", "bad_pose", "missing_manifest", "bad_json_manifest"])
def test_bad_scene_uploads_are_4xx_with_nothing_written(client, app, scene_zip, case):
    m = bundle_members(scene_zip)
    if case == "zip_slip":
        data, needle = make_zip({**m, "../../evil.txt": b"x"}), "unsafe path in archive"
    elif case == "absolute":
        data, needle = make_zip({**m, "/etc/evil": b"x"}), "unsafe path in archive"
    elif case == "symlink":
        data, needle = make_zip(m, symlinks={"images/link.png": "/etc/passwd"}), "symlinks are not allowed"
    elif case == "zip_bomb":
        data, needle = make_zip({**m, "ground_truth/zeros.bin": b"\0" * (80 * 1024 ** 2)}), "zip bomb"
    elif case == "not_archive":
        data, needle = b"hello, this is not an archive" * 10, "not a .zip or .tar.gz"
    elif case == "corrupt_zip":
        good = scene_zip.read_bytes()
        data, needle = good[: len(good) // 2], "corrupt"
    elif case == "invalid_bundle":
        manifest = json.loads(m["bundle.json"])
        del m[manifest["frames"][0]["image"]], m[manifest["frames"][1]["image"]]
        data, needle = make_zip(m), "scene bundle is invalid (2 problem(s))"
    elif case == "bad_pose":
        manifest = json.loads(m["bundle.json"])
        manifest["frames"][0]["cam_to_world"][0][0] = 5.0
        data, needle = make_zip({**m, "bundle.json": json.dumps(manifest).encode()}), "cam_to_world"
    elif case == "missing_manifest":
        data, needle = make_zip({k: v for k, v in m.items() if k != "bundle.json"}), "bundle.json"
    else:
        data, needle = make_zip({**m, "bundle.json": b"{not json"}), "bundle"
    r = upload(client, data)
    assert r.status_code == 422, (r.status_code, r.text)
    assert needle in r.json()["detail"], r.json()
    assert "/svc/uploads/" not in r.text, "server paths leak into the error"
    if case == "invalid_bundle":
        errs = r.json()["errors"]
        assert len(errs) == 2 and all("images/f00" in e for e in errs), errs
    assert_nothing_written(app)


def test_upload_content_type_and_empty_body(client, app, scene_zip):
    r = client.post("/scenes", content=scene_zip.read_bytes(), headers={"Content-Type": "text/plain"})
    assert r.status_code == 415 and "application/zip" in r.json()["detail"]
    r = upload(client, b"")
    assert r.status_code == 400 and "empty body" in r.json()["detail"]
    assert_nothing_written(app)


# --- jobs --------------------------------------------------------------------------------------

@pytest.fixture
def scene_id(client, scene_zip) -> str:
    r = upload(client, scene_zip.read_bytes())
    assert r.status_code == 201, r.text
    return r.json()["id"]


def rq_payload(settings, job_id: str, attempt: int = 1) -> bytes:
    """The stored call of an RQ job (RQ zlib-compresses it); JSON, never a pickle."""
    import zlib

    raw = redis.Redis.from_url(settings.redis_url).hget(f"rq:job:{job_id}-a{attempt}", "data")
    return zlib.decompress(raw)


def test_render_submission_is_queued_as_json(client, scene_id, settings):
    r = client.post(f"/scenes/{scene_id}/render", json={"split": "test", "fps": 5})
    assert r.status_code == 202 and r.json()["state"] == "queued"
    jid = r.json()["id"]
    assert r.headers["location"] == f"/jobs/{jid}" == r.json()["status_url"]
    job = client.get(f"/jobs/{jid}").json()
    assert job["type"] == "render" and job["params"]["split"] == "test" and job["attempts"] == 1
    assert [s["name"] for s in job["stages"]] == ["fetch", "export", "upload"]
    payload = rq_payload(settings, jid)
    assert json.loads(payload) == ["worker.jobs.run_job", None, [jid, 1], {}], payload[:200]
    r = redis.Redis.from_url(settings.redis_url)
    assert r.lrange("rq:queue:render", 0, -1) == [f"{jid}-a1".encode()]
    assert r.llen("rq:queue:train") == 0
    assert int(r.hget(f"rq:job:{jid}-a1", "timeout")) == settings.render_job_timeout_s
    assert client.get("/jobs?state=queued").json()["total"] == 1
    assert client.get(f"/jobs?scene_id={scene_id}").json()["items"][0]["id"] == jid


def test_idempotency_key_creates_one_job(client, scene_id, settings, app):
    h = {"Idempotency-Key": "abc-123"}
    a = client.post(f"/scenes/{scene_id}/render", json={"split": "all"}, headers=h)
    b = client.post(f"/scenes/{scene_id}/render", json={"split": "all"}, headers=h)
    assert a.status_code == b.status_code == 202 and a.json()["id"] == b.json()["id"]
    assert b.headers.get("idempotent-replayed") == "true"
    with app.state.db.session() as s:
        assert s.scalar(select(func.count()).select_from(Job)) == 1
    assert redis.Redis.from_url(settings.redis_url).llen("rq:queue:render") == 1
    c = client.post(f"/scenes/{scene_id}/render", json={"split": "test"}, headers=h)
    assert c.status_code == 409 and "different request" in c.json()["detail"]


def test_idempotency_under_concurrency(client, scene_id, app):
    from concurrent.futures import ThreadPoolExecutor

    def go(_):
        return client.post(f"/scenes/{scene_id}/render", json={}, headers={"Idempotency-Key": "race"})

    with ThreadPoolExecutor(8) as ex:
        rs = list(ex.map(go, range(8)))
    assert {r.status_code for r in rs} == {202} and len({r.json()["id"] for r in rs}) == 1
    with app.state.db.session() as s:
        assert s.scalar(select(func.count()).select_from(Job)) == 1


def test_cancel_queued_job(client, scene_id, settings):
    jid = client.post(f"/scenes/{scene_id}/render", json={}).json()["id"]
    r = client.delete(f"/jobs/{jid}")
    assert r.status_code == 200 and r.json()["state"] == "canceled" and r.json()["error"] == "canceled by request"
    assert redis.Redis.from_url(settings.redis_url).llen("rq:queue:render") == 0
    assert client.delete(f"/jobs/{jid}").json()["state"] == "canceled"


@pytest.mark.parametrize("path,body", [
    ("relight", {"envmap_name": "city", "rotation_deg": 30, "lights": [
        {"kind": "point", "position": [1, 2, 3], "intensity": 50}]}),  # no reconstruction yet
    ("night", {"street_lights": True, "headlights": False}),  # no reconstruction yet
    ("reconstruct", {"profile": "quick", "stages": ["volume", "joint"]}),  # joint needs pbr in its chain
    ("reconstruct", {"profile": "quick", "stages": ["pbr"]}),  # pbr needs the volume stage in its chain
    ("reconstruct", {"profile": "quick", "stages": ["volume2"]}),  # volume2 needs volume + generative_refine
])
def test_unbuilt_job_types_answer_409_and_queue_nothing(client, scene_id, app, settings, path, body):
    r = client.post(f"/scenes/{scene_id}/{path}", json=body)
    assert r.status_code == 409, r.text
    why = "no finished reconstruction" if path in ("relight", "night") else "of the same chain"
    assert why in r.json()["detail"] and "no job was queued" in r.json()["detail"]
    with app.state.db.session() as s:
        assert s.scalar(select(func.count()).select_from(Job)) == 0
    rr = redis.Redis.from_url(settings.redis_url)
    assert rr.llen("rq:queue:render") == 0 and rr.llen("rq:queue:train") == 0


def test_bad_job_requests(client, scene_id):
    r = client.post(f"/scenes/{scene_id}/relight", json={"envmap_name": "city", "lights": [
        {"kind": "spot", "position": [0, 0, 1], "direction": [1, 0, 0], "intensity": -5}]})
    assert r.status_code == 422 and "body.lights.0.intensity" in r.json()["detail"]
    r = client.post(f"/scenes/{scene_id}/relight", content=b'{"envmap_name": "city",',
                    headers={"Content-Type": "application/json"})
    assert r.status_code == 422 and "malformed JSON" in r.json()["detail"]
    r = client.post(f"/scenes/{scene_id}/render", json={"split": "sideways"})
    assert r.status_code == 422 and "body.split" in r.json()["detail"]
    r = client.post("/scenes/doesnotexist/render", json={})
    assert r.status_code == 404 and "scene 'doesnotexist' not found" in r.json()["detail"]
    r = client.post("/scenes/doesnotexist/relight", json={"envmap_name": "city"})
    assert r.status_code == 404
    r = client.post(f"/scenes/{scene_id}/relight", json={"envmap_id": "nosuchmap"})
    assert r.status_code == 404 and "envmap 'nosuchmap' not found" in r.json()["detail"]
    for p in ("/jobs/nosuchjob", "/jobs/nosuchjob/artifacts", "/jobs/nosuchjob/artifacts/a.png", "/scenes/nosuch"):
        assert client.get(p).status_code == 404, p
    assert client.delete("/jobs/nosuchjob").status_code == 404


# --- envmaps -----------------------------------------------------------------------------------

def _exr_bytes(tmp_path, rgb) -> bytes:
    """An RGB EXR written with OpenEXR directly (core's writer refuses NaN/Inf, as it should)."""
    import OpenEXR

    p = tmp_path / "m.exr"
    rgb = np.ascontiguousarray(rgb, np.float32)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    OpenEXR.File(header, {"R": rgb[..., 0].copy(), "G": rgb[..., 1].copy(), "B": rgb[..., 2].copy()}).write(str(p))
    return p.read_bytes()


def _huge_header(exr: bytes) -> bytes:
    i = exr.index(b"dataWindow\0box2i\0") + len(b"dataWindow\0box2i\0") + 4
    return exr[:i] + struct.pack("<iiii", 0, 0, 199_999, 99_999) + exr[i + 16:]


def test_envmap_uploads(client, app, tmp_path):
    from core.io import write_hdr

    good = np.full((8, 16, 3), 0.5, np.float32)
    r = client.post("/envmaps?name=grey", content=_exr_bytes(tmp_path, good), headers={"Content-Type": "image/x-exr"})
    assert r.status_code == 201, r.text
    assert r.json()["width"] == 16 and r.json()["height"] == 8 and r.json()["format"] == "exr"
    write_hdr(tmp_path / "m.hdr", good)
    r2 = client.post("/envmaps?name=grey-hdr", content=(tmp_path / "m.hdr").read_bytes(),
                     headers={"Content-Type": "image/vnd.radiance"})
    assert r2.status_code == 201 and r2.json()["format"] == "hdr"
    assert {e["id"] for e in client.get("/envmaps").json()["items"]} == {r.json()["id"], r2.json()["id"]}
    assert client.get(f"/envmaps/{r.json()['id']}").json()["name"] == "grey"


@pytest.mark.parametrize("case", ["nan", "inf", "not_2to1", "huge_header", "garbage", "truncated"])
def test_bad_envmaps_are_4xx_with_nothing_written(client, app, tmp_path, case):
    good = np.full((8, 16, 3), 0.5, np.float32)
    if case == "nan":
        bad = good.copy()
        bad[2, 3, 1] = np.nan
        data, code, needle = _exr_bytes(tmp_path, bad), 422, "NaN"
    elif case == "inf":
        bad = good.copy()
        bad[0, 0, 0] = np.inf
        data, code, needle = _exr_bytes(tmp_path, bad), 422, "Inf"
    elif case == "not_2to1":
        data, code, needle = _exr_bytes(tmp_path, np.ones((8, 8, 3))), 422, "W == 2 H"
    elif case == "huge_header":
        data, code, needle = _huge_header(_exr_bytes(tmp_path, good)), 422, "exceeds max_pixels"
    elif case == "garbage":
        data, code, needle = b"GIF89a....", 415, "not an OpenEXR or Radiance"
    else:
        data, code, needle = _exr_bytes(tmp_path, good)[:120], 422, "environment map rejected"
    r = client.post("/envmaps", content=data, headers={"Content-Type": "image/x-exr"})
    assert r.status_code == code, r.text
    assert needle in r.json()["detail"], r.json()
    assert "/svc/uploads/" not in r.text
    assert_nothing_written(app)


# --- metrics ------------------------------------------------------------------------------------

def test_metrics_prometheus_text(client, scene_id):
    client.post(f"/scenes/{scene_id}/render", json={})
    client.get("/jobs/nosuch")
    text = client.get("/metrics").text
    lines = [ln for ln in text.splitlines() if ln and not ln.startswith("#")]
    samples = {}
    for ln in lines:
        name_labels, value = ln.rsplit(" ", 1)
        samples[name_labels] = float(value)
    assert samples['brdf_http_requests_total{method="GET",route="/jobs/{job_id}",status="404"}'] == 1
    assert samples['brdf_http_requests_total{method="POST",route="/scenes",status="201"}'] == 1
    assert samples['brdf_jobs{state="queued"}'] == 1 and samples["brdf_scenes"] == 1
    assert samples['brdf_queue_depth{queue="render"}'] == 1 and samples["brdf_redis_up"] == 1
    assert "# TYPE brdf_http_request_duration_seconds histogram" in text
    assert samples['brdf_http_request_duration_seconds_count{method="POST",route="/scenes/{scene_id}/render"}'] == 1


def test_system_status_for_operators(client):
    r = client.get("/system").json()
    assert r["redis"] == "ok" and [q["name"] for q in r["queues"]] == ["render", "train"]


def test_job_out_is_valid(client, scene_id):
    """The job routes build their answers without re-validation: check they validate."""
    import api_schemas as S

    jid = client.post(f"/scenes/{scene_id}/render", json={}).json()["id"]
    S.JobOut.model_validate(client.get(f"/jobs/{jid}").json())
    listing = S.JobList.model_validate(client.get("/jobs").json())
    assert listing.items[0].id == jid and listing.items[0].timings.created_at.tzinfo is not None
