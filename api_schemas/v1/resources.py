"""Scenes, environment maps, API keys, queue and worker status."""

from __future__ import annotations

from datetime import datetime
from enum import Enum

from pydantic import Field

from api_schemas.v1.common import Model


class SceneOut(Model):
    id: str
    name: str
    created_at: datetime
    frames: int
    train_frames: int
    test_frames: int
    cameras: list[str]
    times: int = Field(description="number of time steps")
    objects: int = Field(description="tracked moving objects")
    lidar_sweeps: int
    has_ground_truth: bool
    size_bytes: int = Field(description="size of the uploaded archive")

    model_config = {"json_schema_extra": {"examples": [{
        "id": "3f9c2a7d1e6b4c0a", "name": "street-3", "created_at": "2026-01-01T12:00:00Z", "frames": 20,
        "train_frames": 10, "test_frames": 10, "cameras": ["front"], "times": 10, "objects": 2,
        "lidar_sweeps": 10, "has_ground_truth": True, "size_bytes": 5242880}]}}


class SceneList(Model):
    items: list[SceneOut]
    total: int
    limit: int
    offset: int


class EnvmapOut(Model):
    id: str
    name: str
    format: str = Field(examples=["exr"])
    width: int
    height: int
    size_bytes: int
    created_at: datetime


class EnvmapList(Model):
    items: list[EnvmapOut]


class Scope(str, Enum):
    operator = "operator"
    client = "client"


class ApiKeyCreate(Model):
    tenant: str = Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_.-]+$", examples=["acme"])
    scope: Scope = Scope.client
    name: str = Field("", max_length=128, examples=["acme CI"])


class ApiKeyCreated(Model):
    id: str
    tenant: str
    scope: Scope
    key: str = Field(description="the secret: shown once, stored only as a hash")


class QueueStats(Model):
    name: str
    queued: int
    started: int
    failed: int


class WorkerOut(Model):
    name: str
    state: str
    queues: list[str]
    current_job: str | None
    last_heartbeat: datetime | None
    heartbeat_age_s: float | None


class SystemStatus(Model):
    queues: list[QueueStats]
    workers: list[WorkerOut]
    redis: str
