"""The ``night`` job type: the scene's latest reconstruction at night (its own sky scaled down,
street lamps, vehicle lights, the request's lights and object edits; :mod:`worker.scenario`)."""

from __future__ import annotations

from api_schemas.v1.requests import NightRequest
from worker.reconstruct import needs_reconstruction
from worker.runtime import JobContext, JobType
from worker.scenario import load_graph, render_and_upload, scenario_inputs
from worker.settings import QUEUE_RENDER


def run_night(ctx: JobContext, p: NightRequest) -> None:
    """Night: the reconstruction's own sky scaled down, street lamps (detected, spaced or given),
    vehicle lights on every vehicle but those switched off, the request's lights, automatic
    exposure unless an EV is given (:func:`core.render.scenario.night_scenario`). The lamps'
    positions go to the stage metrics and ``street_lights.json``."""
    from core.render.scenario import night_scenario

    run, common, bundle = scenario_inputs(ctx, p)
    graph, stage = load_graph(run)
    sc, note = night_scenario(run, sky_scale=p.sky_scale, headlights=p.headlights,
                              headlight_intensity=p.headlight_intensity, tail_lights=p.tail_lights,
                              vehicle_lights_off=tuple(p.vehicle_lights_off), exposure_ev=p.exposure_ev,
                              street_lights=p.street_lights, street_light_placement=p.street_light_placement,
                              street_light_positions=p.street_light_positions,
                              street_light_intensity=p.street_light_intensity,
                              street_light_spacing_m=p.street_light_spacing_m, graph=graph, bundle=bundle, **common)
    ctx.stage_metrics({"sky": note}, merge=True)
    ctx.progress(0.05)
    render_and_upload(ctx, run, sc, graph, stage)


JOB_TYPE = JobType("night", QUEUE_RENDER, NightRequest, run_night, stages=("fetch", "render", "upload"),
                   precondition=needs_reconstruction)
