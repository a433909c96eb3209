"""The ``relight`` job type: the scene's latest reconstruction under another environment map (a
bundled HDRI by name or an uploaded one by id; rotation, exposure), with the request's local lights
and object edits (:mod:`worker.scenario`)."""

from __future__ import annotations

from api_schemas.v1.requests import RelightRequest
from core.errors import ConfigError
from worker.db import Envmap
from worker.reconstruct import needs_reconstruction
from worker.runtime import JobContext, JobType
from worker.scenario import render_and_upload, scenario_inputs
from worker.settings import QUEUE_RENDER


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
    from core.render.scenario import Scenario, scene_corrector

    run, common, _bundle = scenario_inputs(ctx, p)
    corrector, _note = scene_corrector(run)  # fitted on the capture by the corrector stage, when it ran
    sc = Scenario(envmap=_relight_env(ctx, p), rotation_deg=p.rotation_deg, exposure_ev=p.exposure_ev,
                  corrector=corrector, **common)
    ctx.progress(0.05)
    render_and_upload(ctx, run, sc)


JOB_TYPE = JobType("relight", QUEUE_RENDER, RelightRequest, run_relight, stages=("fetch", "render", "upload"),
                   precondition=needs_reconstruction)
