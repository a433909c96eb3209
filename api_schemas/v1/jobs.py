"""Job status and artifact listings."""

from __future__ import annotations

from datetime import datetime
from enum import Enum

from pydantic import Field

from api_schemas.v1.common import Model


class JobState(str, Enum):
    queued = "queued"
    running = "running"
    done = "done"
    failed = "failed"
    canceled = "canceled"

    @property
    def final(self) -> bool:
        return self in (JobState.done, JobState.failed, JobState.canceled)


class StageOut(Model):
    name: str = Field(examples=["export"])
    state: JobState
    progress: float = Field(ge=0.0, le=1.0)
    started_at: datetime | None = None
    finished_at: datetime | None = None
    metrics: dict[str, list[float] | float | str | bool | None] = Field(
        default_factory=dict, description="per-stage curves (e.g. the loss by iteration) and figures (e.g. "
                                          "test_psnr, seconds)")


class AttemptOut(Model):
    """One attempt of a job: a retry is a new attempt, and ``reason`` says why the previous one
    ended (e.g. its work horse was killed)."""

    attempt: int = Field(ge=1)
    outcome: str = Field(description="queued, running, done, failed, canceled or retried",
                         examples=["retried"])
    reason: str | None = Field(None, description="why the attempt ended (retried or failed ones)")
    worker: str | None = None
    queued_at: datetime | None = None
    started_at: datetime | None = None
    finished_at: datetime | None = None


class Timings(Model):
    created_at: datetime
    started_at: datetime | None = None
    finished_at: datetime | None = None
    queued_s: float | None = Field(None, description="time spent waiting for a worker: the sum of the attempts' "
                                                     "waits (a dead attempt's run time is not counted)")
    run_s: float | None = Field(None, description="time the last attempt ran (so far)")


class JobOut(Model):
    id: str
    type: str = Field(examples=["render"])
    scene_id: str | None
    state: JobState
    stage: str | None = Field(None, description="the stage running now (or the last one)")
    progress: float = Field(ge=0.0, le=1.0)
    eta_s: float | None = Field(None, description="estimated seconds left, from the progress rate")
    attempts: int = Field(description="how many times the job has been started or queued for a retry")
    max_attempts: int
    error: str | None = Field(None, description="why the job failed (last attempt)")
    timings: Timings
    stages: list[StageOut] = Field(default_factory=list)
    attempt_history: list[AttemptOut] = Field(default_factory=list, description="every attempt, oldest first")
    params: dict = Field(default_factory=dict, description="the validated request")
    artifacts_url: str

    model_config = {"json_schema_extra": {"examples": [{
        "id": "5b0c6f3e2a9d4e1f", "type": "render", "scene_id": "3f9c2a7d1e6b4c0a", "state": "running",
        "stage": "export", "progress": 0.4, "eta_s": 3.2, "attempts": 1, "max_attempts": 3, "error": None,
        "timings": {"created_at": "2026-01-01T12:00:00Z", "started_at": "2026-01-01T12:00:01Z",
                    "finished_at": None, "queued_s": 1.0, "run_s": 2.1},
        "stages": [{"name": "export", "state": "running", "progress": 0.4, "metrics": {}}],
        "params": {"split": "all", "fps": 10.0, "outputs": ["exr", "mp4", "png"]},
        "artifacts_url": "/jobs/5b0c6f3e2a9d4e1f/artifacts"}]}}


class JobList(Model):
    items: list[JobOut]
    total: int
    limit: int
    offset: int


class JobAccepted(Model):
    """202 body of every job submission; ``Location`` points at ``status_url``."""

    id: str
    state: JobState
    status_url: str
    model_config = {"json_schema_extra": {"examples": [
        {"id": "5b0c6f3e2a9d4e1f", "state": "queued", "status_url": "/jobs/5b0c6f3e2a9d4e1f"}]}}


class ArtifactOut(Model):
    name: str = Field(description="path inside the job's output, e.g. frames/f000.exr",
                      examples=["frames/test_000.exr"])
    kind: str = Field(examples=["exr"])
    content_type: str = Field(examples=["image/x-exr"])
    size_bytes: int
    url: str


class ArtifactList(Model):
    job_id: str
    items: list[ArtifactOut]
