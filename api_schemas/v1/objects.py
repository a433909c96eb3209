"""``GET /scenes/{id}/objects``: what a scene holds for edits and lights to refer to."""

from __future__ import annotations

from pydantic import Field

from api_schemas.v1.common import Model


class ObjectPoseOut(Model):
    time_index: int
    time_s: float | None = Field(description="scene seconds of the time index")
    obj_to_world: list[list[float]] = Field(description="4x4 row-major: box centre frame (x forward, y left, z up) "
                                                        "to world, metres")


class ObjectOut(Model):
    id: str = Field(description="the id edits, attach_to and vehicle_lights_off refer to")
    class_: str = Field(alias="class", description="the tracked class (car, truck, ...)")
    size: list[float] = Field(description="box length, width, height, metres")
    moving: bool = Field(description="false: parked (the box never moves)")
    vehicle: bool = Field(description="carries headlights and tail lights at night")
    path_length_m: float
    time_indices: list[int]
    poses: list[ObjectPoseOut] = Field(description="one per time index the object was tracked")

    model_config = {"populate_by_name": True, "extra": "forbid"}


class StreetLampOut(Model):
    position: list[float] = Field(description="lamp head, world metres")
    source: str = Field(description="detected (a pole in the LiDAR)")
    pole_base: list[float] | None = None


class SceneObjects(Model):
    """The scene's tracked objects, cameras, frames and times, and the street lamps detected in its
    LiDAR (the ones a night request with ``street_light_placement: detect`` lights)."""

    scene_id: str
    objects: list[ObjectOut]
    cameras: list[str]
    frames: dict[str, int] = Field(description="frames per split: all, train, test")
    times_s: list[float]
    street_lights: list[StreetLampOut]
