"""Relighting a reconstructed scene: object edits on its scene graph, and a clip rendered by the
PBR pass under a new environment map and local lights, written as multi-layer EXR frames, an MP4
and a PNG preview (the library side of the service's ``relight`` and ``night`` jobs).

Frames: cameras are OpenCV (``core.pbr.render.Camera``), times in seconds of the scene graph.
Outputs in ``out_dir``: ``frames/<name>.exr`` (HDR beauty ``rgb`` and ``Lr`` in float32, the
G-buffers; see :func:`core.pbr.render.write_frame_exr`), ``relit.mp4`` (the LDR frames after the
denoiser) and ``preview.png`` (the middle frame). The EXR beauty is the PBR pass's estimate before
denoising; the denoiser (``none`` / ``oidn`` / ``diffusion``, :func:`core.gen.denoise.denoise`)
works on the LDR clip with the albedo and normal G-buffers as guides.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import torch

from core.errors import ConfigError
from core.pbr.envmap import EnvironmentMap
from core.pbr.render import Camera, ClipRenderer, PBRSettings, write_frame_exr

OUTPUT_KINDS = ("exr", "mp4", "png")


@dataclass(frozen=True)
class View:
    """One frame to render: an OpenCV camera, the scene time (seconds) and a file stem."""

    camera: Camera
    time_s: float
    name: str


@dataclass(frozen=True)
class ObjectEdit:
    """Insert a copy of a node, move or remove a node. ``offset_m``: world translation (metres)
    applied after the node's own pose; ``yaw_deg``: rotation about the node's up axis (+z of the
    node frame), degrees."""

    op: str
    object_id: str
    source_object_id: str | None = None
    offset_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    yaw_deg: float = 0.0


@dataclass
class RelightResult:
    """Paths written and what the clip cost."""

    exr_files: list[Path] = field(default_factory=list)
    video: Path | None = None
    preview: Path | None = None
    seconds_per_frame: float = 0.0
    denoiser: str = "none"
    denoiser_note: str | None = None
    frames: np.ndarray | None = None
    """[T, H, W, 3] the denoised LDR clip in [0, 1] (when mp4 or png was asked for)."""


def _edit_pose(poses: torch.Tensor, offset, yaw_deg: float) -> torch.Tensor:
    """``T(offset) @ pose @ Rz(yaw)`` for every keyframe pose ``[K, 4, 4]``."""
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    rz = torch.eye(4, dtype=poses.dtype)
    rz[0, 0], rz[0, 1], rz[1, 0], rz[1, 1] = c, -s, s, c
    out = poses @ rz
    out[:, :3, 3] = out[:, :3, 3] + torch.as_tensor(offset, dtype=poses.dtype)
    return out


def apply_edits(graph, edits: Sequence[ObjectEdit], what: str = "edits"):
    """A new :class:`core.scene_graph.SceneGraph` with ``edits`` applied in order (the input is
    not modified). Raises ConfigError naming the edit (``<what>[i]``) that refers to an unknown
    node or inserts an existing id."""
    from core.scene_graph import RigidNode, SceneGraph

    nodes = list(graph.nodes)
    for i, e in enumerate(edits):
        names = [n.name for n in nodes]
        if e.op == "remove":
            if e.object_id not in names:
                raise ConfigError(f"{what}[{i}].object_id: no object {e.object_id!r} in the scene (objects: {names})")
            nodes = [n for n in nodes if n.name != e.object_id]
        elif e.op == "move":
            if e.object_id not in names:
                raise ConfigError(f"{what}[{i}].object_id: no object {e.object_id!r} in the scene (objects: {names})")
            nodes = [replace(n, poses=_edit_pose(n.poses.detach(), e.offset_m, e.yaw_deg), pose_delta_trans=None,
                             pose_delta_rot=None) if n.name == e.object_id else n for n in nodes]
        elif e.op == "insert":
            if e.object_id in names:
                raise ConfigError(f"{what}[{i}].object_id: {e.object_id!r} already exists; pick a new id")
            if e.source_object_id not in names:
                raise ConfigError(f"{what}[{i}].source_object_id: no object {e.source_object_id!r} in the scene "
                                  f"(objects: {names})")
            src = next(n for n in nodes if n.name == e.source_object_id)
            nodes.append(RigidNode(e.object_id, src.cls, src.gaussians.detach(), src.time_indices.clone(),
                                   _edit_pose(src.poses.detach(), e.offset_m, e.yaw_deg)))
        else:
            raise ConfigError(f"{what}[{i}].op: must be insert, move or remove, got {e.op!r}")
    return SceneGraph(graph.background, nodes, graph.times)


def render_clip(scene, env: EnvironmentMap, views: Sequence[View], out_dir: str | Path, *,
                settings: PBRSettings | None = None, lights=(), outputs: Sequence[str] = OUTPUT_KINDS,
                denoiser: str = "none", denoiser_fallback: str | None = None, fps: float = 10.0,
                on_frame: Callable[[int, int], None] | None = None) -> RelightResult:
    """Render ``views`` of ``scene`` (a SceneGraph or Gaussians) lit by ``env`` and ``lights``
    with the PBR pass (reuse across the clip: static BVH once, visibility cache when
    ``settings.reuse_visibility``), denoise the LDR clip, and write the outputs (module
    docstring). ``on_frame(done, total)`` is called after each frame (progress, cancel checks).
    Raises ConfigError for an empty view list, unknown outputs or a bad fps."""
    from core.gen.denoise import denoise
    from core.io.images import write_png
    from core.io.video import write_mp4
    from core.tonemap import ldr_to_uint8

    if not views:
        raise ConfigError("views: at least one view is needed")
    bad = [o for o in outputs if o not in OUTPUT_KINDS]
    if bad or not outputs:
        raise ConfigError(f"outputs: each must be one of {OUTPUT_KINDS}, got {list(outputs)}")
    if not (isinstance(fps, (int, float)) and math.isfinite(fps) and 0 < fps <= 240):
        raise ConfigError(f"fps: must be in (0, 240], got {fps!r}")
    s = settings or PBRSettings()
    out = Path(out_dir)
    (out / "frames").mkdir(parents=True, exist_ok=True)
    renderer = ClipRenderer(scene, env, s, lights=list(lights))
    res = RelightResult(denoiser=denoiser)
    ldr, albedo, normal = [], [], []
    extra: dict[str, list] = {"depth": [], "roughness": [], "metallic": []}
    c2w = []
    t0 = time.perf_counter()
    for i, v in enumerate(views):
        r = renderer.render(v.camera, time_s=v.time_s, frame_index=i)
        if "exr" in outputs:
            p = out / "frames" / f"{v.name}.exr"
            write_frame_exr(p, r)
            res.exr_files.append(p)
        ldr.append(r.ldr.detach().to(torch.float32).numpy())
        albedo.append(r.gbuffers["albedo"].detach().to(torch.float32).numpy())
        normal.append(r.gbuffers["normal"].detach().to(torch.float32).numpy())
        if denoiser == "diffusion" or denoiser_fallback == "diffusion":
            for k in extra:
                extra[k].append(r.gbuffers[k].detach().to(torch.float32).numpy())
            c2w.append(np.asarray(v.camera.cam_to_world, np.float64))
        if on_frame is not None:
            on_frame(i + 1, len(views))
    res.seconds_per_frame = (time.perf_counter() - t0) / len(views)
    if "mp4" in outputs or "png" in outputs:
        clip = np.stack(ldr)
        kw = {}
        if c2w:
            kw = dict(gbuffer={k: np.stack(x) for k, x in extra.items()}, cam_to_world=np.stack(c2w),
                      env=env.radiance_map().detach().to(torch.float32).numpy())
        d = denoise(clip, np.clip(np.stack(albedo), 0.0, 1.0), np.stack(normal), backend=denoiser,
                    fallback=denoiser_fallback, **kw)
        clip = np.clip(d.frames, 0.0, 1.0)
        res.frames = clip
        res.denoiser = d.backend
        res.denoiser_note = d.fallback_reason
        if "mp4" in outputs:
            res.video = out / "relit.mp4"
            write_mp4(res.video, [ldr_to_uint8(f) for f in clip], fps=fps)
        if "png" in outputs:
            res.preview = out / "preview.png"
            write_png(res.preview, ldr_to_uint8(clip[len(clip) // 2]))
    return res
