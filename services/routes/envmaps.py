"""Environment map upload (.exr / .hdr, NaN/Inf rejected), listing and metadata."""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Annotated

from fastapi import APIRouter, Query, Request
from sqlalchemy import select

import api_schemas as S
from core.errors import CoreError
from core.io import exr_header, read_envmap
from services.auth import Principal
from services.db import IdempotencyKey
from services.routes.common import (ENVMAP_TYPES, Ctx, E, IdemKey, IdPath, P, _err, _fingerprint, binary_body,
                                    created, envmap_out, receive_upload, require_content_type, route_context, visible)
from worker.db import Envmap, new_id

log = logging.getLogger("brdf.gateway")


def build(ctx: Ctx) -> APIRouter:
    """The routes, bound to the app's context (settings, database, store, Redis)."""
    router, settings, db, store = route_context(ctx)
    idem_lookup = ctx.idem_lookup

    # --- environment maps ---------------------------------------------------------------------
    def ingest_envmap(upload: Path, size: int, digest: str, name: str, p: Principal, idem: str | None):
        fp = _fingerprint("envmap", digest, name)
        with db.session() as s:
            existing = idem_lookup(s, p, idem, fp, "envmap")
            if existing:
                return s.get(Envmap, existing), True
        with open(upload, "rb") as fh:
            head = fh.read(16)
        if head[:4] == b"\x76\x2f\x31\x01":
            fmt = "exr"
        elif head[:2] == b"#?":
            fmt = "hdr"
        else:
            raise _err(415, "not an OpenEXR or Radiance .hdr file (unknown magic bytes)")
        path = upload.with_suffix("." + fmt)
        os.replace(upload, path)
        try:
            if fmt == "exr":
                exr_header(path)
            rgb = read_envmap(path)
        except CoreError as e:
            raise _err(422, f"environment map rejected: {str(e).replace(str(path), 'upload')}") from None
        eid = new_id()
        key = f"envmaps/{eid}.{fmt}"
        store.put_file(path, key)
        row = Envmap(id=eid, tenant=p.tenant, name=name, format=fmt, width=int(rgb.shape[1]),
                     height=int(rgb.shape[0]), size_bytes=size, storage_key=key)
        try:
            with db.session() as s:
                s.add(row)
                if idem:
                    s.add(IdempotencyKey(tenant=p.tenant, key=idem, request_hash=fp, resource="envmap",
                                         resource_id=eid))
        except BaseException:
            store.delete_prefix(key)
            raise
        return row, False

    @router.post("/envmaps", response_model=S.EnvmapOut, status_code=201, tags=["envmaps"], responses=E,
              openapi_extra=binary_body("an equirectangular map, .exr or .hdr", "image/x-exr", "image/vnd.radiance"))
    async def upload_envmap(request: Request, p: P, idem: IdemKey = None,
                            name: Annotated[str, Query(min_length=1, max_length=256)] = "envmap"):
        """Upload an HDR environment map (W = 2 H; finite, non-negative values)."""
        require_content_type(request, ENVMAP_TYPES, "image/x-exr or image/vnd.radiance")
        row, replay = await receive_upload(
            request, settings.data_dir, settings.max_envmap_bytes, "environment map",
            lambda upload, work, size, digest: ingest_envmap(upload, size, digest, name, p, idem))
        return created(envmap_out(row), replay, f"/envmaps/{row.id}")

    @router.get("/envmaps", response_model=S.EnvmapList, tags=["envmaps"], responses=E)
    def list_envmaps(p: P):
        with db.session() as s:
            rows = s.scalars(visible(select(Envmap), Envmap, p).order_by(Envmap.created_at.desc()).limit(500)).all()
            return S.EnvmapList(items=[envmap_out(r) for r in rows])

    @router.get("/envmaps/{envmap_id}", response_model=S.EnvmapOut, tags=["envmaps"], responses=E)
    def read_envmap_meta(envmap_id: IdPath, p: P):
        with db.session() as s:
            e = s.scalar(visible(select(Envmap).where(Envmap.id == envmap_id), Envmap, p))
            if e is None:
                raise _err(404, f"envmap {envmap_id!r} not found")
            return envmap_out(e)

    return router
