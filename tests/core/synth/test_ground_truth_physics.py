"""Physical sanity of the Mitsuba ground truth (issue: foundation, 'Done when')."""

from __future__ import annotations

import math

import numpy as np
import pytest

from core.camera import Camera
from core.conventions import look_at, pixel_to_direction, project_points
from core.synth import geometry as geo
from core.synth.generate import load_envmap
from core.synth.mitsuba_backend import render_beauty
from core.synth.street import Material, Part

pytestmark = pytest.mark.mitsuba

ROAD = Material("asphalt", (0.3, 0.3, 0.3), 0.9, 0.0, model="lambert")


def _sun_direction(env: np.ndarray) -> np.ndarray:
    lum = env.sum(-1)
    r, c = np.unravel_index(np.argmax(lum), lum.shape)
    return pixel_to_direction(r, c, *lum.shape)


@pytest.mark.parametrize("rotation_deg", [0.0, 90.0, 215.0])
def test_road_shadow_falls_away_from_the_sun(rotation_deg):
    """A box on a sun-lit road: the road on the side away from the envmap's brightest pixel is in
    shadow, the side toward it is lit (city.exr, peak ~3.5e4, at three rotations)."""
    env = load_envmap("city", rotation_deg)
    sun = _sun_direction(env)
    elev = math.degrees(math.asin(sun[2]))
    assert 5 < elev < 70, elev  # the sun is above the horizon and casts a visible shadow
    sun_h = np.array([sun[0], sun[1], 0.0])
    sun_h /= np.linalg.norm(sun_h)
    road = Part("road", *geo.quad([(-20, -20, 0), (20, -20, 0), (20, 20, 0), (-20, 20, 0)]), ROAD)
    block = Part("block", *geo.box((0, 0, 1.5), (1.0, 1.0, 3.0)), ROAD)
    # camera high above, looking straight down (small tilt so look_at's up vector is defined)
    cam = Camera.from_intrinsics(look_at([0.0, -0.01, 25.0], [0.0, 0.0, 0.0]), 80.0, 80.0, 32.0, 32.0, 64, 64)
    img = render_beauty([road, block], env, cam, spp=32, max_depth=2, seed=1).mean(-1)
    d = 1.3  # metres from the box centre, just outside it
    pts = np.array([-sun_h * d, sun_h * d])  # away from the sun, toward the sun
    uv, _ = project_points(pts, cam.cam_to_world, cam.fx, cam.fy, cam.cx, cam.cy)
    vals = [img[int(v), int(u)] for u, v in uv]
    shadow, lit = vals
    # the road beside the box, perpendicular to the sun: lit by the sun too
    perp = np.array([-sun_h[1], sun_h[0], 0.0])
    uv2, _ = project_points(np.array([perp * d, -perp * d]), cam.cam_to_world, cam.fx, cam.fy, cam.cx, cam.cy)
    side = [img[int(v), int(u)] for u, v in uv2]
    print(rotation_deg, shadow, lit, side)
    # city's sun is hazy: the sky alone gives about half of the lit radiance
    assert shadow < 0.7 * lit, (rotation_deg, shadow, lit)
    assert shadow < 0.7 * min(side), (rotation_deg, shadow, side)
    # and it is the sun, not the box, that darkens: the point toward the sun is not shadowed
    assert lit > 0.8 * max(side), (lit, side)


def test_white_lambertian_plane_under_unit_environment():
    """A white Lambertian plane under a constant environment of radiance 1 renders to 1 (2%)."""
    white = Material("white", (1.0, 1.0, 1.0), 1.0, 0.0, model="lambert")
    plane = Part("plane", *geo.quad([(-50, -50, 0), (50, -50, 0), (50, 50, 0), (-50, 50, 0)]), white)
    env = np.ones((64, 128, 3), np.float32)
    cam = Camera.from_intrinsics(look_at([0.0, -0.01, 2.0], [0.0, 0.0, 0.0]), 40.0, 40.0, 16.0, 16.0, 32, 32)
    img = render_beauty([plane], env, cam, spp=64, max_depth=2, seed=3)
    assert abs(img.mean() - 1.0) < 0.02, img.mean()
