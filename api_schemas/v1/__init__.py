"""Version 1 of the BRDFusion service schemas."""

from api_schemas.v1.common import ErrorOut, Health, Ready
from api_schemas.v1.jobs import (
    ArtifactList, ArtifactOut, AttemptOut, JobAccepted, JobList, JobOut, JobState, StageOut, Timings,
)
from api_schemas.v1.objects import ObjectOut, ObjectPoseOut, SceneObjects, StreetLampOut
from api_schemas.v1.requests import (
    CameraPath, CameraPose, CapturedPath, Denoiser, FrameRange, LocalLight, NightRequest, ObjectEdit, ObjectPose,
    OutputKind, Quality, ReconstructRequest, RelightRequest, RenderRequest,
)
from api_schemas.v1.resources import (
    ApiKeyCreate, ApiKeyCreated, EnvmapList, EnvmapOut, QueueStats, SceneList, SceneOut, Scope,
    SystemStatus, WorkerOut,
)

SCHEMA_VERSION = 1

__all__ = [
    "ApiKeyCreate", "ApiKeyCreated", "ArtifactList", "ArtifactOut", "AttemptOut", "CameraPath", "CameraPose",
    "CapturedPath", "Denoiser", "EnvmapList", "EnvmapOut", "ErrorOut", "FrameRange", "Health", "JobAccepted",
    "JobList", "JobOut", "JobState", "LocalLight", "NightRequest", "ObjectEdit", "ObjectOut", "ObjectPose",
    "ObjectPoseOut", "OutputKind", "Quality", "QueueStats", "Ready", "ReconstructRequest", "RelightRequest",
    "RenderRequest", "SCHEMA_VERSION", "SceneList", "SceneObjects", "SceneOut", "Scope", "StageOut",
    "StreetLampOut", "SystemStatus", "Timings", "WorkerOut",
]
