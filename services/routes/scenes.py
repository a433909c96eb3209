"""Scene upload (a bundle archive streamed to disk, unpacked safely and validated), listing and metadata."""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Annotated

from fastapi import APIRouter, Query, Request
from sqlalchemy import select
from sqlalchemy.exc import IntegrityError

import api_schemas as S
from core.bundle import ArchiveLimits, open_bundle, unpack_bundle, validate_bundle
from core.bundle.archive import archive_kind
from core.errors import CoreError
from services.auth import Principal
from services.db import IdempotencyKey
from services.routes.common import (SCENE_TYPES, Ctx, E, IdemKey, IdPath, P, _err, _fingerprint, binary_body,
                                    created, ok, page_total, receive_upload, require_content_type, route_context,
                                    scene_out)
from worker.db import Scene, new_id

log = logging.getLogger("brdf.gateway")


def build(ctx: Ctx) -> APIRouter:
    """The routes, bound to the app's context (settings, database, store, Redis)."""
    router, settings, db, store = route_context(ctx)
    idem_lookup = ctx.idem_lookup

    def ingest_scene(upload: Path, work: Path, size: int, digest: str, name: str | None, p: Principal,
                     idem: str | None) -> tuple[Scene, bool]:
        def clean(msg: str) -> str:
            return msg.replace(str(work / "bundle") + "/", "").replace(str(work / "bundle"), "bundle") \
                      .replace(str(upload), "upload")

        fp = _fingerprint("scene", digest, name)
        with db.session() as s:
            existing = idem_lookup(s, p, idem, fp, "scene")
            if existing:
                return s.get(Scene, existing), True
        try:
            kind = archive_kind(upload)
            root = unpack_bundle(upload, work / "bundle", ArchiveLimits(
                max_entries=settings.archive_max_entries, max_total_bytes=settings.archive_max_total_bytes))
            issues = validate_bundle(root)
            if issues:
                raise _err(422, f"scene bundle is invalid ({len(issues)} problem(s)): {clean(str(issues[0]))}",
                           [clean(str(i)) for i in issues])
            b = open_bundle(root, validate=False)
        except CoreError as e:
            raise _err(422, f"scene bundle rejected: {clean(str(e))}") from None
        m = b.manifest
        sid = new_id()
        key = f"scenes/{sid}/bundle.{'zip' if kind == 'zip' else 'tar.gz'}"
        store.put_file(upload, key)
        row = Scene(id=sid, tenant=p.tenant, name=(name or m.name)[:256], storage_key=key, archive_format=kind,
                    size_bytes=size, frames=len(m.frames), train_frames=len(m.split("train")),
                    test_frames=len(m.split("test")), cameras=sorted(m.cameras), times=len(m.times),
                    objects=len(m.objects), lidar_sweeps=len(m.lidar), has_ground_truth=m.ground_truth is not None)
        try:
            with db.session() as s:
                s.add(row)
                if idem:
                    s.add(IdempotencyKey(tenant=p.tenant, key=idem, request_hash=fp, resource="scene", resource_id=sid))
        except IntegrityError:
            store.delete_prefix(f"scenes/{sid}")
            with db.session() as s:
                existing = idem_lookup(s, p, idem, fp, "scene")
                if existing:
                    return s.get(Scene, existing), True
            raise
        except BaseException:
            store.delete_prefix(f"scenes/{sid}")
            raise
        # warm this machine's scene cache (workers elsewhere fetch the archive from the store)
        cache = settings.data_dir / "cache" / "scenes" / sid
        try:
            cache.parent.mkdir(parents=True, exist_ok=True)
            os.replace(work / "bundle", cache)
            (cache / ".complete").write_text(str(cache / root.relative_to(work / "bundle")))
        except OSError as e:
            log.warning("scene %s: cache not warmed: %s", sid, e)
        return row, False

    @router.post("/scenes", response_model=S.SceneOut, status_code=201, tags=["scenes"], responses=E,
              openapi_extra=binary_body("a scene bundle as .zip or .tar.gz", "application/zip", "application/gzip"))
    async def upload_scene(request: Request, p: P, idem: IdemKey = None,
                           name: Annotated[str | None, Query(min_length=1, max_length=256)] = None):
        """Upload a scene bundle (the raw .zip / .tar.gz as the body). Streamed to disk under the
        upload limit, unpacked with zip-slip / symlink / zip-bomb protection, validated; nothing is
        stored unless all of it is valid."""
        require_content_type(request, SCENE_TYPES, "the bundle as application/zip or application/gzip (.tar.gz)")
        row, replay = await receive_upload(
            request, settings.data_dir, settings.max_upload_bytes, "scene upload",
            lambda upload, work, size, digest: ingest_scene(upload, work, size, digest, name, p, idem))
        return created(scene_out(row), replay, f"/scenes/{row.id}")

    scenes_t = Scene.__table__

    # The status and listing routes (the hot path: clients poll them) are ``async def`` and run
    # their short indexed reads on the event loop: no thread hand-off per request, which on a
    # CPU-starved machine measured 20-30% less gateway CPU and a lower p99 (benchmarks/bench_load.py).
    # Everything that writes, uploads or may be slow stays ``def`` (thread pool) or awaits a thread.

    @router.get("/scenes", response_model=S.SceneList, tags=["scenes"], responses=E)
    async def list_scenes(p: P, limit: Annotated[int, Query(ge=1, le=500)] = 50,
                          offset: Annotated[int, Query(ge=0, le=10**9)] = 0):
        with db.read() as c:
            q = select(scenes_t) if p.operator else select(scenes_t).where(scenes_t.c.tenant == p.tenant)
            rows = c.execute(q.order_by(scenes_t.c.created_at.desc(), scenes_t.c.id).limit(limit).offset(offset)).all()
            total = page_total(c, q, len(rows), limit, offset)
        return ok(S.SceneList(items=[scene_out(r) for r in rows], total=total, limit=limit, offset=offset))

    @router.get("/scenes/{scene_id}", response_model=S.SceneOut, tags=["scenes"], responses=E)
    async def read_scene(scene_id: IdPath, p: P):
        q = select(scenes_t).where(scenes_t.c.id == scene_id)
        with db.read() as c:
            row = c.execute(q if p.operator else q.where(scenes_t.c.tenant == p.tenant)).first()
        if row is None:
            raise _err(404, f"scene {scene_id!r} not found")
        return ok(scene_out(row))

    return router
