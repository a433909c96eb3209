"""The ``relight`` and ``night`` job types: the reconstructed scene (the scene graph of the scene's
latest finished ``reconstruct`` job) rendered by the PBR pass under another sky, with local
lights and object edits, into EXR frames, an MP4 and a PNG preview (:mod:`core.relight`).

Request errors the gateway cannot see (no finished reconstruction, an edit or light naming an
object the reconstruction does not have, a missing bundled HDRI) fail the job permanently with a
message naming the field (``CoreError``); anything else is retried.
"""

from __future__ import annotations

from pathlib import Path

from sqlalchemy import select

from api_schemas.v1.requests import LocalLight, NightRequest, OutputKind, RelightRequest
from core.errors import ConfigError
from worker.db import Artifact, Envmap, Job
from worker.jobs import GRAPH_ARTIFACT, JobContext
from worker.settings import QUEUE_RENDER
from worker.registry import JobType, register

LIGHTING_ARTIFACT = "lighting/envmap.exr"
#: Headlights of the night scenario, in the car frame (x forward, y left, z up; metres; the
#: tracked boxes of the bundles are centred on the car).
HEADLIGHT_OFFSETS = ((2.2, 0.6, -0.1), (2.2, -0.6, -0.1))


def _reconstruction_query(scene_id: str):
    """The scene graph artifacts of the scene's finished reconstruct jobs, newest first (whoever
    submitted them: access to the scene is access to its reconstructions)."""
    return (select(Artifact.storage_key, Job.id).join(Job, Artifact.job_id == Job.id)
            .where(Job.scene_id == scene_id, Job.type == "reconstruct", Job.state == "done",
                   Artifact.name == GRAPH_ARTIFACT)
            .order_by(Job.finished_at.desc()))


def needs_reconstruction(session, scene_id: str, tenant: str) -> str | None:
    """The gateway's precondition of relight and night: a finished reconstruct job."""
    if session.execute(_reconstruction_query(scene_id)).first() is None:
        return (f"scene {scene_id} has no finished reconstruction: run POST /scenes/{scene_id}/reconstruct "
                "and wait for it to finish")
    return None


def _load_graph(ctx: JobContext):
    """The scene graph of the newest finished reconstruct job of this job's scene."""
    from core.scene_graph import SceneGraph

    with ctx.db.session() as s:
        row = s.execute(_reconstruction_query(ctx.job.scene_id)).first()
    if row is None:
        raise ConfigError(f"scene {ctx.job.scene_id}: no finished reconstruction; run "
                          f"POST /scenes/{ctx.job.scene_id}/reconstruct first")
    local = ctx.workdir / "scene_graph.pt"
    ctx.store.get_file(row[0], local)
    return SceneGraph.load(local), row[1]


def _load_env(ctx: JobContext, bundle, p: RelightRequest | None, scale: float = 1.0, rotation_deg: float = 0.0,
              reconstruction_job: str | None = None):
    from core.io.envmap_file import read_envmap
    from core.pbr.envmap import EnvironmentMap
    from core.synth.generate import load_envmap

    if p is not None and p.envmap_id is not None:
        with ctx.db.session() as s:
            em = s.get(Envmap, p.envmap_id)
            if em is None or em.tenant != ctx.job.tenant:
                raise ConfigError(f"envmap_id: envmap {p.envmap_id!r} not found")
            key, fmt = em.storage_key, em.format
        local = ctx.workdir / f"envmap.{fmt}"
        ctx.store.get_file(key, local)
        rgb = read_envmap(local)
    else:
        name = p.envmap_name if p is not None else None
        if name is None:  # night: the scene's own map
            rgb = _scene_env(bundle, ctx, reconstruction_job)
        else:
            try:
                rgb = load_envmap(name)
            except ConfigError as e:
                raise ConfigError(f"envmap_name: no bundled HDRI {name!r} ({e})") from e
    return EnvironmentMap(rgb * scale, rotation_deg=rotation_deg, resample_to=(512, 1024))


def _scene_env(bundle, ctx: JobContext | None = None, reconstruction_job: str | None = None):
    """The scene's own sky for the night scenario: the environment map the reconstruction's PBR
    stage recovered (``lighting/envmap.exr``), else the bundle's ground-truth map (synthetic
    captures ship one), else a uniform grey sky."""
    import numpy as np

    from core.io.envmap_file import read_envmap

    if ctx is not None and reconstruction_job is not None:
        with ctx.db.session() as s:
            key = s.scalar(select(Artifact.storage_key).where(Artifact.job_id == reconstruction_job,
                                                              Artifact.name == LIGHTING_ARTIFACT))
        if key is not None:
            local = ctx.workdir / "scene_envmap.exr"
            ctx.store.get_file(key, local)
            ctx.stage_metrics({"sky": f"recovered by the reconstruction's pbr stage ({LIGHTING_ARTIFACT})"}, merge=True)
            return read_envmap(local)
    gt = bundle.manifest.ground_truth
    if gt is not None:
        return read_envmap(bundle.path(gt.envmap))
    return np.full((256, 512, 3), 0.5, np.float32)


def _views(b, p, graph):
    """The views of ``p.frames`` (frames of the bundle ``b``) or ``p.camera_path`` (new poses)."""
    import numpy as np

    from core.pbr.render import Camera
    from core.relight import View

    times = graph.times.tolist()
    views = []
    if p.camera_path is not None:
        cam = b.manifest.cameras.get(p.camera_path.camera)
        if cam is None:
            raise ConfigError(f"camera_path.camera: no camera {p.camera_path.camera!r} in the scene "
                              f"(cameras: {sorted(b.manifest.cameras)})")
        for i, pose in enumerate(p.camera_path.poses):
            views.append(View(Camera(np.asarray(pose.cam_to_world, np.float64), cam.fx, cam.fy, cam.cx, cam.cy,
                                     cam.width, cam.height), float(pose.time_s), f"{i:05d}"))
        return views, float(p.camera_path.fps)
    fr = p.frames
    frames = b.frames(None if fr is None or fr.split == "all" else fr.split)
    if fr is not None:
        frames = frames[fr.start:fr.stop:fr.step]
    if not frames:
        raise ConfigError("frames: the range selects no frame of the scene")
    for f in frames:
        cam = b.camera(f)
        t = times[f.time_index] if f.time_index < len(times) else float(f.time_index)
        views.append(View(Camera(np.asarray(f.cam_to_world, np.float64), cam.fx, cam.fy, cam.cx, cam.cy, cam.width,
                                 cam.height), float(t), f.id))
    return views, 10.0


def _lights(lights: list[LocalLight], graph, what: str = "lights"):
    from core.pbr.lights import PointLight, SpotLight

    names = {n.name for n in graph.nodes}
    out = []
    for i, lt in enumerate(lights):
        if lt.attach_to is not None and lt.attach_to not in names:
            raise ConfigError(f"{what}[{i}].attach_to: no object {lt.attach_to!r} in the reconstruction "
                              f"(objects: {sorted(names)})")
        kw = dict(position=tuple(lt.position), color=tuple(lt.color), intensity=lt.intensity, node=lt.attach_to,
                  name=f"{what}[{i}]")
        if lt.kind == "spot":
            out.append(SpotLight(direction=tuple(lt.direction), inner_deg=lt.cone_inner_deg,
                                 outer_deg=lt.cone_outer_deg, **kw))
        else:
            out.append(PointLight(**kw))
    return out


def _render(ctx: JobContext, bundle, p, graph, env, lights, exposure_ev: float) -> None:
    from core.pbr.render import PBRSettings
    from core.relight import render_clip

    views, fps = _views(bundle, p, graph)
    q = p.quality
    settings = PBRSettings(rays_per_pixel=q.rays_per_pixel, exposure=2.0 ** exposure_ev,
                           shadows=q.shadow_rays, reuse_visibility=len(views) > 1)
    ctx.stage("render")
    want = [o.value if isinstance(o, OutputKind) else o for o in p.outputs]
    out = ctx.workdir / "out"

    def on_frame(done: int, total: int) -> None:
        ctx.check_canceled()
        ctx.progress(0.05 + 0.85 * done / total, stage_fraction=done / total)

    fallback = q.denoiser_fallback
    res = render_clip(graph, env, views, out, settings=settings, lights=lights, outputs=want,
                      denoiser=q.denoiser.value, denoiser_fallback=fallback, fps=fps, on_frame=on_frame)
    ctx.stage_metrics({"frames": len(views), "seconds_per_frame": round(res.seconds_per_frame, 3),
                       "rays_per_pixel": q.rays_per_pixel, "denoiser": res.denoiser,
                       "denoiser_fallback_reason": res.denoiser_note})
    ctx.stage("upload")
    files = list(res.exr_files) + [f for f in (res.video, res.preview) if f is not None]
    for i, f in enumerate(files):
        ctx.check_canceled()
        ctx.add_artifact(f, Path(f).relative_to(out).as_posix())
        ctx.progress(0.9 + 0.1 * (i + 1) / len(files), stage_fraction=(i + 1) / len(files))


def run_relight(ctx: JobContext, p: RelightRequest) -> None:
    """Relight: another environment map (rotation, exposure), local lights, object edits."""
    from core.relight import ObjectEdit, apply_edits

    from core.bundle import open_bundle

    ctx.stage("fetch")
    bundle = open_bundle(ctx.scene_dir())
    graph, _ = _load_graph(ctx)
    edits = [ObjectEdit(e.op, e.object_id, e.source_object_id, tuple(e.offset_m), e.yaw_deg)
             for e in p.object_edits]
    graph = apply_edits(graph, edits, what="object_edits")
    env = _load_env(ctx, bundle, p, rotation_deg=p.rotation_deg)
    lights = _lights(p.lights, graph)
    ctx.progress(0.05)
    _render(ctx, bundle, p, graph, env, lights, p.exposure_ev)


def run_night(ctx: JobContext, p: NightRequest) -> None:
    """Night: the scene's sky scaled down, headlights on every tracked object, street lights from
    the request's lights (the reconstruction holds no lamp positions), exposure raised."""
    from core.pbr.lights import SpotLight

    from core.bundle import open_bundle

    ctx.stage("fetch")
    bundle = open_bundle(ctx.scene_dir())
    graph, rec_job = _load_graph(ctx)
    env = _load_env(ctx, bundle, None, scale=max(p.sky_scale, 1e-6), reconstruction_job=rec_job)
    lights = _lights(p.lights, graph)
    if p.headlights:
        for n in graph.nodes:
            for k, off in enumerate(HEADLIGHT_OFFSETS):
                lights.append(SpotLight(off, direction=(1.0, 0.0, -0.08), inner_deg=12.0, outer_deg=30.0,
                                        intensity=p.headlight_intensity, color=(1.0, 0.95, 0.85), range=60.0,
                                        node=n.name, name=f"{n.name}/headlight{k}"))
    if p.street_lights and not p.lights:
        ctx.stage_metrics({"note": "street_lights: the reconstruction has no lamp positions; pass them as lights"},
                          merge=True)
    ctx.progress(0.05)
    _render(ctx, bundle, p, graph, env, lights, p.exposure_ev)


register(JobType("relight", QUEUE_RENDER, RelightRequest, run_relight, stages=("fetch", "render", "upload"),
                 precondition=needs_reconstruction))
register(JobType("night", QUEUE_RENDER, NightRequest, run_night, stages=("fetch", "render", "upload"),
                 precondition=needs_reconstruction))
