"""Worker jobs against a real Redis, run in-process by an RQ SimpleWorker in burst mode: the real
render job (core.export: the captured frames of a Mitsuba-rendered scene), outputs, progress and stages, permanent
and transient failures with retries, stale attempts, cancel of a running job, and the reconcile
loop that re-enqueues from the database."""

from __future__ import annotations

import threading
import time
from datetime import timedelta

import numpy as np
import pytest
import redis
from sqlalchemy import select, update

from svc_support import make_bundle, zip_bundle
from worker.db import Job, utcnow
from worker_support import upload


def work(settings, queues=("render",)):
    from worker.main import run_worker

    assert run_worker(settings, list(queues), burst=True, fork=False) == 0


@pytest.fixture(scope="session")
def tiny_zip(tiny_scene, tmp_path_factory):
    return zip_bundle(tiny_scene, tmp_path_factory.mktemp("tinyzip") / "tiny.zip")


def test_render_job_end_to_end(client, settings, tiny_zip, tiny_scene):
    from core.io import read_exr

    sid = upload(client, tiny_zip)
    jid = client.post(f"/scenes/{sid}/render", json={"split": "all", "fps": 4}).json()["id"]
    t0 = time.time()
    work(settings)
    job = client.get(f"/jobs/{jid}").json()
    assert job["state"] == "done", job
    assert job["progress"] == 1.0 and job["error"] is None and job["eta_s"] is None
    assert [(s["name"], s["state"], s["progress"]) for s in job["stages"]] == [
        ("fetch", "done", 1.0), ("export", "done", 1.0), ("upload", "done", 1.0)]
    assert 0 <= job["timings"]["run_s"] <= time.time() - t0 + 1
    arts = {a["name"]: a for a in client.get(f"/jobs/{jid}/artifacts").json()["items"]}
    frames = sorted(p.stem for p in (tiny_scene / "images").iterdir())
    assert {f"frames/{f}.exr" for f in frames} <= set(arts), sorted(arts)
    assert {"preview.png", "train.mp4", "test.mp4"} <= set(arts)
    assert not any("gbuffers" in a for a in arts)  # no ground-truth G-buffers leave the service
    assert arts["preview.png"]["content_type"] == "image/png" and arts["train.mp4"]["content_type"] == "video/mp4"
    # the EXR served is the captured frame, linearised (the product path never reads ground truth)
    exr = client.get(arts[f"frames/{frames[0]}.exr"]["url"])
    assert exr.status_code == 200 and exr.headers["content-type"] == "image/x-exr"
    p = settings.data_dir / "check.exr"
    p.write_bytes(exr.content)
    layers = read_exr(p)
    assert set(layers) == {"rgb"} and layers["rgb"].shape[-1] == 3 and np.isfinite(layers["rgb"]).all()
    # HTTP Range on the video
    full = client.get(arts["train.mp4"]["url"]).content
    assert len(full) == arts["train.mp4"]["size_bytes"]
    r = client.get(arts["train.mp4"]["url"], headers={"Range": "bytes=100-199"})
    assert r.status_code == 206 and r.content == full[100:200]
    assert r.headers["content-range"] == f"bytes 100-199/{len(full)}"
    r = client.get(arts["train.mp4"]["url"], headers={"Range": "bytes=-16"})
    assert r.status_code == 206 and r.content == full[-16:]
    r = client.get(arts["train.mp4"]["url"], headers={"Range": f"bytes={len(full)}-"})
    assert r.status_code == 416 and r.headers["content-range"] == f"bytes */{len(full)}"
    h = client.head(arts["preview.png"]["url"])
    assert h.status_code == 200 and int(h.headers["content-length"]) == arts["preview.png"]["size_bytes"]
    assert h.headers["accept-ranges"] == "bytes" and h.content == b""
    # progress reached RQ's job meta too
    from rq.job import Job as RQJob
    from rq.serializers import JSONSerializer

    conn = redis.Redis.from_url(settings.redis_url)
    rj = RQJob.fetch(f"{jid}-a1", connection=conn, serializer=JSONSerializer)
    assert rj.get_status().value == "finished" and rj.return_value()["outcome"] == "done"
    assert rj.meta["progress"] == 1.0 and rj.meta["outcome"] == "done"
    assert rj.timeout == settings.render_job_timeout_s and rj.result_ttl == settings.result_ttl_s
    assert settings.result_ttl_s - 60 < conn.ttl(f"rq:job:{jid}-a1") <= settings.result_ttl_s


def test_outputs_select_artifacts_and_workdir_is_cleaned(client, settings, scene_zip):
    sid = upload(client, scene_zip)
    jid = client.post(f"/scenes/{sid}/render", json={"outputs": ["png"]}).json()["id"]
    work(settings)
    assert client.get(f"/jobs/{jid}").json()["state"] == "done"
    assert [a["name"] for a in client.get(f"/jobs/{jid}/artifacts").json()["items"]] == ["preview.png"]
    assert list((settings.data_dir / "work").iterdir()) == []


def test_bad_input_fails_once_without_retry(client, settings, tmp_path):
    z = zip_bundle(make_bundle(tmp_path / "b", frames=2, test_frames=0), tmp_path / "b.zip")
    sid = upload(client, z)
    jid = client.post(f"/scenes/{sid}/render", json={"split": "test"}).json()["id"]
    work(settings)
    job = client.get(f"/jobs/{jid}").json()
    assert job["state"] == "failed" and job["attempts"] == 1
    assert job["error"] == "ConfigError: split: the bundle has no 'test' frames"
    assert client.get(f"/jobs/{jid}/artifacts").json()["items"] == []
    assert client.get("/metrics").text.count('brdf_jobs{state="failed"} 1') == 1


def _lose_scene(app, sid):
    import shutil

    st = app.state.settings
    shutil.rmtree(st.data_dir / "cache" / "scenes" / sid)
    key = f"scenes/{sid}/bundle.zip"
    backup = st.data_dir / "backup.zip"
    app.state.store.get_file(key, backup)
    app.state.store.delete_prefix(f"scenes/{sid}")
    return key, backup


def test_transient_failure_is_retried_and_succeeds(client, app, settings, scene_zip):
    sid = upload(client, scene_zip)
    key, backup = _lose_scene(app, sid)
    jid = client.post(f"/scenes/{sid}/render", json={}).json()["id"]
    from worker.main import run_worker

    run_worker(settings, ["render"], burst=True, fork=False, max_jobs=1)
    job = client.get(f"/jobs/{jid}").json()
    assert job["state"] == "queued" and job["attempts"] == 2
    assert job["error"] == f"attempt 1 failed: StorageError: no such artifact: {key}"
    app.state.store.put_file(backup, key)  # the store is back
    work(settings)
    job = client.get(f"/jobs/{jid}").json()
    assert job["state"] == "done" and job["attempts"] == 2 and job["error"] is None
    assert any(a["name"] == "preview.png" for a in client.get(f"/jobs/{jid}/artifacts").json()["items"])


def test_transient_failure_exhausts_attempts(client, app, settings, scene_zip):
    sid = upload(client, scene_zip)
    key, _ = _lose_scene(app, sid)
    jid = client.post(f"/scenes/{sid}/render", json={}).json()["id"]
    work(settings)
    job = client.get(f"/jobs/{jid}").json()
    assert job["state"] == "failed" and job["attempts"] == settings.max_attempts == 3
    assert job["error"] == f"attempt 3 of 3 failed: StorageError: no such artifact: {key}"
    assert app.state.store.list(f"jobs/{jid}") == []


def test_stale_or_duplicate_attempt_does_nothing(client, settings, scene_zip):
    from worker.jobs import run_job
    from worker.settings import configure

    sid = upload(client, scene_zip)
    jid = client.post(f"/scenes/{sid}/render", json={}).json()["id"]
    configure(settings)
    try:
        assert "skipped" in run_job(jid, 2)
        assert client.get(f"/jobs/{jid}").json()["state"] == "queued"
        assert run_job(jid, 1)["outcome"] == "done"
        assert "skipped" in run_job(jid, 1)  # a duplicate delivery of the same attempt
    finally:
        configure(None)
    assert client.get(f"/jobs/{jid}").json()["state"] == "done"


def test_cancel_stops_a_running_job(client, app, settings, tmp_path):
    """A running job is interrupted within a heartbeat; the worker goes on to the next job."""
    from worker.queue import redis_conn, request_cancel

    z = zip_bundle(make_bundle(tmp_path / "b", frames=40, width=320, height=240, test_frames=5, with_gt=False),
                   tmp_path / "b.zip")
    sid = upload(client, z)
    long_job = client.post(f"/scenes/{sid}/render", json={}).json()["id"]
    next_job = client.post(f"/scenes/{sid}/render", json={"outputs": ["png"], "split": "test"}).json()["id"]
    seen = {}

    def cancel_when_running():
        deadline = time.time() + 60
        while time.time() < deadline:
            j = client.get(f"/jobs/{long_job}").json()
            if j["state"] == "running" and j["progress"] > 0.05:
                seen["progress"] = j["progress"]
                seen["t"] = time.time()
                request_cancel(app.state.db, redis_conn(settings.redis_url), long_job)
                return
            time.sleep(0.05)

    t = threading.Thread(target=cancel_when_running)
    t.start()
    work(settings)
    t.join()
    assert "progress" in seen, "the job never reported progress while running"
    j = client.get(f"/jobs/{long_job}").json()
    assert j["state"] == "canceled" and j["progress"] < 0.9, j
    assert client.get(f"/jobs/{long_job}/artifacts").json()["items"] == []
    assert app.state.store.list(f"jobs/{long_job}") == []
    assert client.get(f"/jobs/{next_job}").json()["state"] == "done"


def test_reconcile_requeues_jobs_lost_by_redis(client, app, settings, scene_zip):
    from worker.queue import reconcile, redis_conn

    sid = upload(client, scene_zip)
    jid = client.post(f"/scenes/{sid}/render", json={}).json()["id"]
    conn = redis_conn(settings.redis_url)
    conn.flushdb()  # Redis lost everything (restart without persistence)
    with app.state.db.session() as s:  # the submission is older than the grace period
        s.execute(update(Job).values(created_at=utcnow() - timedelta(seconds=30),
                                     enqueued_at=utcnow() - timedelta(seconds=30)))
    assert reconcile(settings, app.state.db, conn)["requeued"] == 1
    assert reconcile(settings, app.state.db, conn)["requeued"] == 0, "an enqueued job is not enqueued twice"
    work(settings)
    assert client.get(f"/jobs/{jid}").json()["state"] == "done"


def test_reconcile_retries_a_job_whose_worker_died(client, app, settings, scene_zip):
    from worker.queue import reconcile, redis_conn

    sid = upload(client, scene_zip)
    jid = client.post(f"/scenes/{sid}/render", json={}).json()["id"]
    conn = redis_conn(settings.redis_url)
    conn.delete("rq:queue:render")
    old = utcnow() - timedelta(seconds=settings.stale_after_s + 5)
    with app.state.db.session() as s:  # as if a worker claimed it and then vanished
        s.execute(update(Job).where(Job.id == jid).values(state="running", heartbeat_at=old, worker_name="w1"))
    done = reconcile(settings, app.state.db, conn)
    assert done["retried"] == 1
    j = client.get(f"/jobs/{jid}").json()
    assert j["state"] == "queued" and j["attempts"] == 2 and "worker w1 lost: no heartbeat" in j["error"]
    assert conn.lrange("rq:queue:render", 0, -1) == [f"{jid}-a2".encode()]
    # out of attempts: failed with the reason
    with app.state.db.session() as s:
        s.execute(update(Job).where(Job.id == jid).values(state="running", heartbeat_at=old, attempts=3))
    assert reconcile(settings, app.state.db, conn)["lost"] == 1
    j = client.get(f"/jobs/{jid}").json()
    assert j["state"] == "failed" and "(attempt 3 of 3)" in j["error"]


def test_service_on_postgresql(settings, scene_zip):
    """The same flow with the state in the machine's PostgreSQL (a fresh database of its own)."""
    from fastapi.testclient import TestClient

    from conftest_shared import OPERATOR_KEY
    from services.app import create_app
    from svc_support import postgres_database

    with postgres_database() as url:
        st = settings.model_copy(update={"database_url": url})
        with TestClient(create_app(st)) as c:
            c.headers["Authorization"] = f"Bearer {OPERATOR_KEY}"
            sid = upload(c, scene_zip)
            h = {"Idempotency-Key": "pg-1"}
            jid = c.post(f"/scenes/{sid}/render", json={"outputs": ["png", "mp4"]}, headers=h).json()["id"]
            assert c.post(f"/scenes/{sid}/render", json={"outputs": ["png", "mp4"]}, headers=h).json()["id"] == jid
            work(st)
            job = c.get(f"/jobs/{jid}").json()
            assert job["state"] == "done", job
            names = [a["name"] for a in c.get(f"/jobs/{jid}/artifacts").json()["items"]]
            assert "preview.png" in names and "train.mp4" in names and not any(n.endswith(".exr") for n in names)
            assert c.app.state.db.engine.dialect.name == "postgresql"


def test_reconstruct_stage_chain_end_to_end(client, app, settings, tiny_zip):
    """The reconstruct job is a chain of RQ jobs, one per stage, linked with ``depends_on``: the
    real volume stage (Gaussians fitted to the frames, held-out PSNR in summary.json, renders and
    the scene graph as artifacts, a loss curve) and then the PBR stage (the environment map fitted
    to the frames on the volume stage's scene graph). Night renders use the recovered sky."""
    import json as _json

    from rq.job import Job as RQJob
    from rq.serializers import JSONSerializer

    from worker.db import rq_job_id

    sid = upload(client, tiny_zip)
    r = client.post(f"/scenes/{sid}/reconstruct", json={"profile": "tiny", "stages": ["pbr", "volume"],
                                                          "iterations_scale": 0.5})
    assert r.status_code == 202, r.text
    jid = r.json()["id"]
    rconn = redis.Redis.from_url(settings.redis_url)
    vol_rq = RQJob.fetch(rq_job_id(jid, 1, "volume"), connection=rconn, serializer=JSONSerializer)
    pbr_rq = RQJob.fetch(rq_job_id(jid, 1, "pbr"), connection=rconn, serializer=JSONSerializer)
    assert vol_rq.get_status() == "queued" and pbr_rq.get_status() == "deferred"
    assert pbr_rq.dependency_ids == [vol_rq.id] and pbr_rq.args == [jid, 1, "pbr"]
    assert client.get(f"/jobs/{jid}").json()["stages"][0]["name"] == "volume"  # chain order, not request order
    work(settings, queues=("train",))
    job = client.get(f"/jobs/{jid}").json()
    assert job["state"] == "done", job
    assert [(st["name"], st["state"]) for st in job["stages"]] == [("volume", "done"), ("pbr", "done")]
    assert vol_rq.get_status(refresh=True) == "finished" and pbr_rq.get_status(refresh=True) == "finished"
    arts = {a["name"]: a for a in client.get(f"/jobs/{jid}/artifacts").json()["items"]}
    assert {"volume/summary.json", "volume/done.json", "volume/checkpoint/scene_graph.pt", "volume/test_renders.mp4",
            "pbr/envmap.exr", "pbr/envmap_prior.exr", "pbr/preview.png", "pbr/summary.json",
            "priors/priors.npz"} <= set(arts), sorted(arts)
    assert not any("/resume/" in n for n in arts)  # the resume state is not an output
    summary = _json.loads(client.get(arts["volume/summary.json"]["url"]).content)
    assert summary["iterations"] == 30 and 5 < summary["test_psnr"] < 60
    lighting = _json.loads(client.get(arts["pbr/summary.json"]["url"]).content)
    assert lighting["iterations"] == 15 and len(lighting["history"]) == 15
    env = __import__("core.io.envmap_file", fromlist=["read_envmap"]).read_envmap(
        _download(client, arts["pbr/envmap.exr"]["url"], settings.data_dir / "env.exr"))
    assert env.shape == (512, 1024, 3) and np.isfinite(env).all() and env.min() >= 0 and env.max() > 0
    from worker.db import JobStage

    with app.state.db.session() as s:
        st = {x.name: x for x in s.scalars(select(JobStage).where(JobStage.job_id == jid))}
        assert len(st["volume"].metrics["loss"]) == 30 and st["volume"].metrics["test_psnr"] == summary["test_psnr"]
        assert len(st["pbr"].metrics["loss"]) == 15
        assert st["pbr"].metrics["photometric_psnr_fitted"] == lighting["photometric_psnr_fitted"]
    # the resume state of a finished stage is cleaned up
    assert not (settings.data_dir / "runs" / jid / "volume" / "resume").exists()

    # relight and night now run on the reconstruction (the render queue)
    objects = [n.name for n in __import__("core.scene_graph", fromlist=["SceneGraph"]).SceneGraph.load(
        _download(client, arts["volume/checkpoint/scene_graph.pt"]["url"], settings.data_dir / "g.pt")).nodes]
    body = {"envmap_name": "sunset", "rotation_deg": 40, "exposure_ev": 0.5, "frames": {"split": "all", "stop": 3},
            "quality": {"rays_per_pixel": 8, "denoiser": "diffusion", "denoiser_fallback": "oidn"},
            "lights": [{"kind": "point", "position": [0, 0, 3], "intensity": 20}]}
    if objects:
        body["object_edits"] = [{"op": "move", "object_id": objects[0], "offset_m": [1.0, 0.0, 0.0]}]
    rel = client.post(f"/scenes/{sid}/relight", json=body)
    assert rel.status_code == 202, rel.text
    bad = client.post(f"/scenes/{sid}/relight", json={**body, "object_edits": [{"op": "remove", "object_id": "nope"}]})
    assert bad.status_code == 422 and "object_edits[0].object_id" in bad.json()["detail"], bad.text  # up front
    night = client.post(f"/scenes/{sid}/night", json={"frames": {"split": "test", "stop": 2}, "outputs": ["png"],
                                                      "quality": {"rays_per_pixel": 4, "denoiser": "none"}})
    # an object of a scene's reconstruction inserted as an asset (here from the same scene, by its id)
    cross = None
    if objects:
        ins = {"op": "insert", "object_id": "copied", "source_object_id": objects[0], "source_scene_id": sid,
               "offset_m": [12.0, -1.75, 0.75], "yaw_deg": 180}
        cross = client.post(f"/scenes/{sid}/relight", json={"envmap_name": "city", "frames": {"stop": 1},
                                                            "outputs": ["png"], "object_edits": [ins],
                                                            "quality": {"rays_per_pixel": 2, "denoiser": "none"}})
        assert cross.status_code == 202, cross.text
        nope = client.post(f"/scenes/{sid}/relight", json={"envmap_name": "city", "object_edits": [
            {**ins, "source_scene_id": "nosuchscene"}]})
        assert nope.status_code == 422 and "object_edits[0].source_scene_id" in nope.json()["detail"], nope.text
    work(settings, queues=("render",))
    job = client.get(f"/jobs/{rel.json()['id']}").json()
    assert job["state"] == "done", job
    assert [s_["name"] for s_ in job["stages"]] == ["fetch", "render", "upload"]
    arts = {a["name"]: a for a in client.get(f"/jobs/{rel.json()['id']}/artifacts").json()["items"]}
    assert {"relit.mp4", "preview.png"} <= set(arts) and sum(n.endswith(".exr") for n in arts) == 3, sorted(arts)
    render_stage = next(s_ for s_ in job["stages"] if s_["name"] == "render")
    with app.state.db.session() as s:
        m = s.scalars(select(JobStage).where(JobStage.job_id == rel.json()["id"], JobStage.name == "render")).one().metrics
    assert render_stage["state"] == "done" and m["frames"] == 3 and m["rays_per_pixel"] == 8
    # the committed diffusion model ran (models/forward_denoiser.onnx); no fallback was needed
    assert m["denoiser"] == "diffusion" and not m.get("denoiser_fallback_reason"), m
    exr = _download(client, arts[next(n for n in arts if n.endswith(".exr"))]["url"], settings.data_dir / "r.exr")
    layers = __import__("core.io", fromlist=["read_exr"]).read_exr(exr)
    assert {"rgb", "albedo", "normal", "depth"} <= set(layers) and np.isfinite(layers["rgb"]).all()
    if cross is not None:
        cj = client.get(f"/jobs/{cross.json()['id']}").json()
        assert cj["state"] == "done", cj
    nj = client.get(f"/jobs/{night.json()['id']}").json()
    assert nj["state"] == "done", nj
    with app.state.db.session() as s:  # the night sky is the one the pbr stage recovered
        m = s.scalars(select(JobStage).where(JobStage.job_id == night.json()["id"], JobStage.name == "fetch")).one()
        assert "recovered by the reconstruction's pbr stage" in m.metrics["sky"], m.metrics
        assert "street lights:" in m.metrics["sky"], m.metrics
        rm = s.scalars(select(JobStage).where(JobStage.job_id == night.json()["id"], JobStage.name == "render")).one()
        assert rm.metrics["exposure"] == "auto" and len(rm.metrics["street_lights"]) > 0, rm.metrics
    arts = {a["name"]: a for a in client.get(f"/jobs/{night.json()['id']}/artifacts").json()["items"]}
    assert set(arts) == {"preview.png", "street_lights.json"}
    lamps = _json.loads(client.get(arts["street_lights.json"]["url"]).content)["street_lights"]
    assert lamps == rm.metrics["street_lights"]


def _download(client, url, path):
    path.write_bytes(client.get(url).content)
    return path


def test_stage_metrics_never_hold_nan(caplog):
    """A stage summary's NaN (e.g. test PSNR of a bundle without test frames) is stored as null
    and logged by key: JSON has no NaN."""
    import json
    import logging

    from worker.runtime import finite_metrics

    with caplog.at_level(logging.WARNING, logger="brdf.jobs"):
        m = finite_metrics({"test_psnr": float("nan"), "train_psnr": 21.5, "gaussians": 10, "prior_source": "onnx",
                            "loss": [0.5, float("inf"), 0.25], "seconds": float("-inf")}, "job j stage volume")
    assert m == {"test_psnr": None, "train_psnr": 21.5, "gaussians": 10, "prior_source": "onnx", "loss": [0.5, 0.25],
                 "seconds": None}
    json.dumps(m, allow_nan=False)
    assert "metric 'test_psnr' is nan" in caplog.text and "curve 'loss' has 1 non-finite value(s)" in caplog.text
