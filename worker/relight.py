"""The ``relight`` and ``night`` job types: a request turned into a :class:`core.render.scenario.Scenario`
and rendered from the scene's latest finished reconstruction (:func:`core.render.scenario.render_scenario`);
EXR frames, an MP4 and a PNG preview become the job's artifacts. No scenario logic lives here: the
CLI's ``brdf relight`` / ``brdf night`` build the same value.

Request errors the gateway cannot see (an edit or light naming an object the reconstruction does
not have, a missing bundled HDRI) fail the job permanently with a message naming the field
(``CoreError``); anything else is retried.
"""

from __future__ import annotations

from pathlib import Path

from api_schemas.v1.requests import NightRequest, OutputKind, RelightRequest
from core.errors import ConfigError
from worker.db import Envmap
from worker.jobs import JobContext
from worker.reconstruct import latest_reconstruction, needs_reconstruction, restore_run
from worker.registry import JobType, register
from worker.settings import QUEUE_RENDER


def _load_run(ctx: JobContext, scene: Path):
    """The run directory of the scene's newest finished reconstruction on this disk."""
    with ctx.db.session() as s:
        found = latest_reconstruction(s, ctx.job.scene_id)
    if found is None:
        raise ConfigError(f"scene {ctx.job.scene_id}: no finished reconstruction; run "
                          f"POST /scenes/{ctx.job.scene_id}/reconstruct first")
    job_id, profile = found
    ctx.stage_metrics({"reconstruction_job": job_id}, merge=True)
    return restore_run(ctx, job_id, scene, profile)


def _views(bundle, p):
    from core.render.scenario import views_from_frames, views_from_path

    if p.camera_path is not None:
        cp = p.camera_path
        return views_from_path(bundle, cp.camera, [(x.cam_to_world, x.time_s) for x in cp.poses],
                               what="camera_path"), float(cp.fps)
    fr = p.frames
    if fr is None:
        return views_from_frames(bundle, "all"), 10.0
    return views_from_frames(bundle, fr.split, fr.start, fr.stop, fr.step), 10.0


def _common(ctx: JobContext, p):
    from core.bundle import open_bundle
    from core.relight import ObjectEdit
    from core.render.scenario import LightSpec

    ctx.stage("fetch")
    scene = ctx.scene_dir()
    bundle = open_bundle(scene)
    run = _load_run(ctx, scene)
    views, fps = _views(bundle, p)
    lights = tuple(LightSpec.from_dict(lt.model_dump(), f"lights[{i}]") for i, lt in enumerate(p.lights))
    edits = tuple(ObjectEdit(e.op, e.object_id, e.source_object_id, tuple(e.offset_m), e.yaw_deg)
                  for e in getattr(p, "object_edits", []))
    q = p.quality
    common = dict(views=tuple(views), lights=lights, edits=edits, base_exposure=bundle.manifest.ldr_exposure,
                  gamma=bundle.manifest.ldr_gamma, rays_per_pixel=q.rays_per_pixel, shadows=q.shadow_rays,
                  denoiser=q.denoiser.value, denoiser_fallback=q.denoiser_fallback, fps=fps,
                  outputs=tuple(o.value if isinstance(o, OutputKind) else o for o in p.outputs))
    return run, common


def _render(ctx: JobContext, run, scenario) -> None:
    from core.render.scenario import render_scenario

    graph, _sky, stage = run.load_scene()
    ctx.stage("render")
    out = ctx.workdir / "out"

    def on_frame(done: int, total: int) -> None:
        ctx.check_canceled()
        ctx.progress(0.05 + 0.85 * done / total, stage_fraction=done / total)

    res = render_scenario(graph, scenario, out, on_frame=on_frame)
    ctx.stage_metrics({**res.metrics, "reconstruction_stage": stage})
    ctx.stage("upload")
    r = res.result
    files = list(r.exr_files) + [f for f in (r.video, r.preview) if f is not None]
    for i, f in enumerate(files):
        ctx.check_canceled()
        ctx.add_artifact(f, Path(f).relative_to(out).as_posix())
        ctx.progress(0.9 + 0.1 * (i + 1) / len(files), stage_fraction=(i + 1) / len(files))


def _relight_env(ctx: JobContext, p: RelightRequest):
    from core.io.envmap_file import read_envmap
    from core.io.hdri import load_hdri

    if p.envmap_id is None:
        return load_hdri(p.envmap_name)
    with ctx.db.session() as s:
        em = s.get(Envmap, p.envmap_id)
        if em is None or em.tenant != ctx.job.tenant:
            raise ConfigError(f"envmap_id: envmap {p.envmap_id!r} not found")
        key, fmt = em.storage_key, em.format
    local = ctx.workdir / f"envmap.{fmt}"
    ctx.store.get_file(key, local)
    return read_envmap(local)


def run_relight(ctx: JobContext, p: RelightRequest) -> None:
    """Relight: another environment map (rotation, exposure), local lights, object edits."""
    from core.render.scenario import Scenario

    run, common = _common(ctx, p)
    sc = Scenario(envmap=_relight_env(ctx, p), rotation_deg=p.rotation_deg, exposure_ev=p.exposure_ev, **common)
    ctx.progress(0.05)
    _render(ctx, run, sc)


def run_night(ctx: JobContext, p: NightRequest) -> None:
    """Night: the reconstruction's own sky scaled down, headlights on every tracked object, the
    request's lights, exposure raised (:func:`core.render.scenario.night_scenario`)."""
    from core.render.scenario import night_scenario

    run, common = _common(ctx, p)
    sc, note = night_scenario(run, sky_scale=p.sky_scale, headlights=p.headlights,
                              headlight_intensity=p.headlight_intensity, exposure_ev=p.exposure_ev, **common)
    ctx.stage_metrics({"sky": note}, merge=True)
    if p.street_lights and not p.lights:
        ctx.stage_metrics({"note": "street_lights: the reconstruction has no lamp positions; pass them as lights"},
                          merge=True)
    ctx.progress(0.05)
    _render(ctx, run, sc)


register(JobType("relight", QUEUE_RENDER, RelightRequest, run_relight, stages=("fetch", "render", "upload"),
                 precondition=needs_reconstruction))
register(JobType("night", QUEUE_RENDER, NightRequest, run_night, stages=("fetch", "render", "upload"),
                 precondition=needs_reconstruction))
