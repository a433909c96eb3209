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
from sqlalchemy import select

from worker.db import Artifact, Envmap, Scene
from worker.jobs import JobContext
from worker.reconstruct import GRAPH_SUFFIX, latest_reconstruction, needs_reconstruction, restore_run
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
    from core.render.scenario import views_from_capture, views_from_frames, views_from_path

    if p.captured_path is not None:
        cp = p.captured_path
        views = views_from_capture(bundle, split=cp.split, camera=cp.camera, lateral_shift_m=cp.lateral_shift_m,
                                   height_shift_m=cp.height_shift_m, start_s=cp.start_s, stop_s=cp.stop_s,
                                   fps=cp.fps, what="captured_path")
        return views, float(cp.fps or 10.0)
    if p.camera_path is not None:
        cp = p.camera_path
        return views_from_path(bundle, cp.camera, [(x.cam_to_world, x.time_s) for x in cp.poses],
                               what="camera_path"), float(cp.fps)
    fr = p.frames
    if fr is None:
        return views_from_frames(bundle, "all"), 10.0
    return views_from_frames(bundle, fr.split, fr.start, fr.stop, fr.step), 10.0


def _foreign_assets(ctx: JobContext, p) -> dict[int, str]:
    """Inserts that copy an object of another scene (``source_scene_id``): edit index -> an asset
    file of that object (:func:`core.render.objects.export_asset`), cut from the other scene's
    latest reconstruction (its scene graph artifact, fetched into the job's work dir)."""
    from core.render.objects import export_asset
    from core.scene_graph import SceneGraph
    from core.stages.chain import GRAPH_STAGES

    out = {}
    for i, e in enumerate(getattr(p, "object_edits", [])):
        sid = getattr(e, "source_scene_id", None)
        if e.op != "insert" or sid is None:
            continue
        with ctx.db.session() as s:
            sc = s.get(Scene, sid)
            if sc is None or sc.tenant != ctx.job.tenant:
                raise ConfigError(f"object_edits[{i}].source_scene_id: no scene {sid!r}")
            found = latest_reconstruction(s, sid)
            if found is None:
                raise ConfigError(f"object_edits[{i}].source_scene_id: scene {sid!r} has no finished reconstruction")
            rows = dict(s.execute(select(Artifact.name, Artifact.storage_key).where(
                Artifact.job_id == found[0], Artifact.name.like(f"%{GRAPH_SUFFIX}"))).all())
        name = next((f"{st}{GRAPH_SUFFIX}" for st in reversed(GRAPH_STAGES) if f"{st}{GRAPH_SUFFIX}" in rows), None)
        if name is None:
            raise ConfigError(f"object_edits[{i}].source_scene_id: scene {sid!r} has no scene graph")
        local = ctx.workdir / "sources" / f"{sid}.pt"
        if not local.is_file():
            local.parent.mkdir(parents=True, exist_ok=True)
            ctx.store.get_file(rows[name], local)
        graph = SceneGraph.load(local)
        out[i] = str(export_asset(graph, e.source_object_id, ctx.workdir / "sources" / f"asset{i}.pt",
                                  crop=e.crop_to_box))
    return out


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
    assets = _foreign_assets(ctx, p)
    edits = tuple(ObjectEdit(e.op, e.object_id, None if i in assets else e.source_object_id, tuple(e.offset_m),
                             e.yaw_deg, speed=e.speed, lateral_offset_m=e.lateral_offset_m,
                             poses=tuple((x.time_index, x.obj_to_world) for x in e.poses), asset=assets.get(i),
                             crop=e.crop_to_box, solid=e.solid)
                  for i, e in enumerate(getattr(p, "object_edits", [])))
    q = p.quality
    common = dict(views=tuple(views), lights=lights, edits=edits, base_exposure=bundle.manifest.ldr_exposure,
                  gamma=bundle.manifest.ldr_gamma, rays_per_pixel=q.rays_per_pixel, shadows=q.shadow_rays,
                  denoiser=q.denoiser.value, denoiser_fallback=q.denoiser_fallback, fps=fps,
                  outputs=tuple(o.value if isinstance(o, OutputKind) else o for o in p.outputs))
    return run, common, bundle


def _render(ctx: JobContext, run, scenario, graph=None, stage=None) -> None:
    from core.render.scenario import render_scenario

    if graph is None:
        graph, stage = _graph(run)
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
    if scenario.street_lights:
        import json

        lamps = out / "street_lights.json"
        lamps.write_text(json.dumps({"street_lights": res.metrics["street_lights"]}, indent=1))
        files.append(lamps)
    for i, f in enumerate(files):
        ctx.check_canceled()
        ctx.add_artifact(f, Path(f).relative_to(out).as_posix())
        ctx.progress(0.9 + 0.1 * (i + 1) / len(files), stage_fraction=(i + 1) / len(files))


def _graph(run):
    """The run's scene graph with every node's tracked box (older runs stored none)."""
    from core.bundle import open_bundle
    from core.render.objects import attach_sizes

    graph, _sky, stage = run.load_scene()
    attach_sizes(graph, open_bundle(run.scene_path(), validate=False).manifest)
    return graph, stage


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

    run, common, _bundle = _common(ctx, p)
    sc = Scenario(envmap=_relight_env(ctx, p), rotation_deg=p.rotation_deg, exposure_ev=p.exposure_ev, **common)
    ctx.progress(0.05)
    _render(ctx, run, sc)


def run_night(ctx: JobContext, p: NightRequest) -> None:
    """Night: the reconstruction's own sky scaled down, street lamps (detected, spaced or given),
    vehicle lights on every vehicle but those switched off, the request's lights, automatic
    exposure unless an EV is given (:func:`core.render.scenario.night_scenario`). The lamps'
    positions go to the stage metrics and ``street_lights.json``."""
    from core.render.scenario import night_scenario

    run, common, bundle = _common(ctx, p)
    graph, stage = _graph(run)
    sc, note = night_scenario(run, sky_scale=p.sky_scale, headlights=p.headlights,
                              headlight_intensity=p.headlight_intensity, tail_lights=p.tail_lights,
                              vehicle_lights_off=tuple(p.vehicle_lights_off), exposure_ev=p.exposure_ev,
                              street_lights=p.street_lights, street_light_placement=p.street_light_placement,
                              street_light_positions=p.street_light_positions,
                              street_light_intensity=p.street_light_intensity,
                              street_light_spacing_m=p.street_light_spacing_m, graph=graph, bundle=bundle, **common)
    ctx.stage_metrics({"sky": note}, merge=True)
    ctx.progress(0.05)
    _render(ctx, run, sc, graph, stage)


register(JobType("relight", QUEUE_RENDER, RelightRequest, run_relight, stages=("fetch", "render", "upload"),
                 precondition=needs_reconstruction))
register(JobType("night", QUEUE_RENDER, NightRequest, run_night, stages=("fetch", "render", "upload"),
                 precondition=needs_reconstruction))
