"""Relighting a reconstructed scene: object edits on its scene graph, and a clip rendered by the
PBR pass under a new environment map and local lights, written as multi-layer EXR frames, an MP4
and a PNG preview (the library side of the service's ``relight`` and ``night`` jobs).

Frames: cameras are OpenCV (:class:`core.camera.Camera`), times in seconds of the scene graph.
Outputs in ``out_dir``: ``frames/<name>.exr`` (HDR beauty ``rgb`` and ``Lr`` in float32, the
G-buffers; see :func:`core.pbr.render.write_frame_exr`), ``relit.mp4`` (the LDR frames after the
denoiser) and ``preview.png`` (the middle frame). The EXR beauty is the PBR pass's estimate before
denoising; the denoiser (``none`` / ``oidn`` / ``diffusion``, :func:`core.gen.denoise.denoise`)
works on the LDR clip with the albedo and normal G-buffers as guides.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import torch

from core.camera import Camera
from core.conventions import is_rigid
from core.errors import ConfigError
from core.gen.denoise import denoise
from core.io.images import write_png
from core.io.video import write_mp4
from core.pbr.envmap import EnvironmentMap
from core.pbr.render import ClipRenderer, PBRSettings, write_frame_exr
from core.render.objects import load_asset, object_box, prepare_edited, retime_poses
from core.render.removal import clear_removed
from core.scene_graph import RigidNode, SceneGraph
from core.tonemap import ldr_to_uint8

OUTPUT_KINDS = ("exr", "mp4", "png")


@dataclass(frozen=True)
class View:
    """One frame to render: an OpenCV camera, the scene time (seconds) and a file stem."""

    camera: Camera
    time_s: float
    name: str


@dataclass(frozen=True)
class ObjectEdit:
    """Insert, move or remove an object (a scene-graph node); removal hides it in every frame.

    ``offset_m``: world translation (metres) applied after the node's own pose; ``yaw_deg``:
    rotation about the node's up axis (+z of the node frame), degrees. Trajectory edits (move and
    insert): ``speed`` (the object covers its path this many times as fast, 0 stops it at its
    first pose), ``lateral_offset_m`` (along the object's own left axis, a lane offset), ``poses``
    (``((time_index, obj_to_world 4x4), ...)``: an explicit trajectory replacing the node's).
    Insert copies ``source_object_id`` or loads ``asset`` (a file of
    :func:`core.render.objects.export_asset`; placed with ``poses``, or at world position
    ``offset_m`` turned by ``yaw_deg`` at every time). ``crop``: the moved or inserted node keeps
    only its Gaussians inside its box (:func:`core.render.objects.crop_to_box`), so floaters
    do not travel with it. ``solid``: its inside is filled with opaque Gaussians
    (:func:`core.render.objects.solid_filler`), so it casts a solid shadow, not the faint one of
    a half-transparent shell. ``fill_ground`` (remove): where the removed object hid the road in
    every frame (no observed ground Gaussian under it or along its lane within 30 m), flat road
    Gaussians coloured like the road around it are added to the background
    (:func:`core.render.removal.ground_fill`), so its pixels show road, not sky, and its remnants in
    the background go with it (:func:`core.render.removal.object_remnants`)."""

    op: str
    object_id: str
    source_object_id: str | None = None
    offset_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    yaw_deg: float = 0.0
    speed: float = 1.0
    lateral_offset_m: float = 0.0
    poses: tuple = ()
    asset: str | None = None
    crop: bool = True
    solid: bool = True
    fill_ground: bool = True


@dataclass
class RelightResult:
    """Paths written and what the clip cost."""

    exr_files: list[Path] = field(default_factory=list)
    video: Path | None = None
    preview: Path | None = None
    seconds_per_frame: float = 0.0
    denoiser: str = "none"
    denoiser_note: str | None = None
    exposure: float = 1.0
    """The exposure of the LDR clip (the automatic one when ``auto_exposure`` was given)."""
    exposure_note: str | None = None
    """How the automatic exposure was chosen (``key``, ``highlights`` or ``clamp``), else None."""
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


def _explicit_poses(e: ObjectEdit, n_times: int, what: str) -> tuple[torch.Tensor, torch.Tensor]:
    ti, mats = [], []
    for k, item in enumerate(e.poses):
        try:
            t, m = item
            m = np.asarray(m, np.float64)
        except (TypeError, ValueError) as exc:
            raise ConfigError(f"{what}.poses[{k}]: expected (time_index, 4x4 obj_to_world)") from exc
        if not isinstance(t, (int, np.integer)) or not 0 <= int(t) < n_times:
            raise ConfigError(f"{what}.poses[{k}].time_index: must be an int in [0, {n_times - 1}], got {t!r}")

        if m.shape != (4, 4) or not np.isfinite(m).all() or not is_rigid(m):
            raise ConfigError(f"{what}.poses[{k}].obj_to_world: expected a finite rigid 4x4 transform")
        ti.append(int(t))
        mats.append(m)
    if len(set(ti)) != len(ti):
        raise ConfigError(f"{what}.poses: a time index appears twice")
    return torch.tensor(ti), torch.from_numpy(np.stack(mats))


def _trajectory(e: ObjectEdit, poses: torch.Tensor, time_indices: torch.Tensor, times, what: str):
    try:
        out = retime_poses(poses, time_indices, times, speed=e.speed, lateral_offset_m=e.lateral_offset_m)
    except ConfigError as exc:
        raise ConfigError(f"{what}.{exc}") from None
    return _edit_pose(out, e.offset_m, e.yaw_deg)


def apply_edits(graph, edits: Sequence[ObjectEdit], what: str = "edits"):
    """A new :class:`core.scene_graph.SceneGraph` with ``edits`` applied in order (the input is
    not modified). Raises ConfigError naming the edit (``<what>[i]``) that refers to an unknown
    node or inserts an existing id."""
    nodes = list(graph.nodes)
    background = graph.background
    n_times = len(graph.times)
    for i, e in enumerate(edits):
        w = f"{what}[{i}]"
        names = [n.name for n in nodes]
        if e.op == "remove":
            if e.object_id not in names:
                raise ConfigError(f"{w}.object_id: no object {e.object_id!r} in the scene (objects: {names})")
            if e.fill_ground:
                src = next(n for n in nodes if n.name == e.object_id)
                background = clear_removed(background, src)[0]
            nodes = [n for n in nodes if n.name != e.object_id]
        elif e.op == "move":
            if e.object_id not in names:
                raise ConfigError(f"{w}.object_id: no object {e.object_id!r} in the scene (objects: {names})")
            src = next(n for n in nodes if n.name == e.object_id)
            ti, poses = (_explicit_poses(e, n_times, w) if e.poses else (src.time_indices.clone(), src.poses.detach()))
            poses = _trajectory(e, poses, ti, graph.times, w)
            g = prepare_edited(src.gaussians, object_box(src), crop=e.crop, solid=e.solid)
            nodes = [RigidNode(src.name, src.cls, g, ti, poses, size=src.size, edited=True) if n.name == e.object_id
                     else n for n in nodes]
        elif e.op == "insert":
            if e.object_id in names:
                raise ConfigError(f"{w}.object_id: {e.object_id!r} already exists; pick a new id")
            if (e.asset is None) == (e.source_object_id is None):
                raise ConfigError(f"{w}.source_object_id: give exactly one of source_object_id or asset")
            if e.asset is not None:
                cls, size, g = load_asset(e.asset, f"{w}.asset")
                if e.poses:
                    ti, poses = _explicit_poses(e, n_times, w)
                    poses = _trajectory(e, poses, ti, graph.times, w)
                else:
                    ti = torch.arange(n_times)
                    poses = _edit_pose(torch.eye(4, dtype=torch.float64).repeat(n_times, 1, 1), e.offset_m,
                                       e.yaw_deg)
                g = prepare_edited(g, size, crop=e.crop, solid=e.solid)
                nodes.append(RigidNode(e.object_id, cls, g, ti, poses, size=size, edited=True))
                continue
            if e.source_object_id not in names:
                raise ConfigError(f"{w}.source_object_id: no object {e.source_object_id!r} in the scene "
                                  f"(objects: {names})")
            src = next(n for n in nodes if n.name == e.source_object_id)
            ti, poses = (_explicit_poses(e, n_times, w) if e.poses else (src.time_indices.clone(), src.poses.detach()))
            poses = _trajectory(e, poses, ti, graph.times, w)
            g = prepare_edited(src.gaussians, object_box(src), crop=e.crop, solid=e.solid)
            nodes.append(RigidNode(e.object_id, src.cls, g, ti, poses, size=src.size, edited=True))
        else:
            raise ConfigError(f"{w}.op: must be insert, move or remove, got {e.op!r}")
    edited = SceneGraph(background, nodes, graph.times)
    edited.occluders = graph.occluders  # the completed facades belong to the static scene
    return edited


def render_clip(scene, env: EnvironmentMap, views: Sequence[View], out_dir: str | Path, *,
                settings: PBRSettings | None = None, lights=(), outputs: Sequence[str] = OUTPUT_KINDS,
                denoiser: str = "none", denoiser_fallback: str | None = None, fps: float = 10.0,
                on_frame: Callable[[int, int], None] | None = None, auto_exposure=None,
                corrector=None, features_out: list | None = None) -> RelightResult:
    """Render ``views`` of ``scene`` (a SceneGraph or Gaussians) lit by ``env`` and ``lights``
    with the PBR pass (reuse across the clip: static BVH once, visibility cache when
    ``settings.reuse_visibility``), denoise the LDR clip, and write the outputs (module
    docstring). ``on_frame(done, total)`` is called after each frame (progress, cancel checks).
    ``auto_exposure`` (:class:`core.render.exposure.AutoExposure`): one exposure for the clip
    measured on its HDR frames replaces ``settings.exposure`` for the LDR clip (the EXR keeps
    the HDR). ``corrector`` (:class:`core.gen.scene_corrector.SceneCorrector`, fitted on this
    scene's capture): applied to each denoised LDR frame with its G-buffers (the MP4 / PNG and
    ``frames``; the EXR keeps the PBR pass's HDR). ``features_out``: a list that receives each
    frame's corrector features ``[H, W, 13]`` (of the denoised frame, before any correction: what
    the ``corrector`` stage fits on). Raises ConfigError for an empty view list,
    unknown outputs or a bad fps."""
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
    ldr, albedo, normal, hdr = [], [], [], []
    extra: dict[str, list] = {"depth": [], "roughness": [], "metallic": []}
    c2w = []
    corr_in: list[tuple[dict, np.ndarray]] = []
    t0 = time.perf_counter()
    for i, v in enumerate(views):
        r = renderer.render(v.camera, time_s=v.time_s, frame_index=i)
        if "exr" in outputs:
            p = out / "frames" / f"{v.name}.exr"
            write_frame_exr(p, r)
            res.exr_files.append(p)
        ldr.append(r.ldr.detach().to(torch.float32).numpy())
        if auto_exposure is not None:
            hdr.append(r.hdr.detach().to(torch.float32).numpy())
        albedo.append(r.gbuffers["albedo"].detach().to(torch.float32).numpy())
        normal.append(r.gbuffers["normal"].detach().to(torch.float32).numpy())
        if denoiser == "diffusion" or denoiser_fallback == "diffusion":
            for k in extra:
                extra[k].append(r.gbuffers[k].detach().to(torch.float32).numpy())
            c2w.append(v.camera.pose_numpy())
        if corrector is not None or features_out is not None:
            keep = ("albedo", "normal", "roughness", "metallic", "opacity", "depth")
            corr_in.append(({k: r.gbuffers[k].detach().to(torch.float32).numpy() for k in keep},
                            v.camera.cam_to_world[:3, :3].detach().to(torch.float64).numpy().T))
        if on_frame is not None:
            on_frame(i + 1, len(views))
    res.seconds_per_frame = (time.perf_counter() - t0) / len(views)
    res.exposure = float(s.exposure)
    if auto_exposure is not None:
        from core.render.exposure import auto_exposure as choose

        ch = choose(hdr, auto_exposure)
        res.exposure, res.exposure_note = ch.exposure, ch.limited_by
        ldr = [np.clip(h * ch.exposure, 0.0, 1.0) ** (1.0 / s.gamma) for h in hdr]
    if "mp4" in outputs or "png" in outputs:
        clip = np.stack(ldr)
        kw = {}
        if c2w:
            kw = dict(gbuffer={k: np.stack(x) for k, x in extra.items()}, cam_to_world=np.stack(c2w),
                      env=env.radiance_map().detach().to(torch.float32).numpy())
        d = denoise(clip, np.clip(np.stack(albedo), 0.0, 1.0), np.stack(normal), backend=denoiser,
                    fallback=denoiser_fallback, **kw)
        clip = np.clip(d.frames, 0.0, 1.0)
        if corr_in:
            from core.gen.scene_corrector import apply_corrector, frame_features

            feats = [frame_features(f, gb, w2c) for f, (gb, w2c) in zip(clip, corr_in)]
            if features_out is not None:
                features_out.extend(feats)
            if corrector is not None:
                clip = np.stack([apply_corrector(corrector, x) for x in feats])
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
