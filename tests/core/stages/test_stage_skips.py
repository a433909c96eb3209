"""The stages' skips (issue #15 item 3): stop a stage once its validation error stops improving
(volume / volume2: held-out PSNR; pbr: the photometric L1 of its steps) and no sun search for an
overcast or night capture (pbr). Each fires when it should, not when it should not, and is in the
stage summary's ``skips_fired``."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from core.camera import Camera
from core.errors import ConfigError
from core.stages.early_stop import stalled
from core.stages.pbr import _FrameData, sunless_capture
from core.stages.pbr_settings import PBRStageConfig
from core.stages.volume import VolumeSettings


# -- the rule ------------------------------------------------------------------------------------

def test_stalled_fires_only_after_patience_measurements_without_a_gain():
    assert not stalled([10.0, 11.0], 2, 0.05, higher_is_better=True)  # too few measurements
    assert stalled([10.0, 11.0, 11.02, 10.9], 2, 0.05, higher_is_better=True)
    assert not stalled([10.0, 11.0, 11.02, 11.2], 2, 0.05, higher_is_better=True)  # the last one gained
    assert not stalled([10.0, 11.0, 10.0, 11.0], 3, 0.05, higher_is_better=True)  # still improving at 3
    # lower is better, relative margin: 1% of 0.1 = 0.001
    assert stalled([0.2, 0.1, 0.0995, 0.0992], 2, 0.01, higher_is_better=False, relative=True)
    assert not stalled([0.2, 0.1, 0.0995, 0.098], 2, 0.01, higher_is_better=False, relative=True)
    # non-finite measurements never count as a gain, and never as the best
    assert stalled([10.0, float("nan"), float("inf")], 2, 0.0, higher_is_better=True)
    assert not stalled([float("nan"), 1.0, 2.0], 2, 0.0, higher_is_better=True)
    with pytest.raises(ConfigError, match="patience"):
        stalled([1.0, 2.0], 0, 0.0, higher_is_better=True)


def test_defaults_follow_the_measurement():
    # benchmarks/results/skips.json: only the skips within noise that save time are on; the sun
    # search skip is off: it fired on a sunny street whose sun was out of view (PBRStageConfig)
    from core.stages.joint import JointSettings

    assert not PBRStageConfig().skip_sun_search
    assert PBRStageConfig().early_stop_every == VolumeSettings().early_stop_every == 0
    assert JointSettings().early_stop_every == 0


def test_skip_settings_are_checked():
    for kw, name in (({"early_stop_every": -1}, "early_stop_every"), ({"early_stop_patience": 0}, "early_stop_patience"),
                     ({"early_stop_min_delta_db": -1.0}, "early_stop_min_delta_db")):
        with pytest.raises(ConfigError, match=name):
            VolumeSettings(**kw)
    for kw, name in (({"skip_sun_search": 1}, "skip_sun_search"), ({"early_stop_every": -1}, "early_stop_every"),
                     ({"overcast_max_clipped_sky": 2.0}, "overcast_max_clipped_sky"),
                     ({"early_stop_min_delta": 1.0}, "early_stop_min_delta")):
        with pytest.raises(ConfigError, match=name):
            PBRStageConfig(**kw)


# -- overcast / night detection --------------------------------------------------------------------

_CAM = Camera.from_intrinsics(np.eye(4), 8.0, 8.0, 4.0, 2.0, 8, 4)


def _frame(sky_value: float, ground_value: float, clipped_sky: int = 0) -> _FrameData:
    h, w = 4, 8
    img = torch.full((h, w, 3), ground_value)
    img[:2] = sky_value
    img.reshape(-1, 3)[:clipped_sky] = 1.0
    sky = torch.zeros(h * w, dtype=torch.bool)
    sky[: 2 * w] = True
    gbuf = {"opacity": (~sky).to(torch.float32).reshape(h, w, 1)}
    return _FrameData(_CAM, gbuf, img.reshape(-1, 3), torch.nonzero(~sky).reshape(-1), [], sky)


def test_sunless_capture_tells_sunny_overcast_and_night_apart():
    cfg = PBRStageConfig()
    kind, st = sunless_capture([_frame(0.6, 0.3, clipped_sky=6)] * 2, None, cfg)  # a sun / glare in view
    assert kind is None and st["clipped_sky_fraction"] == pytest.approx(6 / 16)
    kind, st = sunless_capture([_frame(0.6, 0.3)] * 2, None, cfg)  # a bright sky, nothing clipped
    assert kind == "overcast" and st["clipped_sky_fraction"] == 0.0
    kind, st = sunless_capture([_frame(0.03, 0.01, clipped_sky=6)] * 2, None, cfg)  # dark, lamps clipped
    assert kind == "night" and st["median_ldr"] <= cfg.night_max_median_ldr


# -- on a reconstruction ---------------------------------------------------------------------------



@pytest.fixture(scope="module")
def tiny_run(tiny_scene, tmp_path_factory) -> Path:
    from core.stages.chain import run_pipeline

    out = tmp_path_factory.mktemp("skips") / "run"
    run_pipeline(tiny_scene, out, "tiny", stages=("volume",), progress=False,
                 overrides={"volume": {"iterations": 90, "early_stop_every": 10, "early_stop_min_delta_db": 50.0}})
    return out


@pytest.mark.mitsuba
def test_volume_early_stop_fires_and_is_in_the_stage_summary(tiny_run):
    from core.stages.chain import RunDir

    s = RunDir(tiny_run).summary("volume")
    f = {x["skip"]: x for x in s["skips_fired"]}["early_stop"]
    # checks at 50, 60, 70 (after densify_until=50); no 50 dB gain: stops at the third
    assert s["early_stopped_at"] == f["stopped_at"] == 70 and s["iterations_run"] == 70
    assert [v["it"] for v in s["validation"]] == [50, 60, 70] and "held-out PSNR" in f["why"]
    assert np.isfinite(s["test_psnr"]) and s["history"][-1]["it"] <= 70
    assert (tiny_run / "volume" / "checkpoint" / "scene_graph.pt").is_file()


@pytest.mark.mitsuba
def test_volume_early_stop_does_not_fire_while_improving_or_when_off(tiny_scene):
    from core.bundle import open_bundle
    from core.stages.chain import profile_settings
    from core.stages.volume import run_volume

    b = open_bundle(tiny_scene)
    base = replace(profile_settings("tiny", "volume"), iterations=40, densify_from=10**9, densify_until=0,
                   lambda_normal=0, lambda_albedo=0, lambda_roughness=0, lambda_metallic=0, lambda_prior_depth=0)
    # patience longer than the run has measurements: never fires
    s = run_volume(b, replace(base, early_stop_every=10, early_stop_patience=5), progress=False)
    assert s["skips_fired"] == [] and s["early_stopped_at"] is None and s["iterations_run"] == 40
    assert [v["it"] for v in s["validation"]] == [10, 20, 30]
    s = run_volume(b, base, progress=False)  # off: no measurement at all
    assert s["skips_fired"] == [] and s["validation"] == [] and s["iterations_run"] == 40


@pytest.mark.mitsuba
def test_pbr_skips_fire_when_they_should_and_are_in_the_summary(tiny_run, tmp_path):
    from core.bundle import open_bundle
    from core.stages.chain import RunDir, profile_settings, run_stage
    from core.stages.pbr import fit_lighting

    run = RunDir(tiny_run)
    graph, _sky, _ = run.load_scene()
    b = open_bundle(run.scene_path())
    base = replace(profile_settings("tiny", "pbr"), iterations=12, pixels=128, rays_per_pixel=4, eval_pixels=128)
    # the tiny street is sunny (city): its sky is clipped, no skip fires at the defaults
    s = fit_lighting(graph, b, tmp_path / "a", replace(base, skip_sun_search=True))
    assert s["capture_sky"]["sunless"] is None and s["sun_search"] and s["skips_fired"] == []
    # a threshold that calls it overcast: the sun search is skipped, and said so
    s = fit_lighting(graph, b, tmp_path / "b", replace(base, skip_sun_search=True, overcast_max_clipped_sky=1.0))
    f = {x["skip"]: x for x in s["skips_fired"]}["skip_sun_search"]
    assert not s["sun_search"] and "overcast capture" in f["why"]
    # the same capture with the skip off: the search runs
    s = fit_lighting(graph, b, tmp_path / "c", replace(base, skip_sun_search=False, overcast_max_clipped_sky=1.0))
    assert s["sun_search"] and s["skips_fired"] == [] and s["capture_sky"]["sunless"] == "overcast"
    # early stop: a 99% gain is never reached, so it stops after 3 windows of 3 steps (patience 2)
    s = fit_lighting(graph, b, tmp_path / "d", replace(base, early_stop_every=3, early_stop_min_delta=0.99))
    f = {x["skip"]: x for x in s["skips_fired"]}["early_stop"]
    assert s["early_stopped_at"] == f["stopped_at"] == 9 and s["iterations_run"] == len(s["history"]) == 9
    assert (tmp_path / "d" / "envmap.exr").is_file() and np.isfinite(s["photometric_psnr_fitted"])
    s = fit_lighting(graph, b, tmp_path / "e", replace(base, early_stop_every=3, early_stop_patience=10))
    assert s["skips_fired"] == [] and s["iterations_run"] == 12
    # through the chain: the stage summary (summary.json) keeps skips_fired beside scene_skips' skipped
    out = run_stage("pbr", b, run, replace(base, early_stop_every=3, early_stop_min_delta=0.99), progress=False)
    saved = json.loads((tiny_run / "pbr" / "summary.json").read_text())
    assert [x["skip"] for x in out["skips_fired"]] == [x["skip"] for x in saved["skips_fired"]] == ["early_stop"]
    assert "skipped" in saved


@pytest.mark.mitsuba
def test_joint_early_stop_fires_and_is_in_the_stage_summary(tiny_run):
    from core.bundle import open_bundle
    from core.stages.chain import RunDir, profile_settings, run_stage

    run = RunDir(tiny_run)
    b = open_bundle(run.scene_path())
    if not run.is_done("pbr"):
        run_stage("pbr", b, run, replace(profile_settings("tiny", "pbr"), iterations=6, pixels=128,
                                         rays_per_pixel=4, eval_pixels=128), progress=False)
    base = replace(profile_settings("tiny", "joint"), iterations=12, pixels=64, rays_per_pixel=4)
    s = run_stage("joint", b, run, replace(base, early_stop_every=3, early_stop_patience=10), progress=False)
    assert s["skips_fired"] == [] and s["iterations_run"] == 12 and len(s["history"]) == 12
    s = run_stage("joint", b, run, replace(base, early_stop_every=3, early_stop_min_delta=0.99), progress=False)
    f = {x["skip"]: x for x in s["skips_fired"]}["early_stop"]
    assert s["early_stopped_at"] == f["stopped_at"] == 9 and len(s["history"]) == 9
    saved = json.loads((tiny_run / "joint" / "summary.json").read_text())
    assert saved["skips_fired"][0]["skip"] == "early_stop" and (tiny_run / "joint" / "envmap.exr").is_file()
    with pytest.raises(ConfigError, match="early_stop_every"):
        replace(base, early_stop_every=-1)
