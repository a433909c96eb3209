"""The PBR stage (lighting only, the paper's Eq. 6) on a reconstruction of the tiny Mitsuba scene."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
import torch

from core.bundle import open_bundle
from core.errors import ConfigError
from core.io.envmap_file import read_envmap
from core.lighting.prior_gains import PriorGainSettings
from core.lighting.sky_evidence import SkyEvidence
from core.scene_graph import SceneGraph
from core.stages.chain import profile_settings
from core.stages.pbr import fit_lighting
from core.stages.pbr_settings import PBRStageConfig
from core.stages.volume import run_volume
from core.train.sky import SkyDome

pytestmark = pytest.mark.mitsuba


@pytest.fixture(scope="module")
def volume_dir(tiny_scene, tmp_path_factory):
    out = tmp_path_factory.mktemp("vol")
    cfg = replace(profile_settings("tiny", "volume"), iterations=40, densify_until=30)
    run_volume(open_bundle(tiny_scene), cfg, out, progress=False)
    return out


@pytest.fixture(scope="module")
def reconstruction(volume_dir):
    return SceneGraph.load(volume_dir / "checkpoint" / "scene_graph.pt")


def test_fit_improves_the_photometric_match_and_writes_outputs(tiny_scene, reconstruction, tmp_path):
    # the per-texel fit itself, from the prior as made (its gains, which take most of what the
    # fit would find on this scene, are tested below)
    cfg = replace(profile_settings("tiny", "pbr"), iterations=40, lr=0.05, prior_gains=PriorGainSettings(enabled=False))
    seen = []
    s = fit_lighting(reconstruction, open_bundle(tiny_scene), tmp_path, cfg,
                     on_progress=lambda it, n, rec: seen.append((it, n, rec["loss"])))
    assert [x[0] for x in seen] == list(range(1, 41)) and all(x[1] == 40 for x in seen)
    assert s["photometric_psnr_fitted"] > s["photometric_psnr_prior"] + 0.1, s
    photo = [h["photo"] for h in s["history"]]
    assert np.mean(photo[-8:]) < np.mean(photo[:8])
    for name in ("envmap.exr", "envmap_prior.exr", "preview.png", "summary.json"):
        assert (tmp_path / name).is_file(), name
    env = read_envmap(tmp_path / "envmap.exr")
    assert env.shape == (512, 1024, 3) and np.isfinite(env).all() and env.min() >= 0
    assert not np.allclose(env, read_envmap(tmp_path / "envmap_prior.exr"))  # the fit moved the map
    written = json.loads((tmp_path / "summary.json").read_text())
    assert "ground_truth" not in written  # the product path never reads the bundle's ground truth
    assert written["photometric_psnr_fitted"] == pytest.approx(s["photometric_psnr_fitted"])


def test_the_prior_gains_fit_the_capture_and_are_recorded(tiny_scene, reconstruction, tmp_path):
    """The prior's sun / sky gains (core.lighting.prior_gains) are searched before the fit; the
    rescaled prior matches the training frames no worse than the prior as made."""
    base = replace(profile_settings("tiny", "pbr"), iterations=0)
    on = fit_lighting(reconstruction, open_bundle(tiny_scene), tmp_path / "on", base)
    off = fit_lighting(reconstruction, open_bundle(tiny_scene), tmp_path / "off",
                       replace(base, prior_gains=PriorGainSettings(enabled=False)))
    g = on["prior_gains"]
    assert off["prior_gains"]["enabled"] is False
    if g["enabled"]:
        assert g["l1_best"] <= g["l1_prior"] and g["gain_sun"] > 0 and g["gain_sky"] > 0
        if g["applied"]:
            assert on["photometric_psnr_prior"] > off["photometric_psnr_prior"] - 0.05, (on, off)
            assert not np.allclose(read_envmap(tmp_path / "on" / "envmap_prior.exr"),
                                   read_envmap(tmp_path / "off" / "envmap_prior.exr"))
    else:
        assert g["why"] == "no sun in the prior"
    with pytest.raises(ConfigError, match="prior_gains"):
        replace(base, prior_gains={"enabled": True})


def test_zero_steps_return_the_prior(tiny_scene, reconstruction, tmp_path):
    cfg = replace(profile_settings("tiny", "pbr"), iterations=0, env_height=512)
    s = fit_lighting(reconstruction, open_bundle(tiny_scene), tmp_path, cfg)
    assert s["history"] == [] and s["photometric_psnr_fitted"] == pytest.approx(s["photometric_psnr_prior"])
    fitted, prior = read_envmap(tmp_path / "envmap.exr"), read_envmap(tmp_path / "envmap_prior.exr")
    np.testing.assert_allclose(fitted, np.maximum(prior, fitted.min()), rtol=1e-4, atol=1e-6)


@pytest.mark.parametrize("field,value", [("iterations", -1), ("pixels", 0), ("lr", 0.0), ("env_height", 4),
                                         ("lambda_e_end", -0.1), ("shadow_t_min_m", -0.1), ("normal_offset_m", 11.0),
                                         ("indirect_bounces", 17), ("indirect_bounces", 1.5), ("wall_min_gain", -0.01),
                                         ("indirect_specular_rays", -1), ("indirect_specular_rays", True)])
def test_bad_settings_name_the_field(field, value):
    with pytest.raises(ConfigError, match=field):
        PBRStageConfig(**{field: value})
    from core.stages.joint import JointSettings

    if field in ("shadow_t_min_m", "normal_offset_m", "indirect_bounces", "indirect_specular_rays"):
        with pytest.raises(ConfigError, match=field):
            JointSettings(**{field: value})


def test_the_sun_floor_holds_the_prior_sun_and_nothing_else():
    """``sun_floor``: a fit that dims the whole map keeps the prior's sun disc at its floor
    (``sun_floor`` x the prior there) and is free everywhere else; an observed, held sky texel
    keeps its evidence."""
    from core.lighting.prior import _sph, compose_envmap
    from core.stages.pbr import _sun_floor

    h = 64
    sun = _sph(0.7, 0.6)
    prior = compose_envmap(np.array([[0.0, -0.5, 0.0]] * 3), sun, np.array([3.0, 3.0, 3.0]), np.full(3, 0.2), h)
    cfg = PBRStageConfig(sun_floor=0.5)
    held, stats = _sun_floor(None, prior, sun, h, cfg)
    assert stats["enabled"] and stats["texels"] > 0
    dim = torch.log(torch.from_numpy(prior.astype(np.float64)) * 0.01)
    out = torch.exp(held.hold(dim)).numpy()
    peak = np.unravel_index(int(np.argmax(prior.mean(-1))), prior.shape[:2])
    assert out[peak].min() == pytest.approx(0.5 * prior[peak].min(), rel=1e-6)
    far = (0, 0)  # the map's top row, far from a sun 34 deg high
    assert out[far] == pytest.approx(0.01 * prior[far], rel=1e-6)
    # an evidence that holds a texel: the floor does not touch it
    w = torch.zeros(h, 2 * h, dtype=torch.float64)
    w[peak] = 1.0
    ev = SkyEvidence(torch.zeros(h, 2 * h, 3, dtype=torch.float64), w, torch.full((h, 2 * h), -30.0, dtype=torch.float64))
    held2, _ = _sun_floor(ev, prior, sun, h, cfg)
    assert float(held2.log_floor[peak]) == -30.0
    for bad in ({"sun_floor": -1.0}, {"sun_floor_deg": 0.0}):
        with pytest.raises(ConfigError, match="sun_floor"):
            PBRStageConfig(**bad)


def test_the_stages_trace_shadows_as_a_relight_does():
    """The map is fitted under the visibility and the indirect light it is rendered with."""
    from dataclasses import fields

    from core.render.scenario import Scenario
    from core.stages.joint import JointSettings

    sc = {f.name: f.default for f in fields(Scenario)}
    for cfg in (PBRStageConfig(), JointSettings()):
        assert cfg.shadow_t_min_m == sc["shadow_t_min_m"] and cfg.normal_offset_m == sc["normal_offset_m"]
        assert cfg.indirect_bounces == sc["indirect_bounces"] > 0
        assert cfg.indirect_specular_rays == sc["indirect_specular_rays"]
        assert cfg.pbr_settings().indirect_specular_rays == cfg.indirect_specular_rays


def test_wrong_settings_type(tiny_scene, reconstruction, tmp_path):
    with pytest.raises(ConfigError, match="cfg"):
        fit_lighting(reconstruction, open_bundle(tiny_scene), tmp_path, {"iterations": 3})


def test_the_observed_sky_is_held_in_the_fitted_map(tiny_scene, reconstruction, volume_dir, tmp_path):
    sky = SkyDome.from_state(torch.load(volume_dir / "checkpoint" / "sky.pt", weights_only=True)["sky"])
    cfg = replace(profile_settings("tiny", "pbr"), iterations=10, lr=0.2, coarse_lr=0.2, env_height=64)
    s = fit_lighting(reconstruction, open_bundle(tiny_scene), tmp_path, cfg, sky=sky)
    assert s["sky_evidence"]["enabled"] and s["sky_evidence"]["grid_texels_seen"] > 0, s["sky_evidence"]
    ev = SkyEvidence.load(tmp_path / "sky_evidence.npz").at(512)  # the stage's 64 rows, bilinear to the map's
    held = (ev.weight > 0.999).numpy()
    assert held.sum() > 100, s["sky_evidence"]
    fitted, prior = read_envmap(tmp_path / "envmap.exr"), read_envmap(tmp_path / "envmap_prior.exr")
    obs = np.exp(ev.log_radiance.numpy())
    # held texels keep the observed radiance through the fit; the fit moved the map elsewhere
    np.testing.assert_allclose(fitted[held], obs[held], rtol=1e-3)
    np.testing.assert_allclose(prior[held], obs[held], rtol=1e-3)
    assert not np.allclose(fitted[~held], prior[~held], rtol=0.05)
    # without the dome nothing is held
    s2 = fit_lighting(reconstruction, open_bundle(tiny_scene), tmp_path / "nodome", cfg)
    assert s2["sky_evidence"] == {"enabled": False, "why": "no sky dome"}
    assert not (tmp_path / "nodome" / "sky_evidence.npz").exists()
