"""Deployment settings of the rendering service, read from the environment (prefix ``BRDF_``).

One object configures the gateway, the workers and the CLI. Every field can be set as an
environment variable, e.g. ``BRDF_DATABASE_URL=postgresql+psycopg://brdf@db/brdf``,
``BRDF_REDIS_URL=redis://redis:6379/0``, ``BRDF_ARTIFACT_STORE=s3://bucket/brdf``.
"""

from __future__ import annotations

import json
from functools import lru_cache
from pathlib import Path
from typing import Any

from pydantic import Field, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

REPO_ROOT = Path(__file__).resolve().parents[1]
QUEUE_TRAIN = "train"
QUEUE_RENDER = "render"
QUEUES = (QUEUE_RENDER, QUEUE_TRAIN)


class Settings(BaseSettings):
    model_config = SettingsConfigDict(env_prefix="BRDF_", extra="ignore")

    data_dir: Path = Field(REPO_ROOT / "outputs" / "service",
                           description="Local working directory: the default SQLite database, the "
                                       "local artifact store, upload staging and the scene cache.")
    database_url: str | None = Field(None, description="SQLAlchemy URL; default sqlite:///<data_dir>/brdf.db. "
                                                       "PostgreSQL: postgresql+psycopg://user@host/db")
    redis_url: str = Field("redis://127.0.0.1:6379/0", description="Redis holding the RQ queues.")
    artifact_store: str | None = Field(None, description="fsspec URL of the artifact store; default "
                                                         "file://<data_dir>/artifacts. s3://bucket/prefix "
                                                         "(needs s3fs) for several machines.")
    artifact_store_options: dict[str, Any] = Field(default_factory=dict,
                                                   description="JSON: keyword options for the fsspec "
                                                               "filesystem (endpoint_url, key, ...).")
    max_upload_bytes: int = Field(2 * 1024**3, ge=1, description="Largest scene upload accepted.")
    max_envmap_bytes: int = Field(256 * 1024**2, ge=1, description="Largest environment map upload.")
    archive_max_entries: int = Field(100_000, ge=1)
    archive_max_total_bytes: int = Field(8 * 1024**3, ge=1)
    max_request_json_bytes: int = Field(1024**2, ge=1)

    render_job_timeout_s: int = Field(6 * 3600, ge=1, description="RQ job_timeout of render jobs.")
    train_job_timeout_s: int = Field(48 * 3600, ge=1, description="RQ job_timeout of training stages.")
    result_ttl_s: int = Field(7 * 86400, ge=1, description="How long RQ keeps a finished job's result.")
    failure_ttl_s: int = Field(30 * 86400, ge=1, description="How long RQ keeps a failed job.")
    max_attempts: int = Field(3, ge=1, le=20, description="Tries per job (retries + 1).")
    heartbeat_s: float = Field(2.0, gt=0, description="How often a running job writes its heartbeat.")
    stale_after_s: float = Field(60.0, gt=0, description="A running job whose heartbeat is older is "
                                                           "considered lost (worker died) and retried.")
    reconcile_interval_s: float = Field(15.0, gt=0, description="How often the gateway re-enqueues "
                                                                  "accepted jobs missing from Redis.")
    requeue_grace_s: float = Field(5.0, ge=0, description="A queued job younger than this is never "
                                                          "re-enqueued (its enqueue may be in flight).")
    failed_artifact_ttl_s: float = Field(7 * 86400, ge=0, description="Artifacts of failed or canceled jobs "
                                                                       "(e.g. finished stages of a chain that "
                                                                       "failed later) are deleted this long after "
                                                                       "the job ended.")
    janitor_interval_s: float = Field(60.0, gt=0, description="How often the gateway removes expired artifacts "
                                                                "of failed jobs and dead attempts' work dirs.")
    worker_ttl_s: int = Field(30, ge=16, description="RQ worker TTL: an idle worker refreshes its registration "
                                                       "every worker_ttl_s - 15 s.")
    worker_stale_s: float = Field(60.0, gt=0, description="A worker whose RQ heartbeat is older does not count "
                                                            "as live (readiness, metrics).")
    restart_backoff_max_s: float = Field(30.0, gt=0, description="brdf up: longest wait before restarting a "
                                                                   "worker that keeps exiting.")
    bootstrap_operator_key: str | None = Field(None, description="If set, this operator API key is "
                                                                 "registered (hashed) at startup.")
    auth_cache_s: float = Field(10.0, ge=0, description="How long a verified API key is cached.")
    session_ttl_s: int = Field(12 * 3600, ge=60, description="Dashboard login lifetime.")
    cookie_secure: bool = Field(False, description="Mark the dashboard cookie Secure (behind HTTPS).")

    @field_validator("artifact_store_options", mode="before")
    @classmethod
    def _json_options(cls, v):
        if isinstance(v, str):
            try:
                v = json.loads(v) if v.strip() else {}
            except json.JSONDecodeError as e:
                raise ValueError(f"BRDF_ARTIFACT_STORE_OPTIONS: not valid JSON: {e}") from None
        return v

    @property
    def db_url(self) -> str:
        return self.database_url or f"sqlite:///{(self.data_dir / 'brdf.db').resolve()}"

    @property
    def store_url(self) -> str:
        return self.artifact_store or (self.data_dir / "artifacts").resolve().as_uri()

    def job_timeout(self, queue: str) -> int:
        return self.train_job_timeout_s if queue == QUEUE_TRAIN else self.render_job_timeout_s


_current: Settings | None = None


def configure(settings: Settings | None) -> None:
    """Make ``settings`` what :func:`get_settings` returns in this process (the worker entry
    point passes its settings to the job functions this way; None goes back to the environment)."""
    global _current
    _current = settings
    _from_env.cache_clear()


@lru_cache(maxsize=1)
def _from_env() -> Settings:
    return Settings()


def get_settings() -> Settings:
    return _current if _current is not None else _from_env()
