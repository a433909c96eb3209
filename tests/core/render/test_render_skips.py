"""The render path's skips (issue #15 item 3): rays per pixel set by the measured variance
(``Scenario.adaptive_rays``) and the reconstruction's cached visibility reused across relight
requests (``Scenario.reuse_visibility_across_requests``): each fires when it should, not when it
should not, and is recorded in the metrics' ``skips_fired``."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from core.errors import ConfigError
from core.pbr.render import ClipHook, clear_shared_contexts, gaussians_fingerprint
from core.stages.chain import RunDir, run_pipeline

pytestmark = pytest.mark.mitsuba


@pytest.fixture(scope="module")
def tiny_run(tiny_scene, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("skiprun") / "run"
    run_pipeline(tiny_scene, out, "tiny", stages=("volume",), progress=False)
    return out


@pytest.fixture(scope="module")
def loaded(tiny_run):
    from core.bundle import open_bundle
    from core.render.scenario import views_from_frames

    run = RunDir(tiny_run)
    graph, _sky, _ = run.load_scene()
    b = open_bundle(run.scene_path())
    return graph, tuple(views_from_frames(b, "all"))


def _scenario(views, env=None, **kw):
    from core.render.scenario import Scenario

    env = np.full((16, 32, 3), 0.5, np.float32) if env is None else env
    return Scenario(views=views, envmap=env, denoiser="none", outputs=("png",), **kw)


def _fired(res) -> dict:
    return {f["skip"]: f for f in res.metrics["skips_fired"]}


def test_defaults_follow_the_measurement():
    from core.render.scenario import Scenario

    defaults = {f.name: f.default for f in Scenario.__dataclass_fields__.values()}
    assert defaults["reuse_visibility_across_requests"] is True  # within noise, saves time
    assert defaults["adaptive_rays"] is False  # within noise, saved none


def test_the_skip_fields_are_checked():
    from core.camera import Camera
    from core.relight import View

    v = (View(Camera.from_intrinsics(np.eye(4), 30.0, 30.0, 16.0, 12.0, 32, 24), 0.0, "v0"),)
    for name in ("adaptive_rays", "reuse_visibility_across_requests"):
        with pytest.raises(ConfigError, match=name):
            _scenario(v, **{name: 1})


def test_adaptive_rays_fires_on_a_smooth_sky_and_is_recorded(loaded, tmp_path):
    from core.render.scenario import render_scenario

    graph, views = loaded
    off = render_scenario(graph, _scenario(views, rays_per_pixel=64), tmp_path / "off")
    assert "adaptive_rays" not in _fired(off) and off.metrics["mean_rays_per_pixel"] == 64
    # a uniform sky: a pixel's estimate settles fast, most pixels stop after the minimum batches
    on = render_scenario(graph, _scenario(views, rays_per_pixel=64, adaptive_rays=True), tmp_path / "on")
    f = _fired(on)["adaptive_rays"]
    assert f["mean_rays_per_pixel"] < 64 and "standard error" in f["why"]
    assert on.metrics["mean_rays_per_pixel"] == f["mean_rays_per_pixel"]


def test_adaptive_rays_does_not_fire_when_no_pixel_can_stop_early(loaded, tmp_path):
    from core.render.scenario import render_scenario

    graph, views = loaded
    # 48 rays = the sampler's 6 minimum batches of 8: every pixel takes all of them
    on = render_scenario(graph, _scenario(views, rays_per_pixel=48, adaptive_rays=True), tmp_path / "on")
    assert on.metrics["mean_rays_per_pixel"] == 48 and "adaptive_rays" not in _fired(on)


def test_visibility_is_reused_only_across_requests_of_the_same_reconstruction(loaded, tmp_path):
    from core.io.hdri import load_hdri
    from core.relight import ObjectEdit
    from core.render.scenario import render_scenario

    graph, views = loaded
    clear_shared_contexts()
    env = load_hdri("sunset")
    first = render_scenario(graph, _scenario(views, env, reuse_visibility_across_requests=True), tmp_path / "a")
    assert "reuse_visibility_across_requests" not in _fired(first)  # nothing to reuse yet
    # the same reconstruction, another view range, the same map: BVH and visibility cache reused
    again = render_scenario(graph, _scenario(views[:2], env, reuse_visibility_across_requests=True), tmp_path / "b")
    f = _fired(again)["reuse_visibility_across_requests"]
    assert f["reused"] == "bvh+visibility" and again.metrics["setup_seconds"] < first.metrics["setup_seconds"]
    # another map: only the BVH
    other = render_scenario(graph, _scenario(views, load_hdri("forest"), reuse_visibility_across_requests=True),
                            tmp_path / "c")
    assert _fired(other)["reuse_visibility_across_requests"]["reused"] == "bvh"
    # off: never reused, never recorded
    off = render_scenario(graph, _scenario(views, env, reuse_visibility_across_requests=False), tmp_path / "d")
    assert "reuse_visibility_across_requests" not in _fired(off)
    # other shadow casters (a static object removed): not the same reconstruction, nothing reused
    parked = [n.name for n in graph.nodes if n.is_static]
    if parked:
        edited = render_scenario(graph, _scenario(views, env, reuse_visibility_across_requests=True,
                                                  edits=(ObjectEdit(op="remove", object_id=parked[0]),)),
                                 tmp_path / "e")
        assert "reuse_visibility_across_requests" not in _fired(edited)
    # the reused frames are the frames a fresh context renders (same BVH, same samples)
    clear_shared_contexts()
    a = render_scenario(graph, _scenario(views[:2], env, reuse_visibility_across_requests=True), tmp_path / "f")
    b = render_scenario(graph, _scenario(views[:2], env, reuse_visibility_across_requests=True), tmp_path / "g")
    assert _fired(b)["reuse_visibility_across_requests"]["reused"] == "bvh+visibility"
    assert np.isfinite(b.result.frames).all() and np.abs(a.result.frames - b.result.frames).mean() < 0.02
    clear_shared_contexts()


def test_the_fingerprint_sees_every_shadow_casting_change(loaded):
    graph, _ = loaded
    g = graph.shadow_static()
    fp = gaussians_fingerprint(g)
    assert fp == gaussians_fingerprint(graph.shadow_static())
    moved = replace(g, means=g.means + 1e-6)
    assert gaussians_fingerprint(moved) != fp
    assert gaussians_fingerprint(None) == "empty"
    with ClipHook() as hook:
        assert hook.mean_samples is None and hook.reused is None
