"""Shared test support for the service packages: real Redis and PostgreSQL (started if down),
isolated Redis DB numbers, private throwaway Redis servers, scene bundles, and subprocess
gateways / workers run with the same commands as the docker compose file."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
import uuid
from contextlib import contextmanager
from pathlib import Path

import pytest

from core.bundle.testing import write_fake_bundle as make_bundle  # noqa: F401  (the one fake-bundle builder)
from services.supervisor import descendants
from services.testing import PrivateRedis, free_port, redis_ping  # noqa: F401  (the tests' private Redis)

REPO = Path(__file__).resolve().parents[2]
REDIS_START = ["redis-server", "--daemonize", "yes", "--bind", "127.0.0.1", "-::1", "--port", "6379", "--save", "",
               "--appendonly", "no", "--dir", "/var/lib/redis", "--logfile", "/var/log/redis/ci.log"]


def ensure_redis() -> str:
    """The machine's Redis on 6379, started with the CI command if it is down."""
    url = "redis://127.0.0.1:6379/0"
    if redis_ping(url):
        return url
    if not shutil.which("redis-server"):
        pytest.fail("Redis is down and redis-server is not installed (apt-get install redis-server)")
    for d in ("/var/lib/redis", "/var/log/redis"):
        os.makedirs(d, exist_ok=True)
    subprocess.run(REDIS_START, check=True, stdout=subprocess.DEVNULL)
    for _ in range(50):
        if redis_ping(url):
            return url
        time.sleep(0.1)
    pytest.fail("could not start redis-server on 127.0.0.1:6379")


def claim_redis_db() -> tuple[str, int]:
    """An empty Redis DB number (1..15) claimed with a marker key so parallel test runs never
    share one; the caller flushes it when done."""
    import redis

    ensure_redis()
    for n in range(15, 0, -1):
        r = redis.Redis(host="127.0.0.1", port=6379, db=n)
        if r.dbsize() == 0 and r.set("brdf-test-claim", f"{os.getpid()}", nx=True, ex=3600):
            if r.dbsize() == 1:
                return f"redis://127.0.0.1:6379/{n}", n
            r.delete("brdf-test-claim")
    pytest.fail("no free Redis DB (1..15) to run the service tests in")


def ensure_postgres() -> str:
    """A psycopg conninfo for the machine's PostgreSQL, started with pg_ctlcluster if down."""
    import psycopg

    def ok(user):
        try:
            with psycopg.connect(f"host=127.0.0.1 port=5432 user={user} dbname=postgres", connect_timeout=2):
                return True
        except psycopg.OperationalError:
            return False

    for attempt in range(2):
        for user in ("postgres", "root"):
            if ok(user):
                return f"host=127.0.0.1 port=5432 user={user}"
        if attempt == 0:
            versions = os.listdir("/etc/postgresql") if os.path.isdir("/etc/postgresql") else []
            if not versions:
                pytest.fail("PostgreSQL is down and not installed")
            subprocess.run(["pg_ctlcluster", "--skip-systemctl-redirect", versions[0], "main", "start"],
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            for _ in range(50):
                if ok("postgres") or ok("root"):
                    break
                time.sleep(0.2)
    pytest.fail("could not reach or start PostgreSQL on 127.0.0.1:5432")


@contextmanager
def postgres_database():
    """A dedicated, freshly created PostgreSQL database; dropped afterwards. Yields its URL."""
    import psycopg

    conninfo = ensure_postgres()
    name = f"brdf_test_{uuid.uuid4().hex[:10]}"
    user = conninfo.split("user=")[1]
    with psycopg.connect(conninfo + " dbname=postgres", autocommit=True) as c:
        c.execute(f'CREATE DATABASE "{name}"')
    try:
        yield f"postgresql+psycopg://{user}@127.0.0.1:5432/{name}"
    finally:
        from worker.db import _dbs

        for k in [k for k in _dbs if name in k[0]]:
            _dbs.pop(k).dispose()
        with psycopg.connect(conninfo + " dbname=postgres", autocommit=True) as c:
            c.execute(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)')


def zip_bundle(root: Path, out: Path) -> Path:
    from core.bundle import pack_bundle

    return pack_bundle(root, out)


def svc_env(settings) -> dict[str, str]:
    """Environment for a subprocess gateway / worker with ``settings``."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("BRDF_")}
    env.update({"BRDF_DATA_DIR": str(settings.data_dir), "BRDF_REDIS_URL": settings.redis_url,
                "BRDF_DATABASE_URL": settings.db_url, "BRDF_ARTIFACT_STORE": settings.store_url,
                "BRDF_HEARTBEAT_S": str(settings.heartbeat_s), "BRDF_STALE_AFTER_S": str(settings.stale_after_s),
                "BRDF_RECONCILE_INTERVAL_S": str(settings.reconcile_interval_s),
                "BRDF_REQUEUE_GRACE_S": str(settings.requeue_grace_s), "BRDF_MAX_ATTEMPTS": str(settings.max_attempts),
                "PYTHONUNBUFFERED": "1"})
    if settings.bootstrap_operator_key:
        env["BRDF_BOOTSTRAP_OPERATOR_KEY"] = settings.bootstrap_operator_key
    return env


def cli_cmd(cmd: list[str], **replace: str) -> list[str]:
    """A compose command (``brdf ...``) as run here: the venv's interpreter, and the host / port
    swapped for test values."""
    assert cmd[0] == "brdf"
    out = [sys.executable, "-m", "services.cli", *cmd[1:]]
    return [replace.get(x, x) for x in out]


class Proc:
    """A service subprocess in its own process group (so kill -9 takes its work horse too)."""

    def __init__(self, args: list[str], env: dict, log: Path):
        self.log = log
        self.fh = open(log, "ab")
        self.p = subprocess.Popen(args, env=env, cwd=REPO, stdout=self.fh, stderr=subprocess.STDOUT,
                                  start_new_session=True)

    def descendants(self) -> list[int]:
        """Every process below this one (an RQ work horse calls setsid, leaving our group)."""
        return descendants(self.p.pid)

    def kill9(self) -> None:
        """kill -9 the process and everything it started (as when its machine or container dies)."""
        if self.p.poll() is None:
            victims = self.descendants()
            os.killpg(self.p.pid, signal.SIGKILL)
            for pid in victims:
                try:
                    os.kill(pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
            self.p.wait(10)

    def stop(self) -> None:
        if self.p.poll() is None:
            victims = self.descendants()
            try:
                os.killpg(self.p.pid, signal.SIGTERM)
                self.p.wait(15)
            except (subprocess.TimeoutExpired, ProcessLookupError):
                self.kill9()
            for pid in victims:  # a work horse left running by a killed parent
                try:
                    os.kill(pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
        if not self.fh.closed:
            self.fh.close()

    def tail(self, n: int = 40) -> str:
        try:
            return "\n".join(self.log.read_text(errors="replace").splitlines()[-n:])
        except OSError:
            return ""


def start_gateway(settings, log: Path, port: int | None = None) -> tuple[Proc, str]:
    import httpx

    from services.cli import SERVE_CMD

    port = port or free_port()
    p = Proc(cli_cmd(SERVE_CMD, **{"0.0.0.0": "127.0.0.1", "8000": str(port)}), svc_env(settings), log)
    base = f"http://127.0.0.1:{port}"
    deadline = time.time() + 60
    while time.time() < deadline:
        if p.p.poll() is not None:
            raise RuntimeError(f"gateway exited: {p.tail()}")
        try:
            if httpx.get(base + "/healthz", timeout=1).status_code == 200:
                return p, base
        except httpx.HTTPError:
            pass
        time.sleep(0.2)
    p.stop()
    raise RuntimeError(f"gateway did not start: {p.tail()}")


def start_worker(settings, log: Path) -> Proc:
    from services.cli import WORKER_CMD

    return Proc(cli_cmd(WORKER_CMD), svc_env(settings), log)


def start_up(env: dict, log: Path, workers: int = 1) -> tuple[subprocess.Popen, str]:
    """``brdf up`` (a gateway and ``workers`` supervised workers) on a free port in a session of
    its own, its output in ``log``; (the process, the gateway's base URL)."""
    port = free_port()
    with open(log, "wb") as fh:
        p = subprocess.Popen([sys.executable, "-m", "services.cli", "up", "--port", str(port), "--workers", str(workers)],
                             env=env, cwd=REPO, stdout=fh, stderr=subprocess.STDOUT, start_new_session=True)
    return p, f"http://127.0.0.1:{port}"


def stop_up(p: subprocess.Popen) -> None:
    """Ctrl-C a ``brdf up`` and wait for it; past 30 s it is killed and the timeout raised."""
    p.send_signal(signal.SIGINT)
    try:
        p.wait(30)
    except subprocess.TimeoutExpired:
        p.kill()
        raise


def http_ok(url: str) -> bool:
    """``GET url`` answers 200."""
    import httpx

    try:
        return httpx.get(url, timeout=2).status_code == 200
    except httpx.HTTPError:
        return False


def wait_for(fn, timeout: float, what: str, interval: float = 0.2):
    deadline = time.time() + timeout
    last = None
    while time.time() < deadline:
        last = fn()
        if last:
            return last
        time.sleep(interval)
    raise AssertionError(f"timed out after {timeout:.0f} s waiting for {what} (last: {last!r})")
