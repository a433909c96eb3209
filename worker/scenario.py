"""What the ``relight`` and ``night`` job types share: a request's views, lights and object edits
turned into the arguments of a :class:`core.render.scenario.Scenario`, the scene's latest finished
reconstruction restored on this disk, and the scenario rendered
(:func:`core.render.scenario.render_scenario`) with its EXR frames, MP4, PNG preview (and street
lamps) uploaded as artifacts. No scenario logic lives here: the CLI builds the same value.

Request errors the gateway cannot see (an edit or light naming an object the reconstruction does
not have, a missing bundled HDRI) fail the job permanently with a message naming the field
(``CoreError``); anything else is retried.
"""

from __future__ import annotations

from pathlib import Path

from sqlalchemy import select

from api_schemas.v1.requests import OutputKind
from core.errors import ConfigError
from worker.db import Artifact, Scene
from worker.reconstruct import GRAPH_SUFFIX, latest_reconstruction, restore_run
from worker.runtime import JobContext


def load_run(ctx: JobContext, scene: Path):
    """The run directory of the scene's newest finished reconstruction on this disk."""
    with ctx.db.session() as s:
        found = latest_reconstruction(s, ctx.job.scene_id)
    if found is None:
        raise ConfigError(f"scene {ctx.job.scene_id}: no finished reconstruction; run "
                          f"POST /scenes/{ctx.job.scene_id}/reconstruct first")
    job_id, profile = found
    ctx.stage_metrics({"reconstruction_job": job_id}, merge=True)
    return restore_run(ctx, job_id, scene, profile)


def request_views(bundle, p):
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


def foreign_assets(ctx: JobContext, p) -> dict[int, str]:
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


def scenario_inputs(ctx: JobContext, p):
    from core.bundle import open_bundle
    from core.relight import ObjectEdit
    from core.render.scenario import LightSpec

    ctx.stage("fetch")
    scene = ctx.scene_dir()
    bundle = open_bundle(scene)
    run = load_run(ctx, scene)
    views, fps = request_views(bundle, p)
    lights = tuple(LightSpec.from_dict(lt.model_dump(), f"lights[{i}]") for i, lt in enumerate(p.lights))
    assets = foreign_assets(ctx, p)
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


def render_and_upload(ctx: JobContext, run, scenario, graph=None, stage=None) -> None:
    from core.render.scenario import render_scenario

    if graph is None:
        graph, stage = load_graph(run)
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


def load_graph(run):
    """The run's scene graph with every node's tracked box (older runs stored none)."""
    from core.bundle import open_bundle
    from core.render.objects import attach_sizes

    graph, _sky, stage = run.load_scene()
    attach_sizes(graph, open_bundle(run.scene_path(), validate=False).manifest)
    return graph, stage
