"""Shared building blocks: errors, health."""

from __future__ import annotations

from typing import Annotated

from pydantic import BaseModel, ConfigDict, Field

Id = Annotated[str, Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_-]+$",
                          examples=["3f9c2a7d1e6b4c0a"])]


class Model(BaseModel):
    """Strict base: unknown fields are an error (a typo in a request is a 422, never ignored)."""

    model_config = ConfigDict(extra="forbid")


class ErrorOut(Model):
    """Every 4xx/5xx body: one line naming what is wrong; ``errors`` lists each problem when
    there are several (e.g. every issue of an invalid scene bundle)."""

    detail: str = Field(description="What is wrong, naming the field or file.")
    errors: list[str] = Field(default_factory=list, description="Each problem, when there are several.")

    model_config = ConfigDict(json_schema_extra={"examples": [
        {"detail": "scene bundle is invalid (2 problems)",
         "errors": ["images/f000.png: missing file", "bundle.json [frames[1].cam_to_world]: not a rigid transform"]},
    ]})


class Health(Model):
    status: str = Field("ok", examples=["ok"])
    version: str = Field(examples=["0.1.0"])


class Ready(Model):
    ready: bool
    checks: dict[str, str] = Field(description="Each dependency: 'ok' or what failed.",
                                   examples=[{"database": "ok", "redis": "ok", "artifact_store": "ok"}])
