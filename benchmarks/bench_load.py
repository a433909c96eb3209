"""Load benchmark of the gateway: status and listing requests at a fixed rate on loopback while
a worker renders.

Setup (all local, all torn down at the end): a private ``redis-server`` on a free loopback port,
a SQLite database and artifact store in a temp dir, one gateway (``brdf serve``, one uvicorn
process) and one worker (``brdf worker``), both subprocesses. A scene of 40 frames (160x120 with
G-buffers) is uploaded and render jobs are kept queued for the whole run, so the worker renders
throughout (the number it finished is recorded).

Load: an open-loop asyncio + httpx client sends ``--rps`` requests per second for
``--duration`` seconds (a bounded count: rps x duration), each due at its own time, at most
``--max-in-flight`` at once, as a client-scoped key. The mix: 50% ``GET /jobs/{id}``, 20% ``GET
/scenes``, 20% ``GET /jobs?limit=20``, 10% ``GET /jobs/{id}/artifacts``. Latency is measured from
the moment a request is sent (``p50_ms``, ``p99_ms``) and, to expose client-side lag, from the
moment it was due (``p99_ms_from_due``). An error is any non-200 answer or transport failure.

The machine has 2 cores shared by the client, the gateway, the worker and whatever else runs:
the load average before and after, and the CPU time each process used, are recorded.

Usage: ``python benchmarks/bench_load.py [--rps 200] [--duration 60]``.
Writes ``benchmarks/results/load.json``.
"""

from __future__ import annotations

import argparse
import asyncio
import datetime
import json
import os
import platform
import random
import shutil
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
OPERATOR_KEY = "brdf_bench-operator-" + os.urandom(12).hex()


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def cpu_model() -> str:
    try:
        for ln in open("/proc/cpuinfo"):
            if ln.startswith("model name"):
                return ln.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def proc_cpu_s(pid: int) -> float:
    """CPU seconds (user + system) of a process and its reaped children."""
    try:
        f = open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()
        return sum(int(x) for x in f[11:15]) / os.sysconf("SC_CLK_TCK")
    except OSError:
        return float("nan")


def busy_processes(exclude: set[int], top: int = 4) -> list[dict]:
    """The other processes using the most CPU right now (over the last second), to tell contention
    from a slow gateway."""
    def ticks():
        out = {}
        for d in os.listdir("/proc"):
            if d.isdigit() and int(d) not in exclude:
                try:
                    f = open(f"/proc/{d}/stat").read().rsplit(")", 1)[1].split()
                    if int(f[1]) in exclude:  # a child of ours (the worker's work horse)
                        continue
                    cmd = open(f"/proc/{d}/cmdline", "rb").read().replace(b"\0", b" ").decode(errors="replace")
                    out[int(d)] = (int(f[11]) + int(f[12]), cmd.strip()[:60])
                except (OSError, ValueError, IndexError):
                    pass
        return out

    a = ticks()
    time.sleep(1.0)
    b = ticks()
    hz = os.sysconf("SC_CLK_TCK")
    use = sorted(((b[p][0] - a[p][0]) / hz, b[p][1]) for p in b if p in a)[::-1][:top]
    return [{"process": name, "cpu_cores": round(c, 2)} for c, name in use if c > 0.05]


def make_scene(root: Path) -> Path:
    """40 random frames of 160x120 with G-buffers, 5 of them test frames, zipped."""
    from core.bundle import pack_bundle
    from core.bundle.testing import write_fake_bundle

    return pack_bundle(write_fake_bundle(root / "b", frames=40, width=160, height=120, test_frames=5, name="bench"),
                       root / "bench.zip")


def start(args, env, log: Path) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "services.cli", *args], env=env, cwd=REPO, stdout=open(log, "ab"),
                            stderr=subprocess.STDOUT, start_new_session=True)


def stop(p: subprocess.Popen) -> None:
    if p.poll() is None:
        try:
            os.killpg(p.pid, signal.SIGTERM) if os.getpgid(p.pid) == p.pid else p.terminate()
            p.wait(20)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait(10)
        except ProcessLookupError:
            pass


def request_paths(job_ids: list[str], total: int, seed: int = 0) -> list[str]:
    rng = random.Random(seed)
    paths = []
    for _ in range(total):
        x = rng.random()
        jid = rng.choice(job_ids)
        paths.append(f"/jobs/{jid}" if x < 0.5 else "/scenes" if x < 0.7 else "/jobs?limit=20" if x < 0.9
                     else f"/jobs/{jid}/artifacts")
    return paths


async def load_httpx(base: str, key: str, paths: list[str], rps: float, max_in_flight: int):
    total = len(paths)
    lat, lat_due, errors, err_kinds = [], [], 0, {}
    sem = asyncio.Semaphore(max_in_flight)
    limits = httpx.Limits(max_connections=max_in_flight, max_keepalive_connections=max_in_flight)
    async with httpx.AsyncClient(base_url=base, headers={"Authorization": f"Bearer {key}"}, limits=limits,
                                 timeout=10.0) as c:
        loop = asyncio.get_running_loop()
        t0 = loop.time() + 0.5

        async def one(i: int, due: float):
            nonlocal errors
            async with sem:
                s = loop.time()
                try:
                    r = await c.get(paths[i])
                    ok = r.status_code == 200
                    kind = str(r.status_code)
                except httpx.HTTPError as e:
                    ok, kind = False, type(e).__name__
                e_ = loop.time()
            lat.append((e_ - s) * 1000)
            lat_due.append((e_ - due) * 1000)
            if not ok:
                errors += 1
                err_kinds[kind] = err_kinds.get(kind, 0) + 1

        # open loop: a dispatcher starts each request when it is due (not when the last one ends)
        start_t = time.perf_counter()
        tasks = []
        for i in range(total):
            due = t0 + i / rps
            delay = due - loop.time()
            if delay > 0:
                await asyncio.sleep(delay)
            tasks.append(asyncio.create_task(one(i, due)))
        await asyncio.gather(*tasks)
        wall = time.perf_counter() - start_t - 0.5
    return lat, lat_due, errors, err_kinds, wall, total


async def load_raw(base: str, key: str, paths: list[str], rps: float, conns: int):
    """The same open-loop schedule on ``conns`` keep-alive HTTP/1.1 connections written with
    asyncio streams: ~0.1 ms of client CPU per request, against 1.6-5 ms for httpx's async client
    on this machine, which would otherwise take the CPU the gateway under test needs."""
    host, port = base.split("//")[1].split(":")
    loop = asyncio.get_running_loop()
    queue: asyncio.Queue = asyncio.Queue()
    lat, lat_due, kinds = [], [], {}

    async def conn_worker():
        reader = writer = None
        while True:
            item = await queue.get()
            if item is None:
                break
            i, due = item
            s = loop.time()
            try:
                if writer is None:
                    reader, writer = await asyncio.open_connection(host, int(port))
                writer.write(f"GET {paths[i]} HTTP/1.1\r\nHost: {host}\r\nAuthorization: Bearer {key}\r\n\r\n"
                             .encode())
                head = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), 10)
                status = int(head.split(b" ", 2)[1])
                length = 0
                for ln in head.split(b"\r\n")[1:]:
                    if ln[:15].lower() == b"content-length:":
                        length = int(ln[15:])
                await asyncio.wait_for(reader.readexactly(length), 10)
                kind = str(status) if status != 200 else None
            except (OSError, asyncio.IncompleteReadError, asyncio.TimeoutError, asyncio.LimitOverrunError,
                    ValueError) as e:
                kind = type(e).__name__
                if writer is not None:
                    writer.close()
                reader = writer = None
            e_ = loop.time()
            lat.append((e_ - s) * 1000)
            lat_due.append((e_ - due) * 1000)
            if kind:
                kinds[kind] = kinds.get(kind, 0) + 1
        if writer is not None:
            writer.close()

    workers = [asyncio.create_task(conn_worker()) for _ in range(conns)]
    t0 = loop.time() + 0.5
    start_t = time.perf_counter()
    for i in range(len(paths)):
        due = t0 + i / rps
        delay = due - loop.time()
        if delay > 0:
            await asyncio.sleep(delay)
        queue.put_nowait((i, due))
    for _ in workers:
        queue.put_nowait(None)
    await asyncio.gather(*workers)
    wall = time.perf_counter() - start_t - 0.5
    return lat, lat_due, sum(kinds.values()), kinds, wall, len(paths)


def pct(xs, q):
    xs = sorted(xs)
    return xs[min(len(xs) - 1, max(0, int(round(q / 100 * len(xs))) - 1))]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rps", type=float, default=200.0)
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--max-in-flight", type=int, default=16, help="connections (and requests in flight)")
    ap.add_argument("--client", choices=["raw", "httpx"], default="raw",
                    help="raw: asyncio streams (default, cheap); httpx: httpx.AsyncClient")
    ap.add_argument("--worker-nice", type=int, default=10, help="the worker's niceness (brdf up uses 10)")
    ap.add_argument("--out", default=str(REPO / "benchmarks" / "results" / "load.json"))
    a = ap.parse_args()
    if not shutil.which("redis-server"):
        print("error: redis-server is needed (apt-get install redis-server)", file=sys.stderr)
        return 2
    tmp = Path(tempfile.mkdtemp(prefix="brdf-load-"))
    procs: list[subprocess.Popen] = []
    try:
        rport, port = free_port(), free_port()
        procs.append(subprocess.Popen(["redis-server", "--bind", "127.0.0.1", "--port", str(rport), "--save", "",
                                       "--appendonly", "no", "--dir", str(tmp)], stdout=subprocess.DEVNULL))
        env = {k: v for k, v in os.environ.items() if not k.startswith("BRDF_")}
        env.update({"BRDF_DATA_DIR": str(tmp / "svc"), "BRDF_REDIS_URL": f"redis://127.0.0.1:{rport}/0",
                    "BRDF_BOOTSTRAP_OPERATOR_KEY": OPERATOR_KEY, "PYTHONUNBUFFERED": "1"})
        gw = start(["serve", "--host", "127.0.0.1", "--port", str(port)], env, tmp / "gateway.log")
        procs.append(gw)
        # as `brdf up` runs it on one machine: the worker at a lower CPU priority than the gateway
        wk = start(["worker", "--queues", "render,train", "--nice", str(a.worker_nice)], env, tmp / "worker.log")
        procs.append(wk)
        base = f"http://127.0.0.1:{port}"
        op = httpx.Client(base_url=base, headers={"Authorization": f"Bearer {OPERATOR_KEY}"}, timeout=60)
        for _ in range(300):
            try:
                if op.get("/readyz").status_code == 200:
                    break
            except httpx.HTTPError:
                pass
            time.sleep(0.2)
        else:
            raise RuntimeError("gateway did not become ready: " + (tmp / "gateway.log").read_text()[-2000:])
        key = op.post("/keys", json={"tenant": "bench", "scope": "client"}).json()["key"]
        cl = httpx.Client(base_url=base, headers={"Authorization": f"Bearer {key}"}, timeout=60)
        z = make_scene(tmp)
        sid = cl.post("/scenes", content=z.read_bytes(), headers={"Content-Type": "application/zip"}).json()["id"]
        first = cl.post(f"/scenes/{sid}/render", json={}).json()["id"]
        t = time.time()
        while cl.get(f"/jobs/{first}").json()["state"] != "done":
            if time.time() - t > 120:
                raise RuntimeError("warm-up render did not finish: " + (tmp / "worker.log").read_text()[-2000:])
            time.sleep(0.5)
        one_render_s = time.time() - t
        # keep the worker busy for the whole run: enough renders queued to outlast it
        n_jobs = int(a.duration / max(one_render_s, 1.0)) + 3
        queued = [cl.post(f"/scenes/{sid}/render", json={}).json()["id"] for _ in range(n_jobs)]
        job_ids = [first, *queued]
        time.sleep(1.0)

        others = busy_processes({os.getpid(), gw.pid, wk.pid, procs[0].pid})
        load0 = os.getloadavg()
        cpu0 = {"gateway": proc_cpu_s(gw.pid), "worker": proc_cpu_s(wk.pid)}
        client0 = time.process_time()
        print(f"machine: {os.cpu_count()} cores, {cpu_model()}, Python {platform.python_version()}, "
              f"load average {load0[0]:.2f}; other busy processes: {others}")
        print(f"settings: {a.rps:.0f} req/s for {a.duration:.0f} s ({int(a.rps * a.duration)} requests), "
              f"at most {a.max_in_flight} in flight ({a.client} client); 1 gateway process, 1 worker rendering at nice {a.worker_nice} "
              f"({len(queued)} render jobs queued, one takes ~{one_render_s:.1f} s)")
        paths = request_paths(job_ids, int(a.rps * a.duration))
        if a.client == "httpx":
            lat, lat_due, errors, kinds, wall, total = asyncio.run(load_httpx(base, key, paths, a.rps, a.max_in_flight))
        else:
            lat, lat_due, errors, kinds, wall, total = asyncio.run(load_raw(base, key, paths, a.rps, a.max_in_flight))
        client_cpu = time.process_time() - client0
        cpu = {k: proc_cpu_s(p.pid) - cpu0[k] for k, p in (("gateway", gw), ("worker", wk))}
        load1 = os.getloadavg()
        states = [cl.get(f"/jobs/{j}").json()["state"] for j in queued]
        renders_done = sum(s == "done" for s in states)
        res = {
            "benchmark": "gateway status/listing load while a worker renders",
            "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "rps": round(total / wall, 1), "target_rps": a.rps, "requests": total,
            "p50_ms": round(statistics.median(lat), 2), "p99_ms": round(pct(lat, 99), 2),
            "p99_ms_from_due": round(pct(lat_due, 99), 2), "max_ms": round(max(lat), 2),
            "errors": errors, "error_kinds": kinds, "duration_s": round(wall, 2),
            "mix": {"GET /jobs/{id}": 0.5, "GET /scenes": 0.2, "GET /jobs?limit=20": 0.2,
                    "GET /jobs/{id}/artifacts": 0.1},
            "renders_finished_during_run": renders_done, "render_s_each": round(one_render_s, 2),
            "cpu_s": {"client": round(client_cpu, 1), **{k: round(v, 1) for k, v in cpu.items()}},
            "machine": {"cores": os.cpu_count(), "cpu": cpu_model(), "python": platform.python_version(),
                        "load_avg_before": round(load0[0], 2), "load_avg_after": round(load1[0], 2),
                        "other_busy_processes_at_start": others,
                        "note": "2 cores shared by the load client, the gateway, the rendering worker and "
                                "other work on the machine"},
            "settings": {"max_in_flight": a.max_in_flight, "gateway_processes": 1, "workers": 1,
                         "worker_nice": a.worker_nice,
                         "database": "sqlite (WAL)", "client": "asyncio streams, HTTP/1.1 keep-alive" if a.client == "raw"
                         else f"httpx {httpx.__version__} AsyncClient"},
        }
        print(json.dumps({k: res[k] for k in ("rps", "p50_ms", "p99_ms", "p99_ms_from_due", "errors", "duration_s",
                                              "renders_finished_during_run", "cpu_s")}, indent=None))
        ok = errors == 0 and res["p99_ms"] <= 100
        print(f"target (p99 <= 100 ms, no errors): {'met' if ok else 'NOT met'}")
        Path(a.out).parent.mkdir(parents=True, exist_ok=True)
        Path(a.out).write_text(json.dumps(res, indent=2) + "\n")
        print(f"wrote {a.out}")
        return 0
    finally:
        for p in reversed(procs):
            stop(p)
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main())
