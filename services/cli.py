"""``brdf serve``, ``brdf worker``, ``brdf up`` and ``brdf keys``: the service's commands, and
:func:`main`, the installed ``brdf`` command (the library's commands of :mod:`core.cli` plus
these; ``core`` imports no server code)."""

from __future__ import annotations

import logging
import os
import shutil
import signal
import subprocess
import sys
import time
from argparse import Namespace
from urllib.parse import urlparse

#: The exact commands the docker compose file runs (tests check that they agree).
SERVE_CMD = ["brdf", "serve", "--host", "0.0.0.0", "--port", "8000"]
WORKER_CMD = ["brdf", "worker", "--queues", "render,train"]


class ServiceError(Exception):
    """A service command cannot start; the message says why and what to do."""


def _settings():
    from pydantic import ValidationError

    from worker.settings import Settings

    try:
        return Settings()
    except ValidationError as e:
        raise ServiceError(f"invalid BRDF_* environment setting: {e}") from None


def _logging() -> None:
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")


def serve(host: str, port: int, log_level: str = "info", supervisor=None, settings=None) -> int:
    import uvicorn

    from services.app import create_app

    _logging()
    app = create_app(settings or _settings())
    app.state.supervisor = supervisor
    uvicorn.run(app, host=host, port=port, log_level=log_level, access_log=False, timeout_keep_alive=30)
    return 0


def worker(queues: str, burst: bool = False, fork: bool = True, name: str | None = None, nice: int = 0) -> int:
    from worker.main import run_worker

    _logging()
    if not 0 <= nice <= 19:
        raise ServiceError(f"--nice: expected 0..19, got {nice}")
    if nice:
        os.nice(nice)  # renders yield the CPU to a gateway on the same machine
    qs = [q.strip() for q in queues.split(",") if q.strip()]
    try:
        return run_worker(_settings(), qs, burst=burst, fork=fork, name=name)
    except ValueError as e:
        raise ServiceError(str(e)) from None


def keys_create(tenant: str, scope: str, name: str) -> int:
    from services.auth import create_key
    from services.db import get_database

    s = _settings()
    try:
        secret, row = create_key(get_database(s.db_url), tenant, scope, name)
    except ValueError as e:
        raise ServiceError(str(e)) from None
    print(f"created {scope} key {row.id} for tenant {tenant!r} (shown once, stored hashed):")
    print(secret)
    return 0


def _redis_up(url: str) -> bool:
    import redis

    try:
        return bool(redis.Redis.from_url(url, socket_connect_timeout=1).ping())
    except redis.RedisError:
        return False


def up(host: str, port: int, workers: int) -> int:
    """A gateway and ``workers`` workers on this machine against a local Redis (started here if
    none answers and ``redis-server`` is installed). The workers are supervised: one that exits
    is restarted with backoff (:mod:`services.supervisor`). Ctrl-C stops everything it started."""
    from services.supervisor import WorkerSupervisor
    from services.auth import create_key
    from services.db import ApiKey, get_database

    s = _settings()
    s.data_dir.mkdir(parents=True, exist_ok=True)
    children: list[subprocess.Popen] = []
    u = urlparse(s.redis_url)
    if not _redis_up(s.redis_url):
        if u.hostname not in ("127.0.0.1", "localhost", "::1") or not shutil.which("redis-server"):
            raise ServiceError(f"Redis at {s.redis_url} does not answer; start it or set BRDF_REDIS_URL")
        rdir = s.data_dir / "redis"
        rdir.mkdir(exist_ok=True)
        print(f"starting redis-server on port {u.port or 6379} (append-only file in {rdir})")
        children.append(subprocess.Popen(["redis-server", "--bind", "127.0.0.1", "--port", str(u.port or 6379),
                                          "--appendonly", "yes", "--dir", str(rdir)], stdout=subprocess.DEVNULL))
        for _ in range(50):
            if _redis_up(s.redis_url):
                break
            time.sleep(0.1)
        else:
            raise ServiceError("redis-server did not start")
    db = get_database(s.db_url)
    from sqlalchemy import select

    key = s.bootstrap_operator_key
    with db.session() as ss:
        has_op = ss.scalar(select(ApiKey).where(ApiKey.scope == "operator", ApiKey.revoked_at.is_(None))) is not None
    if key:
        create_key(db, "operator", "operator", "bootstrap", secret=key)
    elif not has_op:
        key, _ = create_key(db, "operator", "operator", "created by brdf up")
    env = dict(os.environ)
    exe = [sys.executable, "-m", "services.cli"]
    _logging()
    # one machine: the gateway's latency comes first, so workers run at a lower CPU priority
    sup = WorkerSupervisor(s, exe + ["worker", "--queues", "render,train", "--nice", "10"], workers, env)
    sup.start()
    print(f"gateway: http://{host}:{port}   dashboard: http://{host}:{port}/dashboard   "
          f"API docs: http://{host}:{port}/docs")
    print(f"data: {s.data_dir}   database: {s.db_url.split('@')[-1]}   redis: {s.redis_url}")
    if key:
        print(f"operator key (shown once, stored hashed): {key}")
    else:
        print("operator key: already created earlier (brdf keys create --scope operator makes another)")
    try:
        return serve(host, port, supervisor=sup, settings=s)
    finally:
        sup.stop()
        for c in reversed(children):
            if c.poll() is None:
                c.send_signal(signal.SIGTERM)
        for c in children:
            try:
                c.wait(timeout=20)
            except subprocess.TimeoutExpired:
                c.kill()


def _run(a: Namespace) -> int:
    from core.errors import CoreError

    try:
        if a.cmd == "serve":
            return serve(a.host, a.port)
        if a.cmd == "worker":
            return worker(a.queues, burst=a.burst, fork=not a.no_fork, name=a.name, nice=a.nice)
        if a.cmd == "up":
            return up(a.host, a.port, a.workers)
        return keys_create(a.tenant, a.scope, a.name)
    except ServiceError as e:
        raise CoreError(str(e)) from None


def add_commands(sub) -> None:
    """Add serve, worker, up and keys to the ``brdf`` subparsers (:func:`core.cli.build_parser`)."""
    sv = sub.add_parser("serve", help="run the HTTP gateway (settings from BRDF_* environment variables)")
    sv.add_argument("--host", default="127.0.0.1")
    sv.add_argument("--port", type=int, default=8000)
    sv.set_defaults(fn=_run)

    wk = sub.add_parser("worker", help="run an RQ worker on the render and/or train queues")
    wk.add_argument("--queues", default="render,train", help="comma-separated: render, train")
    wk.add_argument("--burst", action="store_true", help="exit when the queues are empty")
    wk.add_argument("--no-fork", action="store_true", help="run jobs in the worker process (warm models)")
    wk.add_argument("--name", default=None)
    wk.add_argument("--nice", type=int, default=0, help="lower the worker's CPU priority (0-19), e.g. beside a gateway")
    wk.set_defaults(fn=_run)

    up_ = sub.add_parser("up", help="one machine: a gateway and workers against a local Redis")
    up_.add_argument("--host", default="127.0.0.1")
    up_.add_argument("--port", type=int, default=8000)
    up_.add_argument("--workers", type=int, default=1)
    up_.set_defaults(fn=_run)

    ky = sub.add_parser("keys", help="create an API key (shown once, stored hashed)")
    ky.add_argument("action", choices=["create"])
    ky.add_argument("--tenant", required=True)
    ky.add_argument("--scope", choices=["client", "operator"], default="client")
    ky.add_argument("--name", default="")
    ky.set_defaults(fn=_run)


def main(argv: list[str] | None = None) -> int:
    """The ``brdf`` command: the library's commands and the service's."""
    from core.cli import main as core_main

    return core_main(argv, extensions=(add_commands,))


if __name__ == "__main__":
    sys.exit(main())
