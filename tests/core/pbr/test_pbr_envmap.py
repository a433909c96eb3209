"""EnvironmentMap: lookup convention, rotation, sampling density (chi-square), exact estimators,
sun maps, black maps, gradients, validation."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from core import conventions
from core.errors import ConfigError, NumericalError, ShapeError
from core.pbr.envmap import EnvironmentMap, luminance, rotate_z
from chi_square import chi_square_pvalue  # tests/chi_square.py

REPO = Path(__file__).resolve().parents[3]
CITY = REPO / "data" / "hdri" / "city.exr"


def _gen(seed=0):
    return torch.Generator().manual_seed(seed)


def _random_map(h=8, w=16, seed=0, lo=0.2):
    rng = np.random.default_rng(seed)
    return rng.uniform(lo, 1.0, (h, w, 3)).astype(np.float32)


# ---------------------------------------------------------------------------------------------
# lookup and the project convention
# ---------------------------------------------------------------------------------------------

def test_lookup_at_pixel_centres_returns_pixel_values():
    rgb = _random_map(16, 32, seed=1)
    env = EnvironmentMap(rgb, dtype=torch.float64)
    dirs = torch.from_numpy(conventions.envmap_directions(16, 32))
    got = env.lookup(dirs).numpy()
    np.testing.assert_allclose(got, rgb, rtol=1e-6, atol=1e-7)


def test_lookup_bilinear_wraps_in_azimuth_and_clamps_at_poles():
    h, w = 8, 16
    rgb = np.zeros((h, w, 3), np.float32)
    rgb[:, 0] = 1.0  # first column
    rgb[:, w - 1] = 3.0  # last column
    env = EnvironmentMap(rgb, dtype=torch.float64)
    # the seam between column W-1 and column 0 is at u = 0: halfway between the two centres
    seam = conventions.pixel_to_direction(np.array(3.0), np.array(-0.5), h, w)
    assert env.lookup(torch.from_numpy(seam))[0].item() == pytest.approx(2.0, abs=1e-9)
    # the zenith and the nadir: rows clamp, so only the azimuth interpolation remains
    rgb2 = np.arange(h, dtype=np.float32)[:, None, None].repeat(w, 1).repeat(3, 2)
    env2 = EnvironmentMap(rgb2, dtype=torch.float64)
    up = env2.lookup(torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]], dtype=torch.float64))
    np.testing.assert_allclose(up[:, 0].numpy(), [0.0, h - 1.0], atol=1e-9)


def test_lookup_matches_direction_to_pixel_of_conventions():
    rng = np.random.default_rng(3)
    rgb = _random_map(32, 64, seed=2)
    env = EnvironmentMap(rgb, dtype=torch.float64)
    # directions near pixel centres (within 1e-3 of a pixel) read that pixel
    rows = rng.integers(0, 32, 500)
    cols = rng.integers(0, 64, 500)
    d = conventions.pixel_to_direction(rows + rng.uniform(-1e-4, 1e-4, 500), cols + rng.uniform(-1e-4, 1e-4, 500), 32, 64)
    r, c = conventions.direction_to_pixel(d, 32, 64)
    np.testing.assert_array_equal(r, rows)
    got = env.lookup(torch.from_numpy(d)).numpy()
    np.testing.assert_allclose(got, rgb[rows, cols], rtol=2e-3)


def test_rotation_is_about_z_in_degrees():
    rgb = _random_map(16, 32, seed=4)
    base = EnvironmentMap(rgb, dtype=torch.float64)
    rot = EnvironmentMap(rgb, rotation_deg=90.0, dtype=torch.float64)
    d = torch.nn.functional.normalize(torch.randn(200, 3, generator=_gen(1), dtype=torch.float64), dim=-1)
    np.testing.assert_allclose(rot.lookup(rotate_z(d, math.pi / 2)).numpy(), base.lookup(d).numpy(), atol=1e-9)
    # +90 degrees moves what was at +x to +y
    np.testing.assert_allclose(rot.lookup(torch.tensor([[0.0, 1.0, 0.0]], dtype=torch.float64)).numpy(),
                               base.lookup(torch.tensor([[1.0, 0.0, 0.0]], dtype=torch.float64)).numpy(), atol=1e-9)
    assert rot.rotation_deg == pytest.approx(90.0)


def test_exposure_scales_radiance_not_pdf():
    rgb = _random_map(8, 16, seed=5)
    a = EnvironmentMap(rgb, dtype=torch.float64)
    b = EnvironmentMap(rgb, exposure=2.5, dtype=torch.float64)
    d = torch.nn.functional.normalize(torch.randn(50, 3, generator=_gen(2), dtype=torch.float64), dim=-1)
    np.testing.assert_allclose(b.lookup(d).numpy(), 2.5 * a.lookup(d).numpy(), rtol=1e-12)
    np.testing.assert_allclose(b.pdf(d).numpy(), a.pdf(d).numpy(), rtol=1e-12)


# ---------------------------------------------------------------------------------------------
# sampling
# ---------------------------------------------------------------------------------------------

def test_pdf_integrates_to_one_and_matches_sample_pdf():
    for rot in (0.0, 37.0):
        env = EnvironmentMap(_random_map(16, 32, seed=6), rotation_deg=rot, dtype=torch.float64)
        centres = rotate_z(torch.from_numpy(conventions.envmap_directions(16, 32)), math.radians(rot))
        omega = conventions.envmap_solid_angles(16, 32)[:, None]
        total = float((env.pdf(centres).numpy() * omega).sum())
        assert total == pytest.approx(1.0, abs=1e-9)
        dirs, pdf, _ = env.sample(5000, _gen(3))
        np.testing.assert_allclose(pdf.numpy(), env.pdf(dirs).numpy(), rtol=1e-9)


def test_chi_square_sampler_against_pdf_with_sub_pixel_bins():
    """Bins of 4x4 sub-pixels (equal cos(theta) and azimuth steps) test both the choice of the
    pixel and the uniform-in-solid-angle placement inside it."""
    h, w, sub, n = 8, 16, 4, 200_000
    env = EnvironmentMap(_random_map(h, w, seed=7), dtype=torch.float64)
    dirs, _, _ = env.sample(n, _gen(4))
    d = dirs.numpy()
    u, v = conventions.direction_to_uv(d, h, w)
    row = np.clip(np.floor(v).astype(int), 0, h - 1)
    col = np.clip(np.floor(u).astype(int), 0, w - 1)
    c0 = np.cos(row / h * math.pi)
    c1 = np.cos((row + 1) / h * math.pi)
    sr = np.clip(((c0 - d[:, 2]) / (c0 - c1) * sub).astype(int), 0, sub - 1)
    sc = np.clip(((u - col) * sub).astype(int), 0, sub - 1)
    idx = ((row * w + col) * sub + sr) * sub + sc
    observed = np.bincount(idx, minlength=h * w * sub * sub)
    expected = np.repeat(env.pixel_probabilities().numpy().ravel(), sub * sub) / (sub * sub) * n
    assert chi_square_pvalue(observed, expected) > 1e-3
    # a wrong density (sin(theta) at the centre instead of the row integral) must fail
    wrong = np.repeat((env.pixel_probabilities().numpy() * 1.0).ravel(), sub * sub)
    wrong = wrong.reshape(h, w, sub, sub) * np.linspace(0.7, 1.3, sub)[None, None, :, None]
    assert chi_square_pvalue(observed, wrong.ravel() / wrong.sum() * n) < 1e-6


def test_chi_square_sampler_on_city_hdri_coarse_bins():
    env = EnvironmentMap.from_file(CITY, dtype=torch.float32)
    assert (env.height, env.width) == (512, 1024)
    n = 300_000
    dirs, pdf, rad = env.sample(n, _gen(5))
    assert torch.isfinite(pdf).all() and (pdf > 0).all() and torch.isfinite(rad).all()
    r, c = conventions.direction_to_pixel(dirs.double().numpy(), 512, 1024)
    bins = (r // 16) * 64 + (c // 16)  # 32 x 64 coarse bins of 16x16 pixels
    observed = np.bincount(bins, minlength=32 * 64)
    prob = env.pixel_probabilities().numpy().reshape(32, 16, 64, 16).sum((1, 3)).ravel()
    assert chi_square_pvalue(observed, prob * n) > 1e-3


def test_single_bright_pixel_samples_fall_in_that_pixel():
    h, w = 32, 64
    for rot in (0.0, 90.0):
        rgb = np.zeros((h, w, 3), np.float32)
        rgb[9, 41] = 5.0
        env = EnvironmentMap(rgb, rotation_deg=rot, dtype=torch.float64, sampling_filter="none")
        dirs, pdf, rad = env.sample(2000, _gen(6))
        d_map = rotate_z(dirs, -math.radians(rot)).numpy()
        r, c = conventions.direction_to_pixel(d_map, h, w)
        assert (r == 9).all() and (c == 41).all()
        centre = conventions.pixel_to_direction(np.array(9), np.array(41), h, w)
        centre_world = rotate_z(torch.from_numpy(centre), math.radians(rot)).numpy()
        ang = np.degrees(np.arccos(np.clip(dirs.numpy() @ centre_world, -1, 1)))
        assert ang.max() < 180.0 / h * 1.5  # within a pixel of the centre
        omega = conventions.envmap_solid_angles(h, w)[9]
        np.testing.assert_allclose(pdf.numpy(), 1.0 / omega, rtol=1e-9)


def test_max3x3_filter_samples_the_neighbourhood_of_a_bright_pixel_and_bounds_l_over_pdf():
    h, w = 32, 64
    rgb = np.full((h, w, 3), 1e-3, np.float32)
    rgb[9, 41] = 3.5e4
    env = EnvironmentMap(rgb, dtype=torch.float64)
    dirs, pdf, rad = env.sample(20000, _gen(7))
    r, c = conventions.direction_to_pixel(dirs.numpy(), h, w)
    near = (np.abs(r - 9) <= 1) & (np.abs(c - 41) <= 1)
    assert near.mean() > 0.99
    ratio = luminance(rad).numpy() / pdf.numpy()
    # L / pdf <= sum over pixels of (3x3 max luminance) * solid angle <= 9 * integral of the luminance
    omega = conventions.envmap_solid_angles(h, w)[:, None]
    assert ratio.max() <= 9.0 * float((luminance(env.radiance_map()).numpy() * omega).sum())
    # a direction in the neighbouring pixel, near the sun: bilinear radiance ~ half the sun's
    env0 = EnvironmentMap(rgb, dtype=torch.float64, sampling_filter="none")
    d = torch.from_numpy(conventions.pixel_to_direction(np.array([9.0]), np.array([41.6]), h, w))
    r_f = float(luminance(env.lookup(d))[0] / env.pdf(d)[0])
    r_0 = float(luminance(env0.lookup(d))[0] / env0.pdf(d)[0])
    assert r_f <= 9.0 * float((luminance(env.radiance_map()).numpy() * omega).sum())
    assert r_0 > 1e4 * r_f  # the firefly the filter removes


def test_constant_map_estimators_are_exact_per_sample():
    """pdf = 1/(4 pi) exactly for a constant map, so L / pdf is the same for every sample: the
    estimator of the integral of L over the sphere is exact; the irradiance (cosine) estimator
    is unbiased and converges to pi * L."""
    for h, w, rot, expo in ((16, 32, 0.0, 1.0), (64, 128, 123.0, 2.0), (5, 7, 10.0, 1.0)):
        env = EnvironmentMap.constant(1.0, h, w, rotation_deg=rot, exposure=expo, dtype=torch.float64)
        dirs, pdf, rad = env.sample(200_000, _gen(7))
        est = rad[:, 0] / pdf
        np.testing.assert_allclose(est.numpy(), 4.0 * math.pi * expo, rtol=1e-9)
        irr = rad[:, 0] * dirs[:, 2].clamp_min(0.0) / pdf
        se = float(irr.std()) / math.sqrt(irr.numel())
        assert abs(float(irr.mean()) - math.pi * expo) < 4.0 * se
        # cosine-weighted directions over the upper hemisphere: uniform over the sphere
        assert abs(float((dirs[:, 2] > 0).double().mean()) - 0.5) < 0.005


@pytest.mark.parametrize("peak", [None, 1e6])
def test_sun_maps_give_finite_positive_pdfs(peak):
    from core.io.envmap_file import read_envmap

    rgb = read_envmap(CITY)
    if peak is not None:
        rgb = rgb * 0.01
        rgb[100, 300] = peak
    else:
        assert rgb.max() > 3e4
    env = EnvironmentMap(rgb)
    dirs, pdf, rad = env.sample(100_000, _gen(8))
    assert torch.isfinite(dirs).all() and torch.isfinite(pdf).all() and torch.isfinite(rad).all()
    assert (pdf > 0).all() and (rad >= 0).all()
    est = rad * dirs[:, 2:3].clamp_min(0) / pdf[:, None]
    assert torch.isfinite(est).all()
    if peak is not None:
        # the synthetic sun dominates: most samples go to it or its 3x3 neighbourhood (max3x3)
        r, c = conventions.direction_to_pixel(dirs.double().numpy(), 512, 1024)
        assert ((np.abs(r - 100) <= 1) & (np.abs(c - 300) <= 1)).mean() > 0.5
    p_any = env.pdf(torch.nn.functional.normalize(torch.randn(1000, 3, generator=_gen(9)), dim=-1))
    assert torch.isfinite(p_any).all() and (p_any >= 0).all()


def test_all_zero_map_falls_back_to_uniform_sampling():
    env = EnvironmentMap(np.zeros((8, 16, 3), np.float32))
    assert env.fallback_uniform
    dirs, pdf, rad = env.sample(1000, _gen(10))
    assert torch.isfinite(dirs).all()
    np.testing.assert_allclose(pdf.numpy(), 1.0 / (4.0 * math.pi), rtol=1e-6)
    assert (rad == 0).all()


def test_uniform_fraction_keeps_every_pixel_sampleable():
    rgb = np.zeros((8, 16, 3), np.float32)
    rgb[2, 3] = 1.0
    env = EnvironmentMap(rgb, uniform_fraction=0.1, dtype=torch.float64, sampling_filter="none")
    p = env.pixel_probabilities().numpy()
    assert (p > 0).all() and p.sum() == pytest.approx(1.0)
    assert p[2, 3] > 0.9


# ---------------------------------------------------------------------------------------------
# gradients, resampling, validation
# ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize("log_space", [False, True])
def test_lookup_is_differentiable_wrt_the_map(log_space):
    rgb = _random_map(8, 16, seed=11)
    rgb[0, 0] = 0.0
    env = EnvironmentMap(rgb, log_space=log_space, requires_grad=True, dtype=torch.float64)
    assert env.param.requires_grad and env.param.is_leaf
    dirs, pdf, rad = env.sample(500, _gen(12))
    more = env.lookup(torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64))
    (rad.sum() + more.sum()).backward()
    g = env.param.grad
    assert torch.isfinite(g).all() and g.abs().sum() > 0
    if not log_space:
        # bilinear weights of each lookup sum to one per channel
        assert float(g.sum()) == pytest.approx(3 * 501, rel=1e-9)
    else:
        assert env.radiance_map().detach()[0, 0, 0].item() == pytest.approx(1e-8)


def test_resample_to_paper_size_keeps_constant_and_mean():
    env = EnvironmentMap.constant((0.5, 1.0, 2.0), 64, 128, resample_to=(512, 1024))
    assert (env.height, env.width) == (512, 1024)
    np.testing.assert_allclose(env.radiance_map()[..., 2].numpy(), 2.0, rtol=1e-6)
    rgb = _random_map(1024, 2048, seed=13)
    down = EnvironmentMap(rgb, resample_to=(512, 1024), dtype=torch.float64).radiance_map().numpy()
    assert down.mean() == pytest.approx(rgb.mean(), rel=1e-6)
    up = EnvironmentMap(_random_map(100, 200, seed=14), resample_to=(512, 1024)).radiance_map()
    assert up.shape == (512, 1024, 3) and torch.isfinite(up).all()


def test_invalid_maps_raise_named_errors():
    with pytest.raises(ShapeError, match="rgb"):
        EnvironmentMap(np.zeros((4, 8)))
    with pytest.raises(ConfigError, match="rgb"):
        EnvironmentMap(-np.ones((4, 8, 3)))
    bad = np.ones((4, 8, 3))
    bad[1, 1, 1] = np.nan
    with pytest.raises(NumericalError, match="rgb"):
        EnvironmentMap(bad)
    with pytest.raises(ConfigError, match="exposure"):
        EnvironmentMap(np.ones((4, 8, 3)), exposure=0.0)
    with pytest.raises(ConfigError, match="rotation_deg"):
        EnvironmentMap(np.ones((4, 8, 3)), rotation_deg=float("inf"))
    env = EnvironmentMap(np.ones((4, 8, 3)))
    with pytest.raises(ShapeError, match="dirs_world"):
        env.lookup(torch.ones(5, 2))
    with pytest.raises(NumericalError, match="dirs_world"):
        env.pdf(torch.full((2, 3), float("nan")))
