"""The observed sky held in the recovered map (core.lighting.sky_evidence)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from core.camera import Camera
from core.conventions import direction_to_pixel, envmap_directions, look_at
from core.errors import ConfigError, FormatError, ShapeError
from core.lighting.sky_evidence import SkyEvidence, SkyEvidenceSettings, hold_observed, observed_sky
from core.numerics import LOG_RADIANCE_FLOOR
from core.train.sky import SkyDome

EXPOSURE, GAMMA = 0.5, 2.2


def _dome(value_of_dir) -> SkyDome:
    """A dome whose texels hold ``value_of_dir(dirs [H, W, 3]) -> [H, W, 3]`` in (0, 1)."""
    d = SkyDome(64, 128)
    v = np.clip(value_of_dir(envmap_directions(64, 128)), 1e-4, 1 - 1e-4)
    with torch.no_grad():
        d.logits.copy_(torch.logit(torch.from_numpy(v).float()))
    return d


def _camera_up(pitch_deg: float = 30.0) -> Camera:
    """A 128x96 camera looking north, tilted up by ``pitch_deg`` (0.5 deg a pixel: several pixels
    per texel of the 128-row coverage grid)."""
    t = math.radians(pitch_deg)
    pose = look_at(np.zeros(3), np.array([0.0, math.cos(t), math.sin(t)]))
    return Camera.from_intrinsics(pose, 120.0, 120.0, 64.0, 48.0, 128, 96)


def test_seen_unclipped_sky_is_held_at_the_dome_radiance_and_the_rest_is_free():
    dome = _dome(lambda d: 0.3 + 0.4 * d[..., 2:3].clip(0, 1) * np.array([0.5, 0.8, 1.0]))
    cam = _camera_up()
    mask = np.zeros((96, 128), bool)
    mask[:48] = True  # the upper half of the frame is sky
    rad, w, floor, stats = observed_sky(dome, [cam], [mask], height=64, exposure=EXPOSURE, gamma=GAMMA)
    assert rad.shape == (64, 128, 3) and w.shape == floor.shape == (64, 128)
    assert stats["grid_texels_seen"] > 0 and stats["grid_texels_clipped"] == 0
    # the centre of the seen region: fully held, at dome^gamma / exposure
    sky_dirs = cam.ray_directions()[:48]
    r, c = direction_to_pixel(sky_dirs[24, 64], 64, 128)
    assert w[r, c] == pytest.approx(1.0)
    ldr = dome(torch.from_numpy(envmap_directions(64, 128)[r, c]).float()).detach().double().numpy()
    np.testing.assert_allclose(rad[r, c], ldr ** GAMMA / EXPOSURE, rtol=1e-5)
    # what the frame did not see (behind the camera, below the horizon) is not held
    r2, c2 = direction_to_pixel(np.array([0.0, -1.0, 0.2]), 64, 128)
    r3, c3 = direction_to_pixel(np.array([0.0, 1.0, -0.5]), 64, 128)
    assert w[r2, c2] == 0 and w[r3, c3] == 0 and (floor == 0).all()
    assert np.isfinite(rad).all() and ((w >= 0) & (w <= 1)).all()


def test_clipped_sky_is_a_floor_not_a_value():
    dome = _dome(lambda d: np.where(d[..., 0:1] > 0, 0.999, 0.4) * np.ones(3))  # east half clipped
    cam = _camera_up()
    mask = np.ones((96, 128), bool)
    rad, w, floor, stats = observed_sky(dome, [cam], [mask], height=64, exposure=EXPOSURE, gamma=GAMMA)
    assert stats["grid_texels_clipped"] > 0 and stats["grid_texels_seen"] > 0
    clipped = floor > 0
    assert clipped.any() and (w[clipped] == 0).all()
    np.testing.assert_allclose(floor[clipped], 0.98 ** GAMMA / EXPOSURE)
    # held: a fit below the floor is lifted to it, one above is kept
    ev = SkyEvidence.from_observed(rad, w, floor)
    low = torch.full((64, 128, 3), math.log(1e-3), dtype=torch.float64)
    high = torch.full((64, 128, 3), math.log(1e3), dtype=torch.float64)
    r, c = np.argwhere(clipped)[0]
    assert float(ev.hold(low)[r, c, 0]) == pytest.approx(math.log(0.98 ** GAMMA / EXPOSURE))
    assert float(ev.hold(high)[r, c, 0]) == pytest.approx(math.log(1e3))


def test_hold_passes_gradient_only_where_unseen():
    log_fit = torch.zeros(4, 8, 3, dtype=torch.float64, requires_grad=True)
    w = torch.zeros(4, 8, dtype=torch.float64)
    w[1, 2], w[1, 3] = 1.0, 0.25
    out = hold_observed(log_fit, torch.full((4, 8, 3), 2.0, dtype=torch.float64), w)
    out.sum().backward()
    assert float(out.detach()[1, 2, 0]) == 2.0 and float(out.detach()[1, 3, 0]) == pytest.approx(0.5)
    g = log_fit.grad[..., 0]
    assert float(g[1, 2]) == 0.0 and float(g[1, 3]) == pytest.approx(0.75) and float(g[0, 0]) == 1.0
    with pytest.raises(ShapeError, match="weight"):
        hold_observed(log_fit, log_fit, w[:2])


def test_disabled_holds_nothing_and_bad_settings_name_the_field():
    dome = _dome(lambda d: 0.4 * np.ones_like(d))
    rad, w, floor, _ = observed_sky(dome, [_camera_up()], [np.ones((96, 128), bool)], height=32, exposure=1.0,
                                    gamma=2.2, settings=SkyEvidenceSettings(enabled=False))
    assert not w.any() and not floor.any()
    assert SkyEvidence.from_observed(rad, w, floor).empty
    for field, value in (("grid_height", 2), ("clip", 0.0), ("feather_texels", -1), ("enabled", "yes")):
        with pytest.raises(ConfigError, match=field):
            SkyEvidenceSettings(**{field: value})
    with pytest.raises(ShapeError, match="sky_masks"):
        observed_sky(dome, [_camera_up()], [np.ones((10, 10), bool)], height=32, exposure=1.0, gamma=2.2)


def test_save_load_and_resample(tmp_path):
    dome = _dome(lambda d: 0.2 + 0.5 * d[..., 2:3].clip(0, 1) * np.ones(3))
    mask = np.zeros((96, 128), bool)
    mask[:60] = True
    ev = SkyEvidence.from_observed(*observed_sky(dome, [_camera_up()], [mask], height=64, exposure=EXPOSURE,
                                                 gamma=GAMMA)[:3])
    ev.save(tmp_path / "ev.npz")
    back = SkyEvidence.load(tmp_path / "ev.npz")
    np.testing.assert_allclose(back.weight.numpy(), ev.weight.numpy(), atol=1e-6)
    np.testing.assert_allclose(back.log_radiance.numpy(), ev.log_radiance.numpy(), rtol=1e-5, atol=1e-5)
    low = ev.at(16)
    assert low.log_radiance.shape == (16, 32, 3) and low.weight.shape == (16, 32)
    assert float(low.weight.max()) <= 1.0 and float(low.weight.max()) > 0
    assert bool(torch.isfinite(low.log_floor).all()) and float(low.log_floor.min()) >= math.log(LOG_RADIANCE_FLOOR) - 1e-9
    (tmp_path / "bad.npz").write_bytes(b"not an npz")
    with pytest.raises(FormatError, match="bad.npz"):
        SkyEvidence.load(tmp_path / "bad.npz")
