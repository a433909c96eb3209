"""Lighting prior: exact sun composition, the shading fit on model-consistent data, the default
scene end to end (measured error recorded, regression bound), bad input."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from core.camera import Camera
from core.conventions import envmap_solid_angles
from core.errors import ConfigError, NumericalError, ShapeError
from core.lighting import prior as L

REPO = Path(__file__).resolve().parents[3]
SCENE = REPO / "data" / "scenes" / "default"


def test_compose_envmap_sun_irradiance_is_exact():
    sun = L._sph(math.radians(40.0), math.radians(30.0))
    coeffs = np.array([[0.0, -0.5, 0.0]] * 3)
    e_sun = np.array([5.0, 4.0, 3.0])
    no_sun = L.compose_envmap(coeffs, sun, np.zeros(3), np.ones(3) * 0.1, 128)
    env = L.compose_envmap(coeffs, sun, e_sun, np.ones(3) * 0.1, 128)
    sa = envmap_solid_angles(128, 256)[:, None, None]
    got = ((env - no_sun) * sa).sum((0, 1))
    assert np.allclose(got, e_sun, rtol=1e-5)
    assert L.sun_direction_error_deg(L.brightest_direction(env), sun) < 2.0
    assert L.envmap_log_error(env, env)["log_l1"] == 0.0



def test_sky_statistics_of_a_sun_over_a_uniform_sky():
    """A unit-radiance upper hemisphere (horizontal irradiance pi) plus a 1-degree disc of normal
    irradiance 2 pi at 30 degrees elevation: direct fraction pi / (pi + pi) = 1/2 (up to the
    sky the disc covers); overcast (no disc): close to 0."""
    from core.conventions import envmap_directions

    h = 256
    dirs = envmap_directions(h, 2 * h)
    env = np.repeat((dirs[..., 2:] > 0).astype(np.float64), 3, -1)
    overcast = L.sky_statistics(env)
    assert overcast["direct_fraction"] < 0.01 and overcast["sun_share"] < 0.01
    sun = L._sph(math.radians(70.0), math.radians(30.0))
    disc = dirs @ sun >= math.cos(math.radians(1.0))
    omega = np.repeat(envmap_solid_angles(h, 2 * h)[:, None], 2 * h, 1)
    env[disc] = 2 * math.pi / np.sum(omega[disc] * (dirs[disc] @ sun))
    st = L.sky_statistics(env)
    assert st["sun_elevation_deg"] == pytest.approx(30.0, abs=1.0)  # a pixel of the 1-degree disc
    assert st["direct_fraction"] == pytest.approx(0.5, abs=0.01)
    assert st["sun_share"] == pytest.approx(2 * math.pi / (2 * math.pi + 2 * math.pi), abs=0.01)
    with pytest.raises(ShapeError, match="env"):
        L.sky_statistics(np.ones((4, 4, 3)))


def test_shading_fit_recovers_sun_on_lambertian_samples():
    """Samples that follow the model exactly (plus 3% noise): the search must find the sun."""
    rng = np.random.default_rng(1)
    n = rng.normal(size=(3000, 3))
    n[:, 2] = np.abs(n[:, 2]) * 0.5
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    sun = L._sph(math.radians(-126.0), math.radians(47.6))
    shade = 0.2 + 0.3 * (1 + n[:, 2]) / 2 + 1.5 * np.maximum(n @ sun, 0)
    shade *= np.exp(rng.normal(0, 0.03, len(shade)))
    found, res, diag = L._search_sun(L._lambert_score(n, shade), L.LightingSettings())
    assert L.sun_direction_error_deg(found, sun) < 3.0
    assert diag["shading_contrast"] > 0.2


def _wall_shadow(pts):
    """``vis_of(dirs [K, 3]) -> [K, N]``: visibility of ground points ``pts`` [N, 3] (z = 0,
    y > 0) beside a wall 8 m long (|x| < 4) and 6 m high in the plane y = 0."""
    def vis_of(dirs):
        dirs = np.asarray(dirs, np.float64).reshape(-1, 3)
        sx, sy, sz = dirs[:, 0:1], dirs[:, 1:2], dirs[:, 2:3]
        t = np.where(sy < -1e-9, -pts[None, :, 1] / np.where(sy < -1e-9, sy, -1.0), 1e9)
        hit = (t * sz < 6.0) & (np.abs(pts[None, :, 0] + t * sx) < 4.0)
        return np.where(hit, 0.0, 1.0)
    return vis_of


def test_cast_shadows_identify_the_sun_azimuth_on_a_flat_ground():
    """A flat ground beside a wall 8 m long and 6 m high: shading alone cannot tell the sun's
    azimuth (n . s is the same for every azimuth), the wall's shadow can. The visibility cue
    must find the sun."""
    rng = np.random.default_rng(2)
    pts = np.stack([rng.uniform(-15, 15, 3000), rng.uniform(0.3, 12, 3000), np.zeros(3000)], 1)
    n = np.tile([0.0, 0.0, 1.0], (3000, 1))

    vis_of = _wall_shadow(pts)

    sun = L._sph(math.radians(-110.0), math.radians(35.0))
    shade = 0.2 + 0.3 + 1.5 * vis_of(sun)[0] * max(sun[2], 0.0)
    shade *= np.exp(rng.normal(0, 0.03, len(shade)))
    found, _, diag = L._search_sun(L._lambert_score(n, shade, vis_of), L.LightingSettings())
    assert L.sun_direction_error_deg(found, sun) < 3.0
    flat, _, _ = L._search_sun(L._lambert_score(n, shade), L.LightingSettings())  # no shadow model: azimuth unknown
    assert L.sun_direction_error_deg(flat, sun) > L.sun_direction_error_deg(found, sun) + 10.0


def test_bad_inputs():
    t, h, w = 2, 8, 12
    frames = np.full((t, h, w, 3), 0.5, np.float32)
    one = Camera.from_intrinsics(np.eye(4), 10, 10, 6, 4, w, h)
    cams = Camera.stack([one] * t)
    sky = np.zeros((t, h, w), bool)
    depth = np.ones((t, h, w), np.float32)
    normals = np.zeros((t, h, w, 3), np.float32)
    with pytest.raises(ShapeError, match="sky_masks"):
        L.estimate_lighting(frames, cams, sky[:, :4], depth, normals)
    with pytest.raises(ShapeError, match="roughness"):
        L.estimate_lighting(frames, cams, sky, depth, normals, roughness=np.ones((t, h, w - 1)))
    # the cameras: one per frame, of the frames' image size, a batch or a list of Camera
    with pytest.raises(ShapeError, match="cameras: expected a batch of 2"):
        L.estimate_lighting(frames, one, sky, depth, normals)
    with pytest.raises(ShapeError, match="cameras: expected 2 cameras"):
        L.estimate_lighting(frames, Camera.stack([one] * 3), sky, depth, normals)
    with pytest.raises(ShapeError, match="cameras: image size 12x9"):
        L.estimate_lighting(frames, Camera.stack([Camera.from_intrinsics(np.eye(4), 10, 10, 6, 4, w, h + 1)] * t),
                            sky, depth, normals)
    with pytest.raises(ConfigError, match="cameras"):
        L.estimate_lighting(frames, np.stack([np.eye(4)] * t), sky, depth, normals)
    with pytest.raises(ConfigError, match="cameras"):
        L.estimate_lighting(frames, (10, 10, 6, 4), sky, depth, normals)
    metal = np.zeros((t, h, w, 1), np.float32)
    metal[1, 2, 3] = np.inf
    with pytest.raises(NumericalError, match="metallic"):
        L.estimate_lighting(frames, [one] * t, sky, depth, normals, metallic=metal)
    frames[0, 0, 0, 0] = np.nan
    with pytest.raises(NumericalError, match="frames"):
        L.estimate_lighting(frames, cams, sky, depth, normals)


def test_basin_search_ignores_a_narrow_valley_far_from_the_low_region():
    """A broad low region around the sun and one deeper, narrow valley far from it (noise of a
    reconstruction's landscape, on a coarse grid point): the plain search takes the valley, the
    basin search (``basin_quantile``) stays in the low region and finds the sun."""
    sun = L._sph(math.radians(60.0), math.radians(45.0))
    spur = L._sph(math.radians(-140.0), math.radians(18.0))  # a point of the 8-degree coarse grid

    def score(cands):
        c = np.asarray(cands, np.float64).reshape(-1, 3)
        to_sun = np.degrees(np.arccos(np.clip(c @ sun, -1, 1)))
        to_spur = np.degrees(np.arccos(np.clip(c @ spur, -1, 1)))
        return 0.5 + 0.5 * to_sun / 180.0 - 0.45 * np.exp(-(to_spur / 2.0) ** 2)

    plain, _, _ = L._search_sun(score, L.LightingSettings())
    assert L.sun_direction_error_deg(plain, spur) < 2.0
    found, _, diag = L._search_sun(score, L.LightingSettings(basin_quantile=0.05))
    assert L.sun_direction_error_deg(found, sun) < 2.0
    assert L.sun_direction_error_deg(np.asarray(diag["basin_centroid"]), sun) < 15.0
    with pytest.raises(ConfigError, match="basin_quantile"):
        L.LightingSettings(basin_quantile=1.0)


def test_colour_cue_finds_the_sun_through_a_grey_albedo_error():
    """The wall-and-ground scene of the cast-shadow test, shaded per channel by a blue sky and a
    warm sun, seen through a reconstruction's albedo that is off by a large grey factor per sample
    (log-normal, sigma 0.6) and brighter where the sun falls (the sun baked in, x2.8: as bright as
    the sun makes it): the luminance of radiance / albedo no longer shows the shadow, its red/blue ratio still does.
    With ``chroma_weight`` the search must find the sun, and do better than without it."""
    rng = np.random.default_rng(3)
    m = 4000
    pts = np.stack([rng.uniform(-15, 15, m), rng.uniform(0.3, 12, m), np.zeros(m)], 1)
    n = np.tile([0.0, 0.0, 1.0], (m, 1))

    vis_of = _wall_shadow(pts)

    sun = L._sph(math.radians(-110.0), math.radians(35.0))
    lit = vis_of(sun)[0] * max(sun[2], 0.0)
    shade_rgb = np.array([0.30, 0.40, 0.55]) + np.array([1.6, 1.4, 1.0]) * lit[:, None]   # radiance / true albedo
    grey = np.exp(rng.normal(0, 0.6, m)) * np.where(lit > 0, 2.8, 1.0)                    # albedo error
    seen = shade_rgb / grey[:, None] * np.exp(rng.normal(0, 0.02, (m, 3)))
    lum = seen.mean(1)
    chroma = np.log(seen[:, 0]) - np.log(seen[:, 2])
    s = L.LightingSettings()
    with_c, _, _ = L._search_sun(L._lambert_score(n, lum, vis_of, chroma, chroma_weight=1.0), s)
    without, _, _ = L._search_sun(L._lambert_score(n, lum, vis_of), s)
    assert L.sun_direction_error_deg(with_c, sun) < 3.0
    assert L.sun_direction_error_deg(without, sun) > L.sun_direction_error_deg(with_c, sun) + 10.0
    # a cue whose sunlit side is bluer than the shade is no evidence: the score ignores it
    flat = L._lambert_score(n, lum, vis_of, -chroma, chroma_weight=1.0)(sun[None])[0]
    plain = L._lambert_score(n, lum, vis_of)(sun[None])[0] / L._null_residual(n, lum)
    assert flat == pytest.approx(min(plain, 1.0) + 1.0)
    with pytest.raises(ConfigError, match="chroma_weight"):
        L.LightingSettings(chroma_weight=-1.0)


def test_transport_search_in_the_lambert_suns_cone():
    """``sun_model="lambert+transport"``'s second step: the transport landscape's deepest point
    lies outside the cone around the lambert sun and is ignored; within the cone the transport
    minimum (a low sun under the lambert sun's too-high guess) is found; a cone with no
    candidate that has a sun term keeps the lambert sun."""
    lam_sun = L._sph(math.radians(190.0), math.radians(27.0))  # the lambert search's answer
    low_sun = L._sph(math.radians(184.0), math.radians(8.0))  # 19.6 deg from it, inside 30 deg
    far = L._sph(math.radians(40.0), math.radians(50.0))  # deeper, but far outside the cone

    def score(cands):
        c = np.asarray(cands, np.float64).reshape(-1, 3)
        to_low = np.degrees(np.arccos(np.clip(c @ low_sun, -1, 1)))
        to_far = np.degrees(np.arccos(np.clip(c @ far, -1, 1)))
        return 0.5 + 0.3 * (1 - np.exp(-(to_low / 10.0) ** 2)) - 0.45 * np.exp(-(to_far / 10.0) ** 2)

    s = L.LightingSettings(sun_model="lambert+transport", transport_cone_deg=30.0, basin_quantile=0.05)
    diag: dict = {}
    got = L._transport_in_cone(score, lam_sun, s, diag)
    assert L.sun_direction_error_deg(got, low_sun) < 1.5
    assert diag["transport_search"]["used"] and diag["transport_search"]["moved_deg"] > 15.0
    # the unrestricted transport search would have taken the far valley
    plain, _, _ = L._search_sun(score, L.LightingSettings())
    assert L.sun_direction_error_deg(plain, far) < 2.0
    # no candidate with a sun term in the cone: the lambert sun stays
    diag = {}
    kept = L._transport_in_cone(lambda c: np.full(len(np.asarray(c).reshape(-1, 3)), np.inf), lam_sun, s, diag)
    assert L.sun_direction_error_deg(kept, lam_sun) < 1e-9 and not diag["transport_search"]["used"]
    with pytest.raises(ConfigError, match="transport_cone_deg"):
        L.LightingSettings(transport_cone_deg=0.0)
    with pytest.raises(ConfigError, match="sun_model"):
        L.LightingSettings(sun_model="hybrid")
