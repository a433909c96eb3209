"""Gradients of the C++ rasterizer: against the PyTorch twin's autograd and finite differences."""

from __future__ import annotations

import pytest
import torch
from raster_scenes import NAMES, camera, random_scene

from core.camera import Camera
from core.raster import RasterSettings, rasterize
from core.raster.reference import reference_rasterize


def _loss(out, weights):
    get = (lambda k: getattr(out, k)) if not isinstance(out, dict) else out.__getitem__
    return sum((get(k) * w).sum() for k, w in weights.items())


def _grads(fn, scene, c2w, bg, cam_rest, weights, settings=None):
    leaves = [t.detach().clone().requires_grad_() for t in scene]
    c2w = c2w.detach().clone().requires_grad_()
    bg = bg.detach().clone().requires_grad_()
    out = fn(*leaves, Camera.from_intrinsics(c2w, *cam_rest), background=bg, settings=settings)
    loss = _loss(out, weights)
    return torch.autograd.grad(loss, leaves + [c2w, bg])


@pytest.mark.parametrize("n,width,height,seed", [(50, 37, 29, 0), (200, 64, 40, 1), (30, 17, 45, 2)])
def test_gradients_match_reference_float64(n, width, height, seed):
    scene = random_scene(n, seed)
    c2w, *rest = camera(width, height)
    bg = torch.tensor([0.3, 0.1, 0.6], dtype=torch.float64)
    g = torch.Generator().manual_seed(seed + 100)
    shapes = {"color": 3, "opacity": 1, "depth": 1, "normal": 3, "albedo": 3, "roughness": 1, "metallic": 1}
    weights = {k: torch.randn(height, width, c, generator=g, dtype=torch.float64) for k, c in shapes.items()}
    fast = _grads(rasterize, scene, c2w, bg, rest, weights)
    ref = _grads(reference_rasterize, scene, c2w, bg, rest, weights)
    for name, a, b in zip(NAMES + ("cam_to_world", "background"), fast, ref):
        assert torch.isfinite(a).all(), name
        scale = float(b.abs().max()) + 1e-12
        assert float((a - b).abs().max()) <= 1e-7 * scale, name


def test_gradients_float32_close_to_reference():
    scene = random_scene(150, 5)
    c2w, *rest = camera(48, 36)
    bg = torch.tensor([0.3, 0.1, 0.6], dtype=torch.float64)
    weights = {k: torch.rand(36, 48, 1, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
               for k in ("opacity", "depth", "roughness")}
    weights["color"] = torch.rand(36, 48, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(4))
    ref = _grads(reference_rasterize, scene, c2w, bg, rest, weights)
    fast = _grads(rasterize, [t.float() for t in scene], c2w.float(), bg.float(), rest,
                  {k: w.float() for k, w in weights.items()})
    for name, a, b in zip(NAMES + ("cam_to_world", "background"), fast, ref):
        assert a.dtype == torch.float32, name
        err = (a.double() - b).norm() / (b.norm() + 1e-12)
        assert float(err) < 2e-3, name


@pytest.mark.parametrize("settings", [RasterSettings(transmittance_min=0.3), RasterSettings(alpha_max=0.6),
                                      RasterSettings(threads=1)])
def test_gradients_match_reference_with_settings(settings):
    scene = random_scene(80, 9, opacity=(0.5, 0.99))
    c2w, *rest = camera(33, 27)
    bg = torch.tensor([1.0, 0.0, 0.5], dtype=torch.float64)
    weights = {k: torch.ones(27, 33, 1, dtype=torch.float64) for k in ("opacity", "depth")}
    weights["normal"] = torch.full((27, 33, 3), 0.5, dtype=torch.float64)
    weights["color"] = torch.full((27, 33, 3), -0.7, dtype=torch.float64)
    fast = _grads(rasterize, scene, c2w, bg, rest, weights, settings)
    ref = _grads(reference_rasterize, scene, c2w, bg, rest, weights, settings)
    for name, a, b in zip(NAMES + ("cam_to_world", "background"), fast, ref):
        assert float((a - b).abs().max()) <= 1e-7 * (float(b.abs().max()) + 1e-12), name


def test_gradcheck_finite_differences():
    scene = random_scene(6, 21, scale=(0.2, 0.6), opacity=(0.2, 0.9))
    c2w, *rest = camera(14, 11)
    rest[-2], rest[-1] = 14, 11
    bg = torch.tensor([0.2, 0.4, 0.6], dtype=torch.float64)
    inputs = [t.detach().clone().requires_grad_() for t in scene] + [c2w.clone().requires_grad_(),
                                                                    bg.clone().requires_grad_()]

    def fn(*args):
        out = rasterize(*args[:9], Camera.from_intrinsics(args[9], *rest), background=args[10])
        return out.packed

    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-5, rtol=1e-4)


def test_threads_give_same_gradients():
    scene = [t.float() for t in random_scene(400, 31)]
    c2w, *rest = camera(64, 48, dtype=torch.float32)
    bg = torch.zeros(3)
    weights = {"color": torch.rand(48, 64, 3, generator=torch.Generator().manual_seed(0))}
    a = _grads(rasterize, scene, c2w, bg, rest, weights, RasterSettings(threads=1))
    b = _grads(rasterize, scene, c2w, bg, rest, weights, RasterSettings(threads=2))
    for name, x, y in zip(NAMES, a, b):
        torch.testing.assert_close(x, y, rtol=1e-4, atol=1e-5, msg=lambda m: f"{name}: {m}")


def test_pose_gradient_through_scene_graph_composition():
    # A node pose composed in torch before the call: its gradient flows through autograd.
    scene = random_scene(40, 41)
    c2w, *rest = camera(30, 24)
    angle = torch.tensor(0.1, dtype=torch.float64, requires_grad=True)
    shift = torch.tensor([0.05, -0.02, 0.1], dtype=torch.float64, requires_grad=True)

    def render(fn, a, s):
        ca, sa = torch.cos(a), torch.sin(a)
        zero, one = torch.zeros((), dtype=torch.float64), torch.ones((), dtype=torch.float64)
        rot = torch.stack([torch.stack([ca, -sa, zero]), torch.stack([sa, ca, zero]), torch.stack([zero, zero, one])])
        means = scene[0] @ rot.T + s
        normals = scene[5] @ rot.T
        out = fn(means, *scene[1:5], normals, *scene[6:], Camera.from_intrinsics(c2w, *rest))
        get = out["depth"] if isinstance(out, dict) else out.depth
        return get.sum()

    ga = torch.autograd.grad(render(rasterize, angle, shift), [angle, shift])
    gb = torch.autograd.grad(render(reference_rasterize, angle, shift), [angle, shift])
    for a, b in zip(ga, gb):
        torch.testing.assert_close(a, b, rtol=1e-7, atol=1e-9)
    assert float(ga[1].abs().sum()) > 0
