"""Forward of the C++ tile rasterizer against the dense float64 PyTorch twin."""

from __future__ import annotations

import pytest
import torch
from raster_scenes import CHANNELS, camera, random_scene

from core.camera import Camera
from core.raster import RasterSettings, rasterize
from core.raster.reference import reference_rasterize


def _compare(out, ref, rtol, atol):
    for name in CHANNELS:
        a, b = getattr(out, name), ref[name]
        assert a.shape == b.shape, name
        torch.testing.assert_close(a.double(), b, rtol=rtol, atol=atol, msg=lambda m: f"{name}: {m}")
    torch.testing.assert_close(out.transmittance.double(), ref["transmittance"], rtol=rtol, atol=atol)


@pytest.mark.parametrize(
    "n,width,height,seed,tilted",
    [(40, 37, 29, 0, True), (150, 64, 48, 1, True), (300, 50, 70, 2, False), (80, 16, 16, 3, True),
     (120, 97, 33, 4, True), (1, 20, 20, 5, False)],
)
def test_forward_float64_matches_reference(n, width, height, seed, tilted):
    scene = random_scene(n, seed)
    cam = Camera.from_intrinsics(*camera(width, height, tilted=tilted))
    bg = torch.tensor([0.2, 0.5, 0.9], dtype=torch.float64)
    out = rasterize(*scene, cam, background=bg)
    ref = reference_rasterize(*scene, cam, background=bg)
    assert out.opacity.max() > 0.3  # the scene is visible
    _compare(out, ref, rtol=1e-5, atol=1e-9)
    # and in fact to rounding
    assert (out.packed[..., 0:3] - ref["color"]).abs().max() < 1e-12


def test_forward_float32_close_to_float64_reference():
    scene = random_scene(200, 7)
    cam = Camera.from_intrinsics(*camera(61, 45))
    ref = reference_rasterize(*scene, cam)
    out32 = rasterize(*[t.float() for t in scene], cam.to(torch.float32))
    assert out32.color.dtype == torch.float32
    _compare(out32, ref, rtol=2e-3, atol=2e-4)


@pytest.mark.parametrize(
    "settings",
    [RasterSettings(alpha_min=0.05), RasterSettings(transmittance_min=0.2), RasterSettings(low_pass=2.0),
     RasterSettings(alpha_max=0.5), RasterSettings(near=3.0), RasterSettings(guard_band=1.0), RasterSettings(threads=1),
     RasterSettings(threads=3)],
)
def test_settings_follow_reference(settings):
    scene = random_scene(120, 11, opacity=(0.3, 0.99))
    cam = Camera.from_intrinsics(*camera(40, 33))
    out = rasterize(*scene, cam, settings=settings)
    ref = reference_rasterize(*scene, cam, settings=settings)
    _compare(out, ref, rtol=1e-5, atol=1e-9)


def test_early_stop_and_dense_overlap():
    # Many opaque Gaussians on top of each other: most pixels stop early.
    scene = random_scene(400, 12, spread=0.3, scale=(0.2, 0.6), opacity=(0.5, 0.95))
    cam = Camera.from_intrinsics(*camera(48, 40))
    out = rasterize(*scene, cam, settings=RasterSettings(collect_stats=True))
    ref = reference_rasterize(*scene, cam)
    _compare(out, ref, rtol=1e-5, atol=1e-9)
    assert float(out.transmittance.min()) >= 1e-4 * (1 - 1e-9)
    evaluated, contributed = out.stats[..., 0], out.stats[..., 1]
    assert bool((contributed <= evaluated).all())
    assert float(contributed.float().mean()) > 5


def test_threads_are_deterministic():
    scene = [t.float() for t in random_scene(500, 13)]
    cam = Camera.from_intrinsics(camera(80, 64)[0].float(), *camera(80, 64)[1:])
    a = rasterize(*scene, cam, settings=RasterSettings(threads=1))
    b = rasterize(*scene, cam, settings=RasterSettings(threads=2))
    assert torch.equal(a.packed, b.packed)


def test_culling_counts():
    scene = random_scene(50, 14)
    scene[0][:10, 2] = -1.0  # behind the camera
    scene[0][10:20, 0] = 100.0  # far off to the side
    cam = Camera.from_intrinsics(*camera(32, 32, tilted=False))
    out = rasterize(*scene, cam)
    assert out.num_visible <= 30
    assert out.num_tile_pairs >= out.num_visible


def test_rasterize_gaussians_container():
    from core.gaussians import Gaussians

    scene = random_scene(60, 15)
    g = Gaussians.from_activated(*scene)
    from core.raster import rasterize_gaussians

    cam = Camera.from_intrinsics(*camera(30, 20))
    out = rasterize_gaussians(g, cam)
    ref = reference_rasterize(*scene, cam)
    _compare(out, ref, rtol=1e-5, atol=1e-8)


def test_random_scenes_property():
    from hypothesis import HealthCheck, given, settings
    from hypothesis import strategies as st

    @settings(max_examples=15, deadline=None, suppress_health_check=list(HealthCheck))
    @given(n=st.integers(0, 60), width=st.integers(1, 40), height=st.integers(1, 40), seed=st.integers(0, 10_000),
           tilted=st.booleans(), opac_hi=st.floats(0.05, 1.0))
    def check(n, width, height, seed, tilted, opac_hi):
        scene = random_scene(n, seed, opacity=(0.0, opac_hi))
        cam = Camera.from_intrinsics(*camera(width, height, tilted=tilted))
        out = rasterize(*scene, cam)
        ref = reference_rasterize(*scene, cam)
        _compare(out, ref, rtol=1e-5, atol=1e-9)

    check()
