"""Version 1 of the BRDFusion service schemas."""

from api_schemas.v1.common import ErrorOut, Health, Ready
from api_schemas.v1.jobs import (
    ArtifactList, ArtifactOut, JobAccepted, JobList, JobOut, JobState, StageOut, Timings,
)
from api_schemas.v1.requests import (
    CameraPath, CameraPose, Denoiser, FrameRange, LocalLight, NightRequest, ObjectEdit, OutputKind,
    Quality, ReconstructRequest, RelightRequest, RenderRequest,
)
from api_schemas.v1.resources import (
    ApiKeyCreate, ApiKeyCreated, EnvmapList, EnvmapOut, QueueStats, SceneList, SceneOut, Scope,
    SystemStatus, WorkerOut,
)

SCHEMA_VERSION = 1

__all__ = [
    "ApiKeyCreate", "ApiKeyCreated", "ArtifactList", "ArtifactOut", "CameraPath", "CameraPose",
    "Denoiser", "EnvmapList", "EnvmapOut", "ErrorOut", "FrameRange", "Health", "JobAccepted",
    "JobList", "JobOut", "JobState", "LocalLight", "NightRequest", "ObjectEdit", "OutputKind",
    "Quality", "QueueStats", "Ready", "ReconstructRequest", "RelightRequest", "RenderRequest",
    "SCHEMA_VERSION", "SceneList", "SceneOut", "Scope", "StageOut", "SystemStatus", "Timings",
    "WorkerOut",
]
