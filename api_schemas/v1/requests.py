"""Render requests: the export render available today, and relight / night / reconstruct.

Units: metres, degrees (the API uses degrees; ``core`` uses radians), linear RGB. Every float is
finite and range-checked here, so a request with an out-of-range light is a 422 naming the
field before anything is queued.
"""

from __future__ import annotations

import math
from enum import Enum
from typing import Annotated, Literal

from pydantic import Field, field_validator, model_validator

from api_schemas.v1.common import Id, Model

Finite = Annotated[float, Field(allow_inf_nan=False)]
Coord = Annotated[float, Field(allow_inf_nan=False, ge=-1e5, le=1e5)]
Vec3 = Annotated[list[Coord], Field(min_length=3, max_length=3)]
Unit = Annotated[float, Field(allow_inf_nan=False, ge=0.0, le=1.0)]
Rgb = Annotated[list[Unit], Field(min_length=3, max_length=3, description="linear RGB, each in [0, 1]")]
Row4 = Annotated[list[Coord], Field(min_length=4, max_length=4)]
Mat4 = Annotated[list[Row4], Field(min_length=4, max_length=4,
                                   description="4x4 rigid transform, row-major, metres")]
Degrees = Annotated[float, Field(allow_inf_nan=False, ge=-360.0, le=360.0)]
Ev = Annotated[float, Field(allow_inf_nan=False, ge=-20.0, le=20.0,
                            description="exposure in stops: the LDR frames are (2^ev HDR)^(1/2.2); "
                                        "the EXR keeps the unscaled HDR")]


class OutputKind(str, Enum):
    exr = "exr"
    mp4 = "mp4"
    png = "png"


Outputs = Annotated[list[OutputKind], Field(min_length=1, max_length=3,
                                            description="which artifacts to produce")]


def _unique_outputs(v: list[OutputKind]) -> list[OutputKind]:
    if len(set(v)) != len(v):
        raise ValueError("outputs: each kind at most once")
    return v


class Denoiser(str, Enum):
    none = "none"
    oidn = "oidn"
    diffusion = "diffusion"


class Quality(Model):
    rays_per_pixel: int = Field(64, ge=1, le=4096, description="environment-light samples per pixel")
    shadow_rays: bool = Field(True, description="trace visibility rays through the Gaussians")
    denoiser: Denoiser = Field(Denoiser.oidn, description="none, oidn (Open Image Denoise) or "
                                                         "diffusion (the generative pass)")
    denoiser_fallback: Literal["none", "oidn"] | None = Field(
        None, description="if the denoiser's model cannot be used (missing, corrupt, wrong contract), "
                          "use this one instead of failing the job; null: fail")


class FrameRange(Model):
    split: Literal["all", "train", "test"] = "all"
    start: int = Field(0, ge=0, le=1_000_000)
    stop: int | None = Field(None, ge=1, le=1_000_000, description="exclusive; default: the last frame")
    step: int = Field(1, ge=1, le=10_000)

    @model_validator(mode="after")
    def _order(self):
        if self.stop is not None and self.stop <= self.start:
            raise ValueError(f"stop ({self.stop}) must be greater than start ({self.start})")
        return self


def _check_rigid(m: list[list[float]], what: str) -> list[list[float]]:
    if [round(x, 6) for x in m[3]] != [0.0, 0.0, 0.0, 1.0]:
        raise ValueError(f"{what}: last row must be [0, 0, 0, 1]")
    r = [row[:3] for row in m[:3]]
    for i in range(3):
        for j in range(3):
            dot = sum(r[k][i] * r[k][j] for k in range(3))
            if abs(dot - (1.0 if i == j else 0.0)) > 1e-3:
                raise ValueError(f"{what}: the rotation part is not orthonormal")
    det = (r[0][0] * (r[1][1] * r[2][2] - r[1][2] * r[2][1]) - r[0][1] * (r[1][0] * r[2][2] - r[1][2] * r[2][0])
           + r[0][2] * (r[1][0] * r[2][1] - r[1][1] * r[2][0]))
    if det < 0:
        raise ValueError(f"{what}: the rotation part is a reflection (determinant < 0)")
    return m


class CameraPose(Model):
    cam_to_world: Mat4 = Field(description="OpenCV camera axes (x right, y down, z forward)")
    time_s: float = Field(0.0, ge=0.0, le=1e6, allow_inf_nan=False,
                          description="scene time of this view (poses the moving objects)")

    @field_validator("cam_to_world")
    @classmethod
    def _rigid(cls, v):
        return _check_rigid(v, "cam_to_world")


class CameraPath(Model):
    """Explicit camera poses (a new path), with a scene camera's intrinsics."""

    camera: str = Field(min_length=1, max_length=64, description="camera id in the scene (intrinsics)")
    poses: list[CameraPose] = Field(min_length=1, max_length=10_000)
    fps: float = Field(10.0, gt=0.0, le=240.0, allow_inf_nan=False)


class CapturedPath(Model):
    """The capture's own camera path, edited: shifted sideways (a lane change) or up, over a time
    range, resampled at a frame rate (poses between captured frames interpolated)."""

    split: Literal["all", "train", "test"] = Field("train", description="whose frames make the path")
    camera: str | None = Field(None, min_length=1, max_length=64, description="default: the split's first camera")
    lateral_shift_m: float = Field(0.0, ge=-100.0, le=100.0, allow_inf_nan=False,
                                   description="metres to the camera's left (negative: right), level with the ground")
    height_shift_m: float = Field(0.0, ge=-100.0, le=100.0, allow_inf_nan=False, description="metres up")
    start_s: float | None = Field(None, ge=0.0, le=1e6, allow_inf_nan=False, description="default: the first frame")
    stop_s: float | None = Field(None, ge=0.0, le=1e6, allow_inf_nan=False, description="inclusive; default: the last")
    fps: float | None = Field(None, gt=0.0, le=240.0, allow_inf_nan=False,
                              description="resample at this rate; default: the captured frames themselves")

    @model_validator(mode="after")
    def _range(self):
        if self.start_s is not None and self.stop_s is not None and self.stop_s < self.start_s:
            raise ValueError(f"stop_s ({self.stop_s}) must not be before start_s ({self.start_s})")
        return self


class LocalLight(Model):
    """A point or spot light added to the scene (street light, headlight, ...)."""

    kind: Literal["point", "spot"]
    position: Vec3 = Field(description="world position, metres (relative to the object when attached)")
    direction: Vec3 | None = Field(None, description="spot axis (need not be unit length; not zero)")
    color: Rgb = Field(default_factory=lambda: [1.0, 1.0, 1.0])
    intensity: float = Field(gt=0.0, le=1e6, allow_inf_nan=False, description="candela")
    cone_inner_deg: float = Field(20.0, ge=0.0, le=90.0, allow_inf_nan=False)
    cone_outer_deg: float = Field(30.0, gt=0.0, le=90.0, allow_inf_nan=False)
    attach_to: str | None = Field(None, min_length=1, max_length=64,
                                  description="id of a tracked object the light moves with")

    @model_validator(mode="after")
    def _spot(self):
        if self.kind == "spot":
            if self.direction is None:
                raise ValueError("direction: required for a spot light")
            if math.sqrt(sum(x * x for x in self.direction)) < 1e-6:
                raise ValueError("direction: must not be the zero vector")
            if self.cone_inner_deg > self.cone_outer_deg:
                raise ValueError(f"cone_inner_deg ({self.cone_inner_deg}) must not exceed "
                                 f"cone_outer_deg ({self.cone_outer_deg})")
        if max(self.color) <= 0.0:
            raise ValueError("color: at least one channel must be > 0")
        return self


class ObjectPose(Model):
    time_index: int = Field(ge=0, le=1_000_000, description="the scene's time index")
    obj_to_world: Mat4 = Field(description="box centre frame (x forward, y left, z up) to world")

    @field_validator("obj_to_world")
    @classmethod
    def _rigid(cls, v):
        return _check_rigid(v, "obj_to_world")


class ObjectEdit(Model):
    """Insert (a copy of a tracked object), move or remove an object of the scene graph (removal
    hides it in every frame). GET /scenes/{id}/objects lists the ids."""

    op: Literal["insert", "move", "remove"]
    object_id: str = Field(min_length=1, max_length=64, description="the object to edit or the new id")
    source_object_id: str | None = Field(None, min_length=1, max_length=64,
                                         description="insert: the tracked object to copy")
    source_scene_id: Id | None = Field(None, description="insert: copy source_object_id from this other scene's "
                                                         "latest reconstruction (an asset: its Gaussians cropped to "
                                                         "its box, materials, box); offset_m is then its world "
                                                         "position here and yaw_deg its heading, or poses its path")
    offset_m: Vec3 = Field(default_factory=lambda: [0.0, 0.0, 0.0], description="translation, metres")
    yaw_deg: Degrees = 0.0
    speed: float = Field(1.0, ge=0.0, le=100.0, allow_inf_nan=False,
                         description="trajectory: cover the path this many times as fast (0: stand at the first pose)")
    lateral_offset_m: float = Field(0.0, ge=-100.0, le=100.0, allow_inf_nan=False,
                                    description="trajectory: metres along the object's own left axis (a lane offset)")
    poses: list[ObjectPose] = Field(default_factory=list, max_length=10_000,
                                    description="trajectory: explicit poses replacing the object's")
    crop_to_box: bool = Field(True, description="keep only the object's Gaussians inside its box (no floaters "
                                                "travel with a moved or inserted object)")
    solid: bool = Field(True, description="fill the moved or inserted object's inside with opaque Gaussians, so it "
                                          "casts a solid shadow (a reconstructed shell is half-transparent to shadow "
                                          "rays)")

    @model_validator(mode="after")
    def _fields(self):
        if self.op == "insert" and not self.source_object_id:
            raise ValueError("source_object_id: required for insert")
        if self.op != "insert" and (self.source_object_id or self.source_scene_id):
            raise ValueError(f"source_object_id, source_scene_id: only allowed for insert, not {self.op}")
        if self.op == "remove" and (self.poses or self.speed != 1.0 or self.lateral_offset_m):
            raise ValueError("poses, speed, lateral_offset_m: not allowed for remove")
        if len({p.time_index for p in self.poses}) != len(self.poses):
            raise ValueError("poses: a time_index appears twice")
        return self


class _Shot(Model):
    frames: FrameRange | None = Field(None, description="render these frames' cameras (default: all)")
    camera_path: CameraPath | None = Field(None, description="or a new camera path (explicit poses)")
    captured_path: CapturedPath | None = Field(None, description="or the captured path shifted, over a time range, "
                                                                 "at a frame rate")
    outputs: Outputs = Field(default_factory=lambda: [OutputKind.exr, OutputKind.mp4, OutputKind.png])
    quality: Quality = Field(default_factory=Quality)

    _uo = field_validator("outputs")(_unique_outputs)

    @model_validator(mode="after")
    def _one_view_source(self):
        if sum(x is not None for x in (self.frames, self.camera_path, self.captured_path)) > 1:
            raise ValueError("give one of frames, camera_path or captured_path")
        return self


class RelightRequest(_Shot):
    """``POST /scenes/{id}/relight``: render the reconstructed scene under another sky."""

    envmap_id: Id | None = Field(None, description="an environment map uploaded with POST /envmaps")
    envmap_name: str | None = Field(None, min_length=1, max_length=64, pattern=r"^[a-z0-9_-]+$",
                                    description="or a bundled HDRI: city, sunset, ...")
    rotation_deg: Degrees = Field(0.0, description="rotate the map about +z (azimuth)")
    exposure_ev: Ev | None = Field(None, description="exposure in stops on top of the capture's; null (default): "
                                                     "automatic, one exposure for the clip from its HDR frames")
    lights: list[LocalLight] = Field(default_factory=list, max_length=256)
    object_edits: list[ObjectEdit] = Field(default_factory=list, max_length=256)

    model_config = {"json_schema_extra": {"examples": [{
        "envmap_id": "9b1d3c2e44f04a5c", "rotation_deg": 45.0, "exposure_ev": -0.5,
        "lights": [{"kind": "spot", "position": [0.5, 0.8, 0.7], "direction": [1, 0, -0.1],
                    "color": [1.0, 0.95, 0.85], "intensity": 2000, "cone_inner_deg": 15,
                    "cone_outer_deg": 25, "attach_to": "car0"}],
        "object_edits": [{"op": "move", "object_id": "car1", "offset_m": [2.0, 0.0, 0.0], "yaw_deg": 10}],
        "frames": {"split": "test", "start": 0, "step": 1},
        "outputs": ["exr", "mp4", "png"],
        "quality": {"rays_per_pixel": 64, "denoiser": "oidn"},
    }]}}

    @model_validator(mode="after")
    def _one_envmap(self):
        if (self.envmap_id is None) == (self.envmap_name is None):
            raise ValueError("give exactly one of envmap_id or envmap_name")
        return self


Pos2or3 = Annotated[list[Coord], Field(min_length=2, max_length=3, description="[x, y] or [x, y, z] metres")]


class NightRequest(_Shot):
    """``POST /scenes/{id}/night``: a night scenario with street lights and vehicle lights."""

    sky_scale: float = Field(0.02, ge=0.0, le=1.0, allow_inf_nan=False,
                             description="multiplier on the scene's environment map")
    street_lights: bool = Field(True, description="street lamps: spots pointing down (the job's stage metrics and "
                                                  "street_lights.json list where they were put)")
    street_light_placement: Literal["detect", "spacing"] = Field(
        "detect", description="detect: lamps on the poles found in the LiDAR (else the reconstruction's Gaussians), "
                              "rows by spacing when none is found; spacing: rows along both sides of the road")
    street_light_positions: list[Pos2or3] | None = Field(
        None, max_length=1000, description="explicit lamp positions instead: [x, y] (6 m above the ground there) "
                                           "or [x, y, z] (the lamp head)")
    street_light_spacing_m: float = Field(25.0, ge=1.0, le=1000.0, allow_inf_nan=False,
                                          description="distance between lamps along the road (placement spacing)")
    street_light_intensity: float = Field(2000.0, gt=0.0, le=1e6, allow_inf_nan=False,
                                          description="candela toward the road (a ~6000 lm LED street lamp)")
    headlights: bool = Field(True, description="vehicle lights: two headlights and two red tail lights on every "
                                               "vehicle, following it")
    headlight_intensity: float = Field(3000.0, gt=0.0, le=1e6, allow_inf_nan=False, description="candela")
    tail_lights: bool = True
    vehicle_lights_off: list[Annotated[str, Field(min_length=1, max_length=64)]] = Field(
        default_factory=list, max_length=256, description="object ids whose vehicle lights are off")
    lights: list[LocalLight] = Field(default_factory=list, max_length=256)
    object_edits: list[ObjectEdit] = Field(default_factory=list, max_length=256)
    exposure_ev: Ev | None = Field(None, description="exposure in stops on top of the capture's; null (default): "
                                                     "automatic, one exposure for the clip from its HDR frames")

    model_config = {"json_schema_extra": {"examples": [{
        "sky_scale": 0.02, "street_lights": True, "street_light_placement": "detect", "headlights": True,
        "vehicle_lights_off": ["car0"], "frames": {"split": "test"}, "outputs": ["mp4", "png"],
    }]}}


class ReconstructRequest(Model):
    """``POST /scenes/{id}/reconstruct``: the chain of optimization stages (each its own job)."""

    profile: Literal["tiny", "quick", "benchmark", "paper"] = "quick"
    stages: list[Literal["volume", "generative_refine", "volume2", "pbr", "joint", "corrector"]] = Field(
        default_factory=lambda: ["volume", "generative_refine", "volume2", "pbr", "joint", "corrector"], min_length=1,
        max_length=6,
        description="Stages to run, each its own job, in chain order: volume -> generative_refine -> volume2 -> "
                    "pbr -> joint (the paper's chain) -> corrector (a per-scene corrector of the PBR pass fitted "
                    "on the capture and applied only under the capture's light; not the paper's); default all six. A stage needs the "
                    "stages it reads in the same "
                    "request (409 otherwise).")
    iterations_scale: float = Field(1.0, gt=0.0, le=100.0, allow_inf_nan=False)

    model_config = {"json_schema_extra": {"examples": [{"profile": "quick"}]}}


class RenderRequest(Model):
    """``POST /scenes/{id}/render``: export the scene's captured frames (linearised from the
    stored LDR images, never the ground truth of a generated scene) as EXR, MP4 and a PNG preview.
    The reconstruct-then-relight pipeline renders into the same layout."""

    split: Literal["all", "train", "test"] = "all"
    fps: float = Field(10.0, gt=0.0, le=240.0, allow_inf_nan=False)
    outputs: Outputs = Field(default_factory=lambda: [OutputKind.exr, OutputKind.mp4, OutputKind.png])

    _uo = field_validator("outputs")(_unique_outputs)

    model_config = {"json_schema_extra": {"examples": [{"split": "test", "fps": 10, "outputs": ["exr", "mp4", "png"]}]}}
