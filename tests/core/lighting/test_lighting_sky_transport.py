"""Sky-patch transport of the lighting prior: the patch geometry, the transport integral against
its closed form, the sun search on model-consistent samples with a non-uniform sky (where the
uniform-dome model is misled), hit distances, the observed-radiance lookup, bad input."""

from __future__ import annotations

import math

import numpy as np
import pytest

from core.camera import Camera
from core.errors import ConfigError, NumericalError, ShapeError
from core.lighting import prior as L
from core.lighting import sky_transport as T


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
    cam = Camera.from_intrinsics(c2w, 15.0, 15.0, 15.0, 10.0, 30, 20)
    pts = np.array([[10.0, 0.0, 0.0], [6.0, 0.0, 0.0], [-10.0, 0.0, 0.0], [10.0, 8.0, 0.0]])
    for cams in (Camera.stack([cam]), [cam]):  # a batch of one camera per frame, or their list
        val, known = L.observed_radiance_lookup(cams, depth, rad, invalid)(pts)
        assert known.tolist() == [True, False, False, False]  # off the surface, behind, masked
        assert val[0] == pytest.approx(0.7)
    with pytest.raises(ShapeError, match="cameras: expected a batch of 1"):
        L.observed_radiance_lookup(cam, depth, rad, invalid)
    with pytest.raises(ShapeError, match="cameras: image size 30x20"):
        L.observed_radiance_lookup([cam], depth[:, :10], rad[:, :10], invalid[:, :10])
    with pytest.raises(ShapeError, match="invalid"):
        L.observed_radiance_lookup([cam], depth, rad, invalid[:, :10])


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


def _grazing_samples(m, rng):
    """Road-like samples: up-facing normals seen from a camera 1.5 m up at 3-30 m (grazing)."""
    n = np.tile([0.0, 0.0, 1.0], (m, 1))
    dist = rng.uniform(3.0, 30.0, m)
    az = rng.uniform(-0.6, 0.6, m)
    pts = np.stack([dist * np.cos(az), dist * np.sin(az), np.zeros(m)], 1)
    wo = np.array([0.0, 0.0, 1.5]) - pts
    return n, wo / np.linalg.norm(wo, axis=1, keepdims=True)


def test_paper_brdf_weights_physics():
    """The paper-BRDF weights: the plain cook_torrance at each pair (float64, chunking does not
    matter), reciprocity, reflectance <= 1 under a uniform sky, and a rough dark surface seen at
    a grazing angle reflects a light ahead of the camera (forward scatter) several times more
    than the same light behind it, while Lambert sees no difference."""
    import torch

    from core.pbr.brdf import cook_torrance

    rng = np.random.default_rng(6)
    m = 50
    n, wo = _grazing_samples(m, rng)
    alb = rng.uniform(0.05, 0.6, (m, 3))
    rough, metal = rng.uniform(0.5, 1.0, m), rng.uniform(0.0, 0.1, m)
    dirs = T.patch_rays(2, 6, 3, rng).reshape(-1, 3)
    w = T.paper_brdf_weights(n, wo, alb, rough, metal)(dirs)
    assert w.shape == (m, len(dirs)) and np.all(w >= 0)
    np.testing.assert_array_equal(w, T.paper_brdf_weights(n, wo, alb, rough, metal, chunk=1)(dirs))
    i, j = 7, 11
    f = cook_torrance(*(torch.tensor(v, dtype=torch.float64) for v in (n[i], dirs[j], wo[i], alb[i])),
                      torch.tensor([rough[i]], dtype=torch.float64), torch.tensor([metal[i]], dtype=torch.float64))
    assert w[i, j] == pytest.approx(float((f.numpy() / alb[i]).mean()) * dirs[j, 2], rel=1e-12)
    # reciprocity: f(a, b) = f(b, a), weight = f cos(light) / albedo
    a, b = wo[:1], dirs[j:j + 1]
    wa = T.paper_brdf_weights(n[:1], a, alb[:1], rough[:1], metal[:1])(b)[0, 0] / b[0, 2]
    wb = T.paper_brdf_weights(n[:1], b, alb[:1], rough[:1], metal[:1])(a)[0, 0] / a[0, 2]
    assert wa == pytest.approx(wb, rel=1e-10)
    # uniform sky of radiance 1: reflected radiance / albedo times albedo is at most 1
    fine = T.patch_rays(16, 48, 16, np.random.default_rng(0)).reshape(-1, 3)
    d_omega = 2 * math.pi / len(fine)
    grey = np.full((m, 3), 0.5)
    refl = T.paper_brdf_weights(n, wo, grey, rough, np.zeros(m))(fine).sum(1) * d_omega * 0.5
    assert np.all(refl <= 1.0) and np.all(refl >= 0.5 - 0.01)  # diffuse 0.5 plus a specular part
    # forward scatter
    ahead, behind = L._sph(0.0, math.radians(30.0)), L._sph(math.pi, math.radians(30.0))
    road = T.paper_brdf_weights(n, wo, np.full((m, 3), 0.09), np.full(m, 0.85), np.zeros(m))
    w2 = road(np.stack([ahead, behind]))
    far = np.linalg.norm(wo[:, :2], axis=1) > 0.98  # grazing views (beyond ~7 m)
    assert np.median(w2[far, 0] / w2[far, 1]) > 2.0
    lam = T.lambert_weights(n)(np.stack([ahead, behind]))
    np.testing.assert_allclose(lam[:, 0], lam[:, 1])


def test_transport_with_paper_brdf_finds_the_sun_on_a_grazing_road():
    """Road samples seen at grazing angles, shaded by the paper's BRDF (asphalt: albedo 0.09,
    roughness 0.85) under a sun ahead of the camera and a uniform sky, 3% noise: the search with
    the paper-BRDF weights finds the sun; with Lambert weights the road's forward scatter is
    unexplained and the fit is worse."""
    rng = np.random.default_rng(7)
    m = 1500
    n, wo = _grazing_samples(m, rng)
    # a few walls so the sun's azimuth is constrained
    walls = rng.random(m) < 0.3
    n[walls] = np.array([0.0, -1.0, 0.0])
    wo[walls] = wo[walls] * np.array([1.0, -1.0, 1.0])
    pts = np.zeros((m, 3))
    weights = T.paper_brdf_weights(n, wo, np.full((m, 3), 0.09), np.full(m, 0.85), np.zeros(m))
    truth = T.SkyTransport(pts, n, np.ones(m), None, weights=weights)
    sun = L._sph(math.radians(10.0), math.radians(35.0))
    shade = truth.patch_T @ np.full(48, 0.4) + 3.0 * truth.sun_columns(sun[None])[:, 0]
    shade *= np.exp(rng.normal(0, 0.03, m))
    st = T.TransportSettings(occluder_radiance=False)
    paper = T.SkyTransport(pts, n, shade, None, settings=st, weights=weights)
    found, res_paper, _ = L._search_sun(L._transport_score(paper), L.LightingSettings())
    assert L.sun_direction_error_deg(found, sun) < 3.0
    lam = T.SkyTransport(pts, n, shade, None, settings=st)
    _, res_lam, _ = L._search_sun(L._transport_score(lam), L.LightingSettings())
    assert res_lam > 1.5 * res_paper


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
    with pytest.raises(ConfigError, match="surface_brdf"):
        L.LightingSettings(surface_brdf="disney")
    with pytest.raises(ConfigError, match="min_view_cos"):
        L.LightingSettings(min_view_cos=1.0)
    n1 = np.tile([0.0, 0.0, 1.0], (2, 1))
    with pytest.raises(ShapeError, match="view_dirs"):
        T.paper_brdf_weights(n1, n1[:1], np.full((2, 3), 0.5), np.ones(2), np.zeros(2))
    with pytest.raises(NumericalError, match="roughness"):
        T.paper_brdf_weights(n1, n1, np.full((2, 3), 0.5), np.array([0.5, np.inf]), np.zeros(2))
    with pytest.raises(ShapeError, match="weights"):
        T.SkyTransport(np.zeros((2, 3)), n1, np.ones(2), weights=lambda d: np.ones((3, len(d))))
