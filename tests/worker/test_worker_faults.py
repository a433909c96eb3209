"""Fault tests with real processes: a gateway (``brdf serve``) and workers (``brdf worker``) run
as subprocesses with the docker compose file's commands, against a real Redis.

- kill -9 of a worker mid-job: the job is retried (new attempt) on another worker and finishes;
- Redis killed and restarted empty mid-queue: no accepted job is lost (the gateway re-enqueues
  from the database) and the worker reconnects;
- cancel of a running job in a forking worker.
"""

from __future__ import annotations

import time

import pytest

from svc_support import PrivateRedis, start_gateway, start_worker, wait_for, zip_bundle
from worker_support import api, job, upload

pytestmark = pytest.mark.slow


@pytest.fixture
def procs():
    started = []
    yield started
    for p in reversed(started):
        p.stop()


def test_worker_killed_mid_job_is_retried_and_finishes(settings, tmp_path, long_zip, procs):
    gw, base = start_gateway(settings, tmp_path / "gateway.log")
    procs.append(gw)
    w1 = start_worker(settings, tmp_path / "worker1.log")
    procs.append(w1)
    c = api(base)
    sid = upload(c, long_zip)
    jid = c.post(f"/scenes/{sid}/render", json={}).json()["id"]
    j = wait_for(lambda: (lambda j: j if j["state"] == "running" and j["progress"] >= 0.05 else None)(job(c, jid)),
                 90, "the job to run on worker 1")
    assert j["progress"] < 0.9, f"the job was nearly done before the kill: {j}"
    assert j["attempts"] == 1
    assert w1.descendants(), "the forking worker runs the job in a work horse"
    w1.kill9()
    time.sleep(1.0)
    assert job(c, jid)["state"] == "running", "the database still shows the dead worker's attempt"
    w2 = start_worker(settings, tmp_path / "worker2.log")
    procs.append(w2)
    done = wait_for(lambda: (lambda j: j if j["state"] in ("done", "failed") else None)(job(c, jid)), 120,
                    f"the retried job to finish\n--- gateway:\n{gw.tail()}\n--- worker2:\n{w2.tail()}")
    assert done["state"] == "done", done
    assert done["attempts"] == 2 and done["error"] is None and done["progress"] == 1.0
    names = {a["name"] for a in c.get(f"/jobs/{jid}/artifacts").json()["items"]}
    assert {"preview.png", "train.mp4", "test.mp4"} <= names and len([n for n in names if n.endswith(".exr")]) == 40
    assert "lost: no heartbeat" in gw.tail(200) or "lost: no heartbeat" in w2.tail(200)


def test_redis_restart_mid_queue_loses_no_job(settings, tmp_path, long_zip, scene_zip, procs):
    rd = PrivateRedis(tmp_path / "redis")
    rd.start()
    try:
        st = settings.model_copy(update={"redis_url": rd.url})
        gw, base = start_gateway(st, tmp_path / "gateway.log")
        procs.append(gw)
        w = start_worker(st, tmp_path / "worker.log")
        procs.append(w)
        c = api(base)
        long_sid, sid = upload(c, long_zip), upload(c, scene_zip)
        running = c.post(f"/scenes/{long_sid}/render", json={}).json()["id"]
        queued = [c.post(f"/scenes/{sid}/render", json={"split": "all", "fps": f}).json()["id"] for f in (5, 6, 7)]
        wait_for(lambda: job(c, running)["state"] == "running", 60, "the long job to start")
        assert all(job(c, q)["state"] == "queued" for q in queued)
        rd.kill()  # Redis dies with everything it held (no persistence)...
        time.sleep(1.0)
        during = c.post(f"/scenes/{sid}/render", json={"fps": 8})  # accepted while Redis is down
        assert during.status_code == 202, during.text
        rd.start()  # ...and comes back empty
        ids = [running, *queued, during.json()["id"]]
        final = wait_for(lambda: (lambda js: js if all(j["state"] in ("done", "failed", "canceled") for j in js)
                                  else None)([job(c, i) for i in ids]), 180,
                         f"every accepted job to finish\n--- gateway:\n{gw.tail()}\n--- worker:\n{w.tail()}")
        assert [j["state"] for j in final] == ["done"] * 5, [(j["id"], j["state"], j["error"]) for j in final]
        assert "(missing from Redis)" in gw.tail(400), gw.tail(400)
        # the worker is listed again (it re-registered in the new Redis)
        ws = wait_for(lambda: c.get("/system").json()["workers"], 30, "the worker to re-register")
        assert len(ws) == 1 and ws[0]["queues"] == ["render", "train"]
    finally:
        for p in reversed(procs):  # stop the services before their Redis goes away for good
            p.stop()
        rd.kill()


def test_cancel_running_job_in_forking_worker(settings, tmp_path, long_zip, scene_zip, procs):
    gw, base = start_gateway(settings, tmp_path / "gateway.log")
    procs.append(gw)
    procs.append(start_worker(settings, tmp_path / "worker.log"))
    c = api(base)
    long_sid, sid = upload(c, long_zip), upload(c, scene_zip)
    jid = c.post(f"/scenes/{long_sid}/render", json={}).json()["id"]
    nxt = c.post(f"/scenes/{sid}/render", json={"outputs": ["png"]}).json()["id"]
    wait_for(lambda: (lambda j: j["state"] == "running" and j["progress"] > 0.02)(job(c, jid)), 60, "the job to run")
    t0 = time.time()
    r = c.delete(f"/jobs/{jid}")
    assert r.status_code == 200 and r.json()["state"] == "canceled"
    wait_for(lambda: job(c, nxt)["state"] == "done", 60, "the next job to run after the cancel")
    took = time.time() - t0
    j = job(c, jid)
    assert j["state"] == "canceled" and j["progress"] < 1.0
    assert c.get(f"/jobs/{jid}/artifacts").json()["items"] == []
    assert took < 30, f"the canceled job kept the worker busy for {took:.0f} s"


def _reconstruct_on_one_worker(settings, tmp_path, tiny_scene, procs, stages, iterations_scale):
    """A gateway and one worker; the tiny scene uploaded and a reconstruct of ``stages`` queued:
    (API client, job id, the worker process)."""
    gw, base = start_gateway(settings, tmp_path / "gateway.log")
    procs.append(gw)
    w1 = start_worker(settings, tmp_path / "worker1.log")
    procs.append(w1)
    c = api(base)
    sid = upload(c, zip_bundle(tiny_scene, tmp_path / "tiny.zip"))
    jid = c.post(f"/scenes/{sid}/reconstruct", json={"profile": "tiny", "stages": list(stages),
                                                      "iterations_scale": iterations_scale}).json()["id"]
    return c, jid, w1


def test_killed_reconstruct_resumes_from_its_checkpoint(settings, tmp_path, tiny_scene, procs):
    """kill -9 of a worker in the middle of the volume stage: the retried attempt continues from
    the stage checkpoint instead of starting over, and finishes."""
    from pathlib import Path

    import torch

    c, jid, w1 = _reconstruct_on_one_worker(settings, tmp_path, tiny_scene, procs, ["volume"], 10)
    state = Path(settings.data_dir) / "runs" / jid / "volume" / "resume" / "train_state.pt"
    wait_for(lambda: state.is_file() or None, 180, f"a checkpoint of the volume stage\n{w1.tail()}")
    saved = torch.load(state, weights_only=True)["iteration"]
    assert job(c, jid)["state"] == "running"
    w1.kill9()
    w2 = start_worker(settings, tmp_path / "worker2.log")
    procs.append(w2)
    done = wait_for(lambda: (lambda j: j if j["state"] in ("done", "failed") else None)(job(c, jid)), 240,
                    f"the retried reconstruct to finish\n--- worker2:\n{w2.tail()}")
    assert done["state"] == "done", done
    assert done["attempts"] == 2
    arts = {a["name"]: a for a in c.get(f"/jobs/{jid}/artifacts").json()["items"]}
    summary = c.get(arts["volume/summary.json"]["url"]).json()
    assert summary["iterations"] == 600
    assert summary["resumed_from_iteration"] >= saved > 0, summary["resumed_from_iteration"]


def test_killed_chain_stage_is_retried_without_rerunning_finished_stages(settings, tmp_path, tiny_scene, procs):
    """kill -9 of a worker in the second stage of a reconstruct chain (pbr): the retried attempt
    starts at that stage (the finished volume stage and its artifacts are kept) and finishes."""
    from sqlalchemy import select

    from worker.db import Artifact, JobStage, get_database

    c, jid, w1 = _reconstruct_on_one_worker(settings, tmp_path, tiny_scene, procs, ["volume", "pbr"], 6)

    def in_pbr():
        j = job(c, jid)
        st = {s["name"]: s for s in j["stages"]}
        return j if j["state"] == "running" and j["stage"] == "pbr" and st["pbr"]["progress"] > 0.1 else None

    wait_for(in_pbr, 240, f"the pbr stage to be under way\n{w1.tail()}")
    db = get_database(settings.db_url)
    with db.session() as s:
        volume_done = s.scalar(select(JobStage.finished_at).where(JobStage.job_id == jid, JobStage.name == "volume"))
    assert volume_done is not None
    w1.kill9()
    w2 = start_worker(settings, tmp_path / "worker2.log")
    procs.append(w2)
    done = wait_for(lambda: (lambda j: j if j["state"] in ("done", "failed") else None)(job(c, jid)), 240,
                    f"the retried chain to finish\n--- worker2:\n{w2.tail()}")
    assert done["state"] == "done" and done["attempts"] == 2, done
    with db.session() as s:
        keys = dict(s.execute(select(Artifact.name, Artifact.storage_key).where(Artifact.job_id == jid)).all())
        assert s.scalar(select(JobStage.finished_at).where(JobStage.job_id == jid, JobStage.name == "volume")) \
            == volume_done  # not run again
    assert f"jobs/{jid}/volume.a1/" in keys["volume/checkpoint/scene_graph.pt"]
    assert f"jobs/{jid}/pbr.a2/" in keys["pbr/envmap.exr"]
    assert "volume.a2" not in " ".join(keys.values())
    names = {a["name"] for a in c.get(f"/jobs/{jid}/artifacts").json()["items"]}
    assert {"volume/checkpoint/scene_graph.pt", "pbr/envmap.exr", "pbr/preview.png"} <= names
