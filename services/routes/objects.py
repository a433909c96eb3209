"""A scene's objects (``GET /scenes/{id}/objects``) and the up-front check of relight / night
requests against them (:func:`check_scene_request`): an unknown object id, ``attach_to``,
camera, envmap name or an empty frame range is a 422 naming the field and the valid choices
before anything is queued, not a job that fails seconds later.

The scene's manifest is read from this machine's scene cache (the upload warmed it; otherwise the
archive is fetched from the artifact store once) and kept in memory: bundles never change.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import threading
import time
from collections import OrderedDict
from pathlib import Path

from fastapi import APIRouter, HTTPException

import api_schemas as S
from services.auth import Principal
from services.routes.common import E, Ctx, IdPath, P, _err, ok_json

log = logging.getLogger("brdf.gateway")
_CACHE: "OrderedDict[str, dict]" = OrderedDict()
_CACHE_MAX = 64
_LOCK = threading.Lock()


def _scene_root(ctx: Ctx, scene_id: str, key: str, fmt: str) -> Path:
    """The unpacked bundle of a scene in this machine's cache (fetched from the store if absent)."""
    from core.bundle import ArchiveLimits, unpack_bundle

    cache = ctx.settings.data_dir / "cache" / "scenes" / scene_id
    marker = cache / ".complete"
    if marker.is_file():
        return Path(marker.read_text())
    staging = cache.parent / f".{scene_id}.gw.{os.getpid()}.{time.time_ns()}"
    staging.mkdir(parents=True)
    try:
        tmp = staging / f"bundle.{fmt}"
        ctx.store.get_file(key, tmp)
        root = unpack_bundle(tmp, staging / "b", ArchiveLimits(
            max_entries=ctx.settings.archive_max_entries, max_total_bytes=ctx.settings.archive_max_total_bytes))
        tmp.unlink(missing_ok=True)
        rel = root.relative_to(staging)
        try:
            os.replace(staging, cache)
        except OSError:  # cached meanwhile by a worker
            return Path(marker.read_text())
        marker.write_text(str(cache / rel))
        return cache / rel
    finally:
        shutil.rmtree(staging, ignore_errors=True)


def _scene_ref(ctx: Ctx, p: Principal, scene_id: str) -> tuple[str, str, str]:
    """(id, storage key, archive format) of a scene the principal may see; 404 otherwise."""
    with ctx.db.session() as s:
        sc = ctx.get_scene(s, scene_id, p)
        return sc.id, sc.storage_key, sc.archive_format


def scene_info(ctx: Ctx, ref: tuple[str, str, str]) -> dict:
    """``{"manifest", "objects", "street_lights", ...}`` of a scene ``ref`` (:func:`_scene_ref`),
    cached in memory and the lamps beside the scene cache (``<id>.objects.json``)."""
    sid, key, fmt = ref
    with _LOCK:
        if sid in _CACHE:
            _CACHE.move_to_end(sid)
            return _CACHE[sid]
    from core.bundle import open_bundle
    from core.render.objects import describe_objects

    root = _scene_root(ctx, sid, key, fmt)
    b = open_bundle(root, validate=False)
    m = b.manifest
    side = ctx.settings.data_dir / "cache" / "scenes" / f"{sid}.objects.json"
    lamps = None
    if side.is_file():
        try:
            lamps = json.loads(side.read_text())["street_lights"]
        except (OSError, ValueError, KeyError):
            lamps = None
    if lamps is None:
        lamps = []
        if m.lidar:
            import numpy as np

            from core.render.streetlights import detect_poles

            frames = sorted(b.frames("train") or b.frames(None), key=lambda f: f.time_index)
            path = np.array([np.asarray(f.cam_to_world)[:3, 3] for f in frames]) if frames else None
            lamps = [lp.as_dict() for lp in detect_poles(b.load_lidar(), path_xyz=path)]
        try:
            side.write_text(json.dumps({"street_lights": lamps}))
        except OSError as e:
            log.warning("scene %s: objects.json not cached: %s", sid, e)
    info = {"manifest": m, "objects": describe_objects(m), "street_lights": lamps,
            "cameras": sorted(m.cameras), "times_s": [float(t) for t in m.times],
            "frames": {"all": len(m.frames), "train": len(m.split("train")), "test": len(m.split("test"))}}
    with _LOCK:
        _CACHE[sid] = info
        while len(_CACHE) > _CACHE_MAX:
            _CACHE.popitem(last=False)
    return info


def check_scene_request(ctx: Ctx, p: Principal, scene_id: str, body) -> None:
    """422 naming every field of a relight / night ``body`` that refers to something the scene
    does not have (:func:`core.render.scenario.request_problems`); 404 for an unknown scene."""
    from core.render.scenario import request_problems

    info = scene_info(ctx, _scene_ref(ctx, p, scene_id))
    req = body.model_dump(mode="json")
    problems = request_problems(info["manifest"], req)
    for i, e in enumerate(req.get("object_edits") or []):  # inserts copying an object of another scene
        sid = e.get("source_scene_id")
        if e.get("op") != "insert" or sid is None:
            continue
        try:
            other = scene_info(ctx, _scene_ref(ctx, p, sid))
        except HTTPException:
            problems.append(f"object_edits[{i}].source_scene_id: no scene {sid!r}")
            continue
        ids = [o["id"] for o in other["objects"]]
        if e.get("source_object_id") not in ids:
            problems.append(f"object_edits[{i}].source_object_id: no object {e.get('source_object_id')!r} in scene "
                            f"{sid!r} (objects: {ids})")
        from worker.reconstruct import latest_reconstruction

        with ctx.db.session() as s:
            if latest_reconstruction(s, sid) is None:
                problems.append(f"object_edits[{i}].source_scene_id: scene {sid!r} has no finished reconstruction "
                                "to copy the object from")
    if problems:
        raise _err(422, f"the request does not fit scene {scene_id!r} ({len(problems)} problem(s)): {problems[0]}",
                   problems)


def build(ctx: Ctx) -> APIRouter:
    """The routes, bound to the app's context."""
    router = APIRouter()

    @router.get("/scenes/{scene_id}/objects", response_model=S.SceneObjects, tags=["scenes"], responses=E)
    def scene_objects(scene_id: IdPath, p: P):
        """The scene's tracked objects (id, class, box size, parked or moving, a pose per time
        index), its cameras, frames per split and times, and the street lamps detected in its
        LiDAR: what object edits, ``attach_to``, ``vehicle_lights_off``, camera paths and frame
        ranges may refer to."""
        info = scene_info(ctx, _scene_ref(ctx, p, scene_id))
        out = S.SceneObjects(scene_id=scene_id, objects=info["objects"], cameras=info["cameras"],
                             frames=info["frames"], times_s=info["times_s"], street_lights=info["street_lights"])
        return ok_json(out.model_dump(mode="json", by_alias=True))

    return router
