"""Fixtures shared by tests/services, tests/worker and tests/api_schemas (see svc_support.py)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from svc_support import claim_redis_db, make_bundle, zip_bundle  # noqa: E402

OPERATOR_KEY = "brdf_test-operator-key-0123456789abcdefghijklmnop"


@pytest.fixture(autouse=True)
def _reset_worker_settings():
    """In-process workers point get_settings() at a test's settings; undo that after each test."""
    yield
    from worker.settings import configure

    configure(None)


@pytest.fixture
def redis_url():
    import redis

    url, n = claim_redis_db()
    yield url
    redis.Redis.from_url(url).flushdb()


@pytest.fixture
def settings(tmp_path, redis_url):
    from worker.settings import Settings

    return Settings(data_dir=tmp_path / "svc", redis_url=redis_url, bootstrap_operator_key=OPERATOR_KEY,
                    heartbeat_s=0.3, stale_after_s=4.0, reconcile_interval_s=1.0, requeue_grace_s=1.0,
                    auth_cache_s=0.0)


@pytest.fixture
def app(settings):
    from services.app import create_app

    return create_app(settings)


@pytest.fixture
def client(app):
    from fastapi.testclient import TestClient

    with TestClient(app) as c:
        c.headers["Authorization"] = f"Bearer {OPERATOR_KEY}"
        yield c


@pytest.fixture
def keys(app):
    """Client keys of two tenants: {'acme': key, 'globex': key}."""
    from services.auth import create_key

    return {t: create_key(app.state.db, t, "client", "test")[0] for t in ("acme", "globex")}


@pytest.fixture(scope="session")
def scene_zip(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("scene")
    return zip_bundle(make_bundle(d / "b"), d / "scene.zip")
