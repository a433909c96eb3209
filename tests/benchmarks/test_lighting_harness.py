"""The lighting prior's ground-truth harness (``benchmarks/lighting_harness.py``): the prior on the
default scene's ground-truth G-buffers, with and without the street's true meshes as occluders
(measured errors recorded, regression bounds), and a bad occluder name."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from benchmarks.lighting_harness import estimate_from_bundle
from core.bundle import open_bundle
from core.errors import ConfigError
from core.lighting import prior as L

REPO = Path(__file__).resolve().parents[2]
SCENE = REPO / "data" / "scenes" / "default"


def test_oracle_occluders_find_the_sun_of_the_default_scene():
    """With the street's meshes as occluders (cast shadows), the default scene's sun (city.exr)
    is found within 2 degrees (measured 0.5), against 20 degrees without them."""
    est = estimate_from_bundle(SCENE, "train", occluders="oracle")

    # glossy and metallic pixels (use_materials) are left out of the shading fit
    plain = estimate_from_bundle(SCENE, "train", use_materials=False)
    assert 0 < est.diagnostics["surface_pixels"] < plain.diagnostics["surface_pixels"]

    gt = open_bundle(SCENE, validate=False).load_envmap()
    assert est.diagnostics["cast_shadows"] is True
    assert est.diagnostics["sun_model"] == "transport" and plain.diagnostics["sun_model"] == "lambert"
    assert 0.0 < est.diagnostics["interreflection_known_fraction"] < 1.0
    assert L.sun_direction_error_deg(est.sun_dir, L.brightest_direction(gt)) < 2.0
    with pytest.raises(ConfigError, match="occluders"):
        estimate_from_bundle(SCENE, "train", occluders="mesh")


def test_default_scene_estimate():
    """End to end on the bundled scene (city.exr: hazy, the sun carries ~20% of the light). With
    the scene's albedo/normals/depth standing in for the reconstruction the measured sun error is
    20 degrees (the issue's 10-degree target is NOT met on this map; see the module docstring)."""
    est = estimate_from_bundle(SCENE, "train")

    gt = open_bundle(SCENE, validate=False).load_envmap()
    err = L.sun_direction_error_deg(est.sun_dir, L.brightest_direction(gt))
    assert est.envmap.shape == (512, 1024, 3) and np.isfinite(est.envmap).all() and est.envmap.min() > 0
    assert est.sun_source in ("shading", "sky")
    assert err < 30.0, err  # regression bound around the measured 20.2 degrees
    le = L.envmap_log_error(est.envmap, gt)
    assert le["log_l1"] < 0.35  # measured 0.24
    assert np.all(est.sun_irradiance > 0)
