"""Degenerate inputs: no NaN/Inf in outputs or gradients, and the dense twin still agrees."""

from __future__ import annotations

import pytest
import torch
from raster_scenes import CHANNELS, NAMES, camera, random_scene

from core.camera import Camera
from core.raster import RasterSettings, rasterize
from core.raster.reference import reference_rasterize


def _render_and_grad(scene, cam, dtype=torch.float64, settings=None, bg=None):
    leaves = [t.to(dtype).detach().clone().requires_grad_() for t in scene]
    c2w = cam[0].to(dtype).clone().requires_grad_()
    out = rasterize(*leaves, Camera.from_intrinsics(c2w, *cam[1:]), background=bg, settings=settings)
    loss = sum(getattr(out, k).sum() * (i + 1) for i, k in enumerate(CHANNELS))
    grads = torch.autograd.grad(loss, leaves + [c2w])
    for k in CHANNELS:
        assert torch.isfinite(getattr(out, k)).all(), k
    for name, g in zip(NAMES + ("cam_to_world",), grads):
        assert torch.isfinite(g).all(), name
    return out, grads


def _variants():
    def zero_scale(s):
        s[2][:5] = 0.0

    def huge_scale(s):
        s[2][:5] = 1e30

    def one_huge_axis(s):
        s[2][5:8, 0] = 1e8

    def zero_quat(s):
        s[1][:6] = 0.0

    def behind(s):
        s[0][:5, 2] = -2.0

    def on_plane(s):
        s[0][5:10, 2] = 0.0

    def at_near(s):
        s[0][10:12, 2] = 0.01

    def just_past_near(s):
        s[0][12:14, 2] = 0.0101

    def cover_all(s):
        s[0][0] = torch.tensor([0.0, 0.0, 3.0], dtype=s[0].dtype)
        s[2][0] = 50.0
        s[3][0] = 0.7

    def outside_guard_band(s):  # means far outside the view (clamped Jacobian), footprints reaching in
        s[0][20:26] = torch.tensor([[4.0, 0.3, 2.5], [-5.0, 0.0, 3.0], [0.2, 3.5, 2.0], [0.0, -4.0, 2.2],
                                    [6.0, 6.0, 3.0], [-3.0, 2.5, 2.0]], dtype=s[0].dtype)
        s[2][20:26] = 1.5
        s[3][20:26] = 0.9

    def opac_01(s):
        s[3][:10] = 0.0
        s[3][10:20] = 1.0

    return {f.__name__: f for f in (zero_scale, huge_scale, one_huge_axis, zero_quat, behind, on_plane,
                                    at_near, just_past_near, cover_all, outside_guard_band, opac_01)}


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("variant", sorted(_variants()))
def test_degenerate_inputs_are_finite(variant, dtype):
    scene = random_scene(40, 3)
    _variants()[variant](scene)
    cam = camera(33, 21)
    out, grads = _render_and_grad(scene, cam, dtype)
    if dtype == torch.float64 and variant not in ("huge_scale", "one_huge_axis"):
        leaves = [t.detach().clone().requires_grad_() for t in scene]
        c2w = cam[0].clone().requires_grad_()
        ref = reference_rasterize(*leaves, Camera.from_intrinsics(c2w, *cam[1:]))
        for k in CHANNELS:
            torch.testing.assert_close(getattr(out, k).detach(), ref[k].detach(), rtol=1e-5, atol=1e-8)
        loss = sum(ref[k].sum() * (i + 1) for i, k in enumerate(CHANNELS))
        ref_grads = torch.autograd.grad(loss, leaves + [c2w])
        for name, a, b in zip(NAMES + ("cam_to_world",), grads, ref_grads):
            assert float((a - b).abs().max()) <= 1e-7 * (float(b.abs().max()) + 1e-12), name


def test_gaussian_covering_the_whole_image():
    scene = random_scene(1, 0)
    scene[0][0] = torch.tensor([0.0, 0.0, 3.0], dtype=torch.float64)
    scene[2][0] = 30.0
    scene[3][0] = 0.8
    cam = camera(40, 30, tilted=False)
    out, _ = _render_and_grad(scene, cam)
    op = out.opacity.detach()
    assert float(op.min()) > 0.79 and float(op.max()) <= 0.8
    torch.testing.assert_close(out.opacity, reference_rasterize(*scene, Camera.from_intrinsics(*cam))["opacity"], rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_empty_scene(dtype):
    scene = [t[:0] for t in random_scene(3, 0)]
    bg = torch.tensor([0.1, 0.2, 0.3], dtype=dtype)
    out, grads = _render_and_grad(scene, camera(19, 7), dtype, bg=bg)
    assert out.color.shape == (7, 19, 3)
    torch.testing.assert_close(out.color, bg.expand(7, 19, 3))
    assert float(out.opacity.detach().abs().max()) == 0.0
    assert out.num_visible == 0 and out.num_tile_pairs == 0
    assert all(g.shape[0] == 0 for g in grads[:9])


def test_one_by_one_image():
    scene = random_scene(30, 4)
    cam = camera(1, 1)
    out, _ = _render_and_grad(scene, cam)
    assert out.color.shape == (1, 1, 3)
    ref = reference_rasterize(*scene, Camera.from_intrinsics(*cam))
    torch.testing.assert_close(out.color, ref["color"], rtol=1e-6, atol=1e-9)


def test_all_behind_camera():
    scene = random_scene(20, 5)
    scene[0][:, 2] = -scene[0][:, 2]
    out, grads = _render_and_grad(scene, camera(16, 16, tilted=False))
    assert float(out.opacity.detach().abs().max()) == 0.0
    assert all(float(g.abs().max()) == 0.0 for g in grads[:9])


def test_extreme_settings_finite():
    scene = random_scene(60, 6, opacity=(0.9, 1.0))
    _render_and_grad(scene, camera(24, 24), settings=RasterSettings(alpha_max=0.999999, transmittance_min=0.0))
    _render_and_grad(scene, camera(24, 24), torch.float32, settings=RasterSettings(alpha_max=0.999999,
                                                                                   transmittance_min=0.0))
