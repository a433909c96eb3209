"""Sky-patch transport of the lighting prior: the patch geometry, the transport integral against
its closed form, the sun search on model-consistent samples with a non-uniform sky (where the
uniform-dome model is misled), hit distances, the observed-radiance lookup, bad input."""

from __future__ import annotations

import math

import numpy as np
import pytest

from core.errors import ConfigError, NumericalError, ShapeError
from core.gen import lighting as L
from core.gen import sky_transport as T


def _wall_visibility(origins, dirs, t_max=None):
    """An opaque wall in the plane y = 0, |x| < 4, 0 < z < 6 (origins at y > 0)."""
    o, d = np.asarray(origins, np.float64), np.asarray(dirs, np.float64)
    sy = np.where(d[:, 1] < -1e-9, d[:, 1], -1.0)
    t = np.where(d[:, 1] < -1e-9, -o[:, 1] / sy, np.inf)
    p = o + d * np.where(np.isfinite(t), t, 0.0)[:, None]
    hit = np.isfinite(t) & (np.abs(p[:, 0]) < 4.0) & (p[:, 2] > 0) & (p[:, 2] < 6.0)
    if t_max is not None:
        hit &= t <= np.asarray(t_max, np.float64)
    return np.where(hit, 0.0, 1.0)


def test_patches_partition_the_upper_hemisphere():
    rng = np.random.default_rng(0)
    rays = T.patch_rays(4, 12, 16, rng)
    assert np.allclose(np.linalg.norm(rays, axis=-1), 1.0)
    idx = T.patch_of(rays, 4, 12)
    assert (idx == np.arange(48)[:, None]).all()
    assert (T.patch_of(np.array([[0.3, 0.2, -0.5]]), 4, 12) == -1).all()
    pairs = T.patch_neighbours(4, 12)
    assert len(pairs) == 4 * 12 + 3 * 12 and pairs.max() == 47


def test_unoccluded_transport_matches_the_closed_form():
    """A uniform sky of radiance 1 gives shading (1 + n_z) / 2 on a Lambertian surface."""
    rng = np.random.default_rng(1)
    n = rng.normal(size=(200, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    tr = T.SkyTransport(np.zeros((200, 3)), n, np.ones(200), None,
                        settings=T.TransportSettings(bands=8, sectors=24, rays_per_patch=32))
    np.testing.assert_allclose(tr.patch_T.sum(1), (1 + n[:, 2]) / 2, atol=0.01)
    assert tr.occluder_T.sum() == 0.0 and tr.known_fraction == 0.0


def test_transport_search_finds_the_sun_under_a_glowing_sky():
    """Samples beside a wall under a sky that is ten times brighter on one side (a sunset glow,
    away from the sun), rendered with the transport model itself plus 3% noise: the transport
    search finds the sun; the uniform-dome model is pulled towards the glow."""
    rng = np.random.default_rng(2)
    m = 2500
    pts = np.stack([rng.uniform(-12, 12, m), rng.uniform(0.3, 10, m), np.zeros(m)], 1)
    n = rng.normal(size=(m, 3))
    n[:, 2] = np.abs(n[:, 2]) + 0.3
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    pts = pts + n * 0.05
    truth = T.SkyTransport(pts, n, np.ones(m), _wall_visibility,
                           settings=T.TransportSettings(rays_per_patch=16, seed=5))
    centres = T.patch_rays(4, 12, 1, np.random.default_rng(0))[:, 0]
    sky = 0.3 + 3.0 * np.maximum(centres @ np.array([1.0, 0.0, 0.0]), 0) ** 4  # glow towards +x
    sun = L._sph(math.radians(-100.0), math.radians(40.0))
    shade = truth.patch_T @ sky + 2.0 * truth.sun_columns(sun[None])[:, 0]
    shade *= np.exp(rng.normal(0, 0.03, m))
    tr = T.SkyTransport(pts, n, shade, _wall_visibility, settings=T.TransportSettings(occluder_radiance=False))
    found, _, diag = L._search_sun(L._transport_score(tr), L.LightingSettings())
    assert L.sun_direction_error_deg(found, sun) < 4.0
    assert diag["shading_contrast"] > 0.05

    def vis_of(dirs):
        dirs = np.asarray(dirs, np.float64).reshape(-1, 3)
        return np.stack([_wall_visibility(pts, np.broadcast_to(d, pts.shape)) for d in dirs])
    dome, _, _ = L._search_sun(L._lambert_score(n, shade, vis_of), L.LightingSettings())
    assert L.sun_direction_error_deg(dome, sun) > L.sun_direction_error_deg(found, sun) + 5.0


def test_hit_distance_and_observed_radiance():
    tr = T.SkyTransport(np.array([[0.0, 5.0, 0.5]]), np.array([[0.0, 0.0, 1.0]]), np.ones(1), _wall_visibility)
    t = tr._hit_distance(np.array([[0.0, 5.0, 1.0], [1.0, 2.0, 1.0]]), np.array([[0.0, -1.0, 0.0], [0.0, -0.6, 0.8]]))
    np.testing.assert_allclose(t, [5.0, 2.0 / 0.6], rtol=0.04)
    # a camera at the origin looking +x at a wall x = 10 seen with radiance 0.7 (OpenCV frame)
    c2w = np.eye(4)
    c2w[:3, :3] = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    depth = np.full((1, 20, 30), 10.0)
    rad = np.full((1, 20, 30), 0.7)
    invalid = np.zeros((1, 20, 30), bool)
    invalid[0, :, :5] = True
    look = L.observed_radiance_lookup(c2w[None], (15.0, 15.0, 15.0, 10.0), depth, rad, invalid)
    val, known = look(np.array([[10.0, 0.0, 0.0], [6.0, 0.0, 0.0], [-10.0, 0.0, 0.0], [10.0, 8.0, 0.0]]))
    assert known.tolist() == [True, False, False, False]  # off the surface, behind, masked
    assert val[0] == pytest.approx(0.7)


def test_mostly_clipped_patch_is_a_lower_bound():
    """A patch seen mostly clipped bounds its radiance from below (the fit may go above, never
    below); a patch seen unclipped is held near its median."""
    rng = np.random.default_rng(3)
    n = np.tile([0.0, 0.0, 1.0], (300, 1))
    sky = T.patch_rays(4, 12, 40, rng)  # 40 directions in every patch
    rad = np.full(sky.shape[:2], 0.5)
    clipped = np.zeros(sky.shape[:2], bool)
    clipped[3] = True  # patch 3: every pixel clipped at 0.9
    rad[3] = 0.9
    truth = np.full(48, 0.5)
    truth[3] = 1.2  # brighter than its clip level
    shade = T.SkyTransport(np.zeros((300, 3)), n, np.ones(300)).patch_T @ truth
    tr = T.SkyTransport(np.zeros((300, 3)), n, shade, None, sky.reshape(-1, 3), rad.reshape(-1),
                        sky_clipped=clipped.reshape(-1))
    assert tr.lower[3] == pytest.approx(0.9) and 3 not in tr.observed.tolist() and len(tr.observed) == 47
    _, x = tr.fit(np.zeros(300))
    assert x[3] >= 0.9 - 1e-9 and np.all(x >= -1e-12)
    assert abs(np.median(x[tr.observed]) - 0.5) < 0.05


def test_interreflection_as_seen_or_scaled():
    """With ``free_interreflection_scale=False`` the interreflection the frames saw is a known
    term (scale 1, subtracted from the shading); with True its scale is fitted."""
    rng = np.random.default_rng(4)
    m = 400
    pts = np.stack([rng.uniform(-3, 3, m), rng.uniform(0.5, 4, m), rng.uniform(0.2, 3, m)], 1)
    n = np.tile([0.0, 0.0, 1.0], (m, 1))

    def seen(points):  # the wall as the frames saw it: radiance 0.4 everywhere
        return np.full(len(points), 0.4), np.ones(len(points), bool)

    kw = dict(visibility=_wall_visibility, radiance_at=seen)
    fixed = T.SkyTransport(pts, n, np.ones(m), settings=T.TransportSettings(free_interreflection_scale=False), **kw)
    assert fixed.indirect.max() > 0.01 and fixed.known_fraction == 1.0
    sky = np.full(48, 0.6)
    with_ir = fixed.patch_T @ sky + fixed.indirect
    res_fixed, x_fixed = fixed.fit(np.zeros(m), shading=with_ir)
    assert res_fixed < 1e-3 and x_fixed[-3] == 1.0
    # shading without the interreflection: the fixed model cannot drop it, the free one can
    no_ir = fixed.patch_T @ sky
    res_fixed_no, _ = fixed.fit(np.zeros(m), shading=no_ir)
    free = T.SkyTransport(pts, n, np.ones(m), settings=T.TransportSettings(free_interreflection_scale=True), **kw)
    res_free_no, x_free = free.fit(np.zeros(m), shading=no_ir)
    assert res_free_no < 1e-3 and x_free[-3] < 0.05
    assert res_fixed_no > 10 * res_free_no


def test_bad_input():
    with pytest.raises(ConfigError, match="sectors"):
        T.TransportSettings(sectors=2)
    with pytest.raises(ConfigError, match="weights"):
        T.TransportSettings(smoothness=-1.0)
    with pytest.raises(ShapeError, match="points"):
        T.SkyTransport(np.zeros((5, 3)), np.zeros((4, 3)), np.ones(5))
    with pytest.raises(NumericalError, match="shading"):
        T.SkyTransport(np.zeros((2, 3)), np.tile([0.0, 0.0, 1.0], (2, 1)), np.array([1.0, np.nan]))
    with pytest.raises(ConfigError, match="visibility"):
        T.SkyTransport(np.zeros((2, 3)), np.tile([0.0, 0.0, 1.0], (2, 1)), np.ones(2),
                       lambda o, d, t_max=None: np.full(len(o), np.nan))
    with pytest.raises(ConfigError, match="sun_model"):
        L.LightingSettings(sun_model="learned")
