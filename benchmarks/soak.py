"""Soak test of the service on one machine, loopback only, bounded in time.

``brdf up`` (a gateway and supervised workers) runs against a private Redis (no persistence, on a
free port: the machine's Redis is never touched) and SQLite in a temporary directory. For
``--duration`` seconds a client mixes scene uploads, reconstructs (tiny profile), relights of the
finished reconstructions, cancels and status polling; every ``--kill-every`` seconds a worker is
killed with kill -9 (with its work horse, as when its container dies), and Redis is killed and
restarted empty once (at ``--redis-restart-at``). Then submissions stop and every accepted job is
given ``--drain`` seconds to reach a final state.

Reported (JSON, ``--out``): jobs accepted, done, failed, canceled, lost (accepted but unknown to
the API) and stuck (not final after the drain); the status-route latency (p50, p99, max) and
errors; per kill, the time from the kill to the retry of each job the worker was running (its
next attempt running); worker restarts; Redis downtime and what the gateway re-enqueued.

    python benchmarks/soak.py                          # 10 minutes, a kill every 60 s
    python benchmarks/soak.py --duration 120 --out /tmp/soak.json   # a short trial
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import random
import re
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import httpx

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
from services.supervisor import children  # noqa: E402
from services.testing import PrivateRedis, free_port  # noqa: E402

KEY = "brdf_soak-operator-key-0123456789abcdefghijklmnopqrstu"
FINAL = ("done", "failed", "canceled")


def pct(xs: list[float], q: float) -> float | None:
    if not xs:
        return None
    xs = sorted(xs)
    return xs[min(len(xs) - 1, max(0, int(round(q / 100 * len(xs) + 0.5)) - 1))]


def cmdline(pid: int) -> list[str]:
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as fh:
            return [x.decode() for x in fh.read().split(b"\0") if x]
    except OSError:
        return []


class Soak:
    def __init__(self, a: argparse.Namespace):
        self.a = a
        self.rng = random.Random(a.seed)
        self.tmp = Path(tempfile.mkdtemp(prefix="brdf-soak-"))
        self.redis = PrivateRedis(self.tmp / "redis")
        self.port = free_port()
        self.base = f"http://127.0.0.1:{self.port}"
        self.lock = threading.Lock()
        self.jobs: dict[str, dict] = {}  # id -> {"type", "submitted"}
        self.scenes: list[str] = []
        self.reconstructed: set[str] = set()
        self.latency: list[float] = []
        self.status_errors: list[str] = []
        self.submit_errors: list[str] = []
        self.kills: list[dict] = []
        self.cancels = 0
        self.stop = threading.Event()
        self.events: list[dict] = []

    # -- the system under test ---------------------------------------------------------------
    def start(self) -> None:
        self.redis.start()
        env = {k: v for k, v in os.environ.items() if not k.startswith("BRDF_")}
        env.update({"BRDF_DATA_DIR": str(self.tmp / "data"), "BRDF_REDIS_URL": f"redis://127.0.0.1:{self.redis.port}/0",
                    "BRDF_BOOTSTRAP_OPERATOR_KEY": KEY, "PYTHONUNBUFFERED": "1"})
        self.log = self.tmp / "up.log"
        self.up = subprocess.Popen([sys.executable, "-m", "services.cli", "up", "--port", str(self.port),
                                    "--workers", str(self.a.workers)], env=env, cwd=REPO,
                                   stdout=open(self.log, "wb"), stderr=subprocess.STDOUT, start_new_session=True)
        self.c = httpx.Client(base_url=self.base, headers={"Authorization": f"Bearer {KEY}"}, timeout=30)
        deadline = time.time() + 60
        while time.time() < deadline:
            try:
                if self.c.get("/healthz").status_code == 200:
                    return
            except httpx.HTTPError:
                time.sleep(0.2)
        raise RuntimeError(f"brdf up did not start:\n{self.log.read_text()[-3000:]}")

    def shutdown(self) -> None:
        if getattr(self, "up", None) is not None and self.up.poll() is None:
            self.up.send_signal(signal.SIGINT)
            try:
                self.up.wait(60)
            except subprocess.TimeoutExpired:
                os.killpg(self.up.pid, signal.SIGKILL)
        self.redis.kill()

    def workers(self) -> dict[int, str]:
        """pid -> supervisor slot name of each worker process of brdf up."""
        out = {}
        for pid in children(self.up.pid):
            cmd = cmdline(pid)
            if "worker" in cmd and "--name" in cmd:
                out[pid] = cmd[cmd.index("--name") + 1]
        return out

    # -- the client ----------------------------------------------------------------------------
    def accepted(self, r: httpx.Response, kind: str) -> str | None:
        if r.status_code == 202:
            jid = r.json()["id"]
            with self.lock:
                self.jobs[jid] = {"type": kind, "submitted": time.time()}
            return jid
        self.submit_errors.append(f"{kind}: {r.status_code} {r.text[:200]}")
        return None

    def upload(self) -> None:
        r = self.c.post("/scenes", content=self.scene_zip, headers={"Content-Type": "application/zip"},
                        params={"name": f"soak-{len(self.scenes)}"})
        if r.status_code == 201:
            self.scenes.append(r.json()["id"])
        else:
            self.submit_errors.append(f"upload: {r.status_code} {r.text[:200]}")

    def reconstruct(self) -> None:
        sid = self.rng.choice(self.scenes)
        r = self.c.post(f"/scenes/{sid}/reconstruct", json={"profile": "tiny"})
        jid = self.accepted(r, "reconstruct")
        if jid:
            self.jobs[jid]["scene"] = sid

    def relight(self) -> None:
        ready = sorted(self.reconstructed)
        if not ready:
            return
        sid = self.rng.choice(ready)
        body = {"envmap_name": self.rng.choice(["sunset", "city", "forest"]), "rotation_deg": self.rng.uniform(0, 360),
                "frames": {"split": "test"}, "outputs": ["mp4", "png"],
                "quality": {"rays_per_pixel": 4, "denoiser": "none"}}
        self.accepted(self.c.post(f"/scenes/{sid}/relight", json=body), "relight")

    def cancel(self) -> None:
        """Cancel a live relight; every third cancel a live reconstruct instead."""
        self.n_cancel = getattr(self, "n_cancel", 0) + 1
        kind = "reconstruct" if self.n_cancel % 3 == 0 else "relight"
        with self.lock:
            live = [j for j, m in self.jobs.items() if m.get("state") not in FINAL and m["type"] == kind]
        if live:
            jid = self.rng.choice(live)
            r = self.c.delete(f"/jobs/{jid}")
            if r.status_code == 200:
                self.cancels += 1
                with self.lock:
                    self.jobs[jid]["cancel_requested"] = True

    def poll(self) -> None:
        """Status polling: GET /jobs/<id> of random accepted jobs and listings (~10 requests/s)."""
        cl = httpx.Client(base_url=self.base, headers={"Authorization": f"Bearer {KEY}"}, timeout=30)
        while not self.stop.is_set():
            with self.lock:
                ids = list(self.jobs)
            url = f"/jobs/{self.rng.choice(ids)}" if ids and self.rng.random() < 0.8 else "/jobs?limit=20"
            t0 = time.perf_counter()
            try:
                r = cl.get(url)
                dt = time.perf_counter() - t0
                self.latency.append(dt)
                if r.status_code != 200:
                    self.status_errors.append(f"{url}: {r.status_code} {r.text[:200]}")
                elif url.startswith("/jobs/"):
                    j = r.json()
                    with self.lock:
                        self.jobs[j["id"]]["state"] = j["state"]
                        if j["type"] == "reconstruct" and j["state"] == "done":
                            self.reconstructed.add(j["scene_id"])
            except httpx.HTTPError as e:
                self.status_errors.append(f"{url}: {type(e).__name__}: {e}")
            self.stop.wait(0.1)

    def refresh_states(self) -> None:
        r = self.c.get("/jobs", params={"limit": 500})
        for j in r.json()["items"]:
            with self.lock:
                if j["id"] in self.jobs:
                    self.jobs[j["id"]]["state"] = j["state"]
                    if j["type"] == "reconstruct" and j["state"] == "done":
                        self.reconstructed.add(j["scene_id"])

    # -- faults ----------------------------------------------------------------------------------
    def kill_worker(self) -> None:
        ws = self.workers()
        if not ws:
            self.kills.append({"t": time.time(), "skipped": "no worker process found"})
            return
        running = [j for j in self.c.get("/jobs", params={"state": "running", "limit": 500}).json()["items"]]
        busy = {pid: name for pid, name in ws.items() if children(pid)}
        pid, name = (self.rng.choice(sorted(busy.items())) if busy else self.rng.choice(sorted(ws.items())))
        on_it = [(j["id"], j["attempts"]) for j in running
                 if j["attempt_history"] and (j["attempt_history"][-1]["worker"] or "").startswith(name + ".")]
        # a job the worker has taken from the queue but not yet started (claimed) counts too
        from worker.queue import parse_rq_id

        for w in self.c.get("/system").json()["workers"]:
            held = parse_rq_id(w["current_job"] or "") if w["name"].startswith(name + ".") else None
            if held and held[0] not in {jid for jid, _ in on_it}:
                on_it.append((held[0], held[1]))
        victims = [*children(pid), pid]  # the horse first: it never outlives its parent
        t_kill = time.time()
        for v in victims:
            try:
                os.kill(v, signal.SIGKILL)
            except ProcessLookupError:
                pass
        rec = {"t": t_kill, "worker": name, "pid": pid, "busy": pid in busy, "jobs": [j for j, _ in on_it],
               "retry_s": {}, "outcome": {}}
        self.kills.append(rec)
        threading.Thread(target=self._watch_retry, args=(rec, on_it), daemon=True).start()

    def _watch_retry(self, rec: dict, on_it: list[tuple[str, int]]) -> None:
        """Times, from the kill: each job's next attempt running (``retry_s``) and the worker
        replaced (``replaced_s``: as many worker processes as before, the killed one gone)."""
        cl = httpx.Client(base_url=self.base, headers={"Authorization": f"Bearer {KEY}"}, timeout=30)
        pending = dict(on_it)
        deadline = rec["t"] + 120
        while (pending or "replaced_s" not in rec) and time.time() < deadline:
            if "replaced_s" not in rec:
                ws = self.workers()
                if len(ws) >= self.a.workers and rec["pid"] not in ws:
                    rec["replaced_s"] = round(time.time() - rec["t"], 2)
            for jid, attempt in list(pending.items()):
                try:
                    j = cl.get(f"/jobs/{jid}").json()
                except (httpx.HTTPError, ValueError):
                    continue
                if j["attempts"] > attempt and j["state"] in ("running", "done"):
                    rec["retry_s"][jid] = round(time.time() - rec["t"], 3)
                    pending.pop(jid)
                elif j["state"] in FINAL:
                    rec["outcome"][jid] = f"{j['state']} without a retry running: {j['error']}"
                    pending.pop(jid)
                if j["attempts"] > attempt and jid not in rec.setdefault("requeued_s", {}):
                    rec["requeued_s"][jid] = round(time.time() - rec["t"], 3)  # queued again, not yet running
            time.sleep(0.05)
        for jid in pending:
            rec["outcome"][jid] = "no retry running within 120 s"

    def restart_redis(self) -> None:
        t0 = time.time()
        self.redis.kill()
        time.sleep(self.a.redis_down_s)
        self.redis.start()
        self.events.append({"redis_restart_at": round(t0 - self.t_start, 1), "down_s": round(time.time() - t0, 2)})

    # -- the run ---------------------------------------------------------------------------------
    def run(self) -> dict:
        from core.bundle import pack_bundle
        from core.synth import generate_scene, profile

        print(f"soak: generating a tiny scene in {self.tmp}", flush=True)
        scene = generate_scene(profile("tiny"), self.tmp / "tiny", progress=False, workers=1)
        self.scene_zip = pack_bundle(scene, self.tmp / "tiny.zip").read_bytes()
        self.start()
        # warm-up (not part of the measured run): one finished reconstruction, so relights can start
        t0 = time.time()
        self.upload()
        self.reconstruct()
        seed = next(iter(self.jobs))
        while time.time() - t0 < 900:
            self.refresh_states()
            if self.jobs[seed].get("state") in FINAL:
                break
            time.sleep(2)
        if self.jobs[seed].get("state") != "done":
            raise RuntimeError(f"the warm-up reconstruction did not finish: {self.c.get(f'/jobs/{seed}').json()}")
        self.warmup_s = round(time.time() - t0, 1)
        print(f"soak: brdf up on {self.base}, redis on {self.redis.port}; warm-up reconstruction {self.warmup_s} s; "
              f"load for {self.a.duration:.0f} s", flush=True)
        self.t_start = time.time()
        poller = threading.Thread(target=self.poll, daemon=True)
        poller.start()
        a = self.a
        # periods chosen so that cancels and kills rarely coincide (a canceled job is not retried)
        every = {"upload": 30.0, "reconstruct": 60.0, "relight": 6.0, "cancel": 37.0, "kill": a.kill_every,
                 "refresh": 5.0}
        next_at = {"upload": 15.0, "reconstruct": 10.0, "relight": 2.0, "cancel": 25.0, "kill": a.kill_every,
                   "refresh": 5.0}
        actions = {"upload": self.upload, "reconstruct": self.reconstruct, "relight": self.relight,
                   "cancel": self.cancel, "kill": self.kill_worker, "refresh": self.refresh_states}
        redis_done = False
        while (el := time.time() - self.t_start) < a.duration:
            if not redis_done and el >= a.redis_restart_at:
                self.restart_redis()
                redis_done = True
            for name, t in sorted(next_at.items(), key=lambda kv: kv[1]):
                if el >= t:
                    try:
                        actions[name]()
                    except httpx.HTTPError as e:
                        self.submit_errors.append(f"{name}: {type(e).__name__}: {e}")
                    next_at[name] = t + every[name]
            time.sleep(0.2)
        print(f"soak: load done, {len(self.jobs)} jobs accepted; draining up to {a.drain:.0f} s", flush=True)
        deadline = time.time() + a.drain
        while time.time() < deadline:
            self.refresh_states()
            with self.lock:
                if all(m.get("state") in FINAL for m in self.jobs.values()):
                    break
            time.sleep(2)
        self.stop.set()
        poller.join(5)
        return self.report()

    def report(self) -> dict:
        final = {}
        lost = []
        for jid in list(self.jobs):
            r = self.c.get(f"/jobs/{jid}")
            if r.status_code == 404:
                lost.append(jid)
            else:
                final[jid] = r.json()
        states = {s: sum(1 for j in final.values() if j["state"] == s) for s in ("queued", "running", *FINAL)}
        stuck = [jid for jid, j in final.items() if j["state"] not in FINAL]
        retry_times = [s for k in self.kills for s in k.get("retry_s", {}).values()]
        metrics = self.c.get("/metrics").text
        restarts = re.search(r"^brdf_worker_restarts_total (\S+)$", metrics, re.M)
        log = self.log.read_text(errors="replace")
        by_type = {}
        for j in final.values():
            by_type.setdefault(j["type"], {}).setdefault(j["state"], 0)
            by_type[j["type"]][j["state"]] += 1
        failed = {jid: j["error"] for jid, j in final.items() if j["state"] == "failed"}
        lat_ms = [x * 1000 for x in self.latency]
        return {
            "what": "soak: brdf up (gateway + supervised workers), private Redis restarted once, kill -9 of a worker "
                    "(with its work horse) periodically; uploads, tiny reconstructs, relights, cancels, status polls",
            "command": "python benchmarks/soak.py " + " ".join(sys.argv[1:]),
            "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "python": platform.python_version()},
            "settings": {"duration_s": self.a.duration, "kill_every_s": self.a.kill_every, "workers": self.a.workers,
                         "redis_restart_at_s": self.a.redis_restart_at, "drain_s": self.a.drain, "seed": self.a.seed},
            "jobs": {"accepted": len(self.jobs), **states, "lost": len(lost), "stuck": len(stuck),
                     "by_type": by_type, "cancel_requests": self.cancels,
                     "retried": sum(1 for j in final.values() if j["attempts"] > 1)},
            "lost_ids": lost, "stuck_ids": stuck, "failed_errors": failed,
            "scenes_uploaded": len(self.scenes), "warmup_reconstruction_s": getattr(self, "warmup_s", None), "submit_errors": self.submit_errors[:50],
            "status": {"requests": len(lat_ms), "p50_ms": pct(lat_ms, 50), "p99_ms": pct(lat_ms, 99),
                       "max_ms": max(lat_ms) if lat_ms else None, "errors": len(self.status_errors),
                       "error_samples": self.status_errors[:20]},
            "kills": [{**k, "t": round(k["t"] - self.t_start, 1)} for k in self.kills],
            "kill_to_retry_s": {"n": len(retry_times), "max": max(retry_times) if retry_times else None,
                                "median": statistics.median(retry_times) if retry_times else None,
                                "all": sorted(retry_times)},
            "kill_to_requeue_s": sorted(v for k in self.kills for v in k.get("requeued_s", {}).values()),
            "worker_restarts": float(restarts.group(1)) if restarts else None,
            "kill_to_replacement_s": sorted(k["replaced_s"] for k in self.kills if k.get("replaced_s") is not None),
            "redis": self.events, "reenqueued_after_redis_restart": log.count("(missing from Redis)"),
        }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--duration", type=float, default=600.0, help="seconds of load (default 600)")
    ap.add_argument("--kill-every", type=float, default=60.0, help="kill -9 a worker this often (s)")
    ap.add_argument("--redis-restart-at", type=float, default=None, help="when to restart Redis (default: half way)")
    ap.add_argument("--redis-down-s", type=float, default=3.0, help="how long Redis stays down")
    ap.add_argument("--drain", type=float, default=300.0, help="seconds for accepted jobs to finish after the load")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=str(REPO / "benchmarks" / "results" / "soak.json"))
    a = ap.parse_args()
    if a.redis_restart_at is None:
        a.redis_restart_at = a.duration / 2
    if not shutil.which("redis-server"):
        print("soak: redis-server is not installed", file=sys.stderr)
        return 2
    s = Soak(a)
    watchdog = threading.Timer(a.duration + a.drain + 600, lambda: os.kill(os.getpid(), signal.SIGTERM))
    watchdog.daemon = True
    watchdog.start()
    try:
        res = s.run()
    finally:
        s.shutdown()
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(res, indent=1, default=str))
    j, st, k = res["jobs"], res["status"], res["kill_to_retry_s"]
    print(f"soak: accepted {j['accepted']}, done {j['done']}, failed {j['failed']}, canceled {j['canceled']}, "
          f"lost {j['lost']}, stuck {j['stuck']}; status p99 {st['p99_ms']:.1f} ms ({st['requests']} requests, "
          f"{st['errors']} errors); kill -> retry running: max {k['max']} s over {k['n']} jobs; "
          f"worker restarts {res['worker_restarts']}; -> {a.out}")
    shutil.rmtree(s.tmp, ignore_errors=True)
    return 0 if j["lost"] == 0 and j["stuck"] == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
