"""The Scenario value (core.render.scenario): validation names the field; the night sky is the
reconstruction's own or a stated fallback, never the bundle's ground truth."""

from __future__ import annotations

import numpy as np
import pytest

from core.camera import Camera
from core.errors import ConfigError
from core.relight import View
from core.render.scenario import FALLBACK_SKY_RADIANCE, LightSpec, Scenario, scene_sky
from core.stages.chain import RunDir

VIEW = View(Camera.from_intrinsics(np.eye(4), 30.0, 30.0, 16.0, 12.0, 32, 24), 0.0, "v0")
ENV = np.ones((8, 16, 3), np.float32)


@pytest.mark.parametrize("field,value", [("normal_offset_m", -0.1), ("shadow_t_min_m", float("nan")),
                                         ("object_shadow_t_min_m", -0.01), ("object_shadow_t_min_m", float("nan")),
                                         ("object_shadow_t_min_m", None), ("object_shadow_t_min_m", True),
                                         ("rotation_deg", float("inf")), ("exposure_ev", 40.0),
                                         ("denoiser", "magic"), ("rays_per_pixel", 0), ("sky_scale", -1.0)])
def test_bad_fields_are_named(field, value):
    with pytest.raises(ConfigError, match=field):
        Scenario(views=(VIEW,), envmap=ENV, **{field: value})


def test_envmap_and_views_are_checked():
    with pytest.raises(ConfigError, match="envmap"):
        Scenario(views=(VIEW,), envmap=np.ones((8, 8, 3), np.float32))
    bad = ENV.copy()
    bad[0, 0, 0] = np.nan
    with pytest.raises(ConfigError, match="envmap"):
        Scenario(views=(VIEW,), envmap=bad)
    with pytest.raises(ConfigError, match="views"):
        Scenario(views=(), envmap=ENV)


@pytest.mark.parametrize("d,field", [({"kind": "lamp", "position": [0, 0, 1], "intensity": 10}, "kind"),
                                     ({"kind": "point", "position": [0, 0], "intensity": 10}, "position"),
                                     ({"kind": "point", "position": [0, 0, 1], "intensity": -1}, "intensity"),
                                     ({"kind": "spot", "position": [0, 0, 1], "intensity": 1}, "direction"),
                                     ({"kind": "point", "position": [0, 0, 1], "intensity": 1, "x": 1}, "unknown")])
def test_light_specs_name_the_bad_field(d, field):
    with pytest.raises(ConfigError, match=field):
        LightSpec.from_dict(d, "lights[0]")


def test_night_sky_without_a_pbr_stage_is_a_stated_grey_sky(small_bundle, tmp_path):
    run = RunDir.create(tmp_path / "r", small_bundle, "tiny")
    env, note = scene_sky(run)
    assert env.shape == (512, 1024, 3) and np.all(env == FALLBACK_SKY_RADIANCE)
    assert "no recovered sky" in note
