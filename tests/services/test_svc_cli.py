"""The service commands: ``brdf keys``, ``brdf worker`` argument errors, and ``brdf up`` (a
gateway and a worker on one machine) rendering a scene end to end."""

from __future__ import annotations

import re
import subprocess
import sys
import time

import httpx
import pytest

from services.supervisor import descendants
from svc_support import REPO, http_ok, make_bundle, start_up, stop_up, svc_env, wait_for, zip_bundle


def run_cli(args, env):
    return subprocess.run([sys.executable, "-m", "services.cli", *args], env=env, cwd=REPO, capture_output=True, text=True,
                          timeout=120)


def test_keys_create_prints_a_working_key_once(settings):
    env = svc_env(settings)
    r = run_cli(["keys", "create", "--tenant", "acme", "--scope", "client", "--name", "ci"], env)
    assert r.returncode == 0, r.stderr
    key = r.stdout.strip().splitlines()[-1]
    assert key.startswith("brdf_") and "stored hashed" in r.stdout
    from services.auth import Authenticator
    from worker.db import get_database

    p = Authenticator(get_database(settings.db_url), 0, 60).from_key(key)
    assert p is not None and p.tenant == "acme" and p.scope == "client"
    r = run_cli(["keys", "create", "--tenant", "acme", "--scope", "root"], env)
    assert r.returncode == 2 and "invalid choice: 'root'" in r.stderr


def test_worker_rejects_unknown_queue(settings):
    r = run_cli(["worker", "--queues", "render,gpu", "--burst"], svc_env(settings))
    assert r.returncode == 2
    assert r.stderr.strip() == "error: --queues: unknown queue(s) ['gpu']; known: ['render', 'train']"


@pytest.mark.slow
def test_up_runs_gateway_and_worker(settings, tmp_path):
    env = svc_env(settings)
    env.pop("BRDF_BOOTSTRAP_OPERATOR_KEY", None)
    log = tmp_path / "up.log"
    p, base = start_up(env, log)
    try:
        key = wait_for(lambda: (re.findall(r"operator key \(shown once, stored hashed\): (\S+)",
                                           log.read_text()) or [None])[0], 60, "brdf up to print its operator key")
        wait_for(lambda: http_ok(base + "/readyz"), 60, f"the gateway to be ready\n{log.read_text()}")
        c = httpx.Client(base_url=base, headers={"Authorization": f"Bearer {key}"}, timeout=30)
        z = zip_bundle(make_bundle(tmp_path / "b"), tmp_path / "b.zip")
        sid = c.post("/scenes", content=z.read_bytes(), headers={"Content-Type": "application/zip"}).json()["id"]
        jid = c.post(f"/scenes/{sid}/render", json={}).json()["id"]
        j = wait_for(lambda: (lambda j: j if j["state"] in ("done", "failed") else None)(c.get(f"/jobs/{jid}").json()),
                     90, f"the job to finish\n{log.read_text()}")
        assert j["state"] == "done", j
        assert "dashboard: http://127.0.0.1:" in log.read_text()
        # the job's RQ work horse marks the job done just before it exits: give it a moment
        deadline = time.monotonic() + 15
        while len(children := descendants(p.pid)) > 1 and time.monotonic() < deadline:
            time.sleep(0.2)
        assert len(children) == 1, f"brdf up runs one worker process beside the gateway: {children}"
    finally:
        stop_up(p)
    assert p.returncode in (0, 130), log.read_text()[-2000:]
    time.sleep(0.5)
    alive = [pid for pid in children if _alive(pid)]
    assert alive == [], f"brdf up left processes behind: {alive}"


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as fh:
            return fh.read().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False
