"""Point and spot lights: 1/d^2, smooth cone, range window, culling == no culling, scene-graph
attachment, degenerate placements, shadow rays."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from core.errors import ConfigError
from core.numerics import LIGHT_DIST_SQ_MIN, LIGHT_INTENSITY_MAX
from core.pbr.lights import PointLight, SpotLight, direct_lighting, lights_to_world

D64 = torch.float64


def _floor(points, albedo=1.0, rough=1.0, metal=0.0, dtype=D64):
    p = points.shape[0]
    n = torch.tensor([[0.0, 0.0, 1.0]], dtype=dtype).expand(p, 3)
    wo = torch.tensor([[0.0, 0.0, 1.0]], dtype=dtype).expand(p, 3)
    return (points, n, wo, torch.full((p, 3), albedo, dtype=dtype), torch.full((p, 1), rough, dtype=dtype),
            torch.full((p, 1), metal, dtype=dtype))


def test_inverse_square_falloff_on_a_lambertian_floor():
    pts = torch.zeros(1, 3, dtype=D64)
    vals = []
    for h in (1.0, 2.0, 4.0):
        ls = lights_to_world([PointLight((0.0, 0.0, h), intensity=10.0)], dtype=D64)
        vals.append(float(direct_lighting(*_floor(pts), ls, specular=0.0)[0, 0]))
    np.testing.assert_allclose(vals, [10.0 / math.pi, 10.0 / math.pi / 4, 10.0 / math.pi / 16], rtol=1e-12)
    # off-axis: cosine and distance together
    pts = torch.tensor([[3.0, 0.0, 0.0]], dtype=D64)
    ls = lights_to_world([PointLight((0.0, 0.0, 4.0), intensity=10.0, color=(1.0, 0.5, 0.0))], dtype=D64)
    got = direct_lighting(*_floor(pts), ls, specular=0.0)[0].numpy()
    np.testing.assert_allclose(got, 10.0 / 25.0 * 0.8 / math.pi * np.array([1.0, 0.5, 0.0]), rtol=1e-12)


def test_spot_cone_smoothstep_in_degrees():
    inner, outer = 20.0, 30.0
    ls = lights_to_world([SpotLight((0.0, 0.0, 1.0), direction=(0.0, 0.0, -1.0), inner_deg=inner, outer_deg=outer)],
                         dtype=D64)
    angles = np.array([0.0, 10.0, 20.0, 22.0, 25.0, 28.0, 30.0, 40.0])
    # points on the floor at angle a from the axis, all at distance 1 from the light
    pts = torch.from_numpy(np.stack([np.sin(np.radians(angles)), np.zeros_like(angles), 1 - np.cos(np.radians(angles))], -1))
    got = direct_lighting(*_floor(pts), ls, specular=0.0)[:, 0].numpy()
    co, ci = math.cos(math.radians(outer)), math.cos(math.radians(inner))
    t = np.clip((np.cos(np.radians(angles)) - co) / (ci - co), 0, 1)
    cone = t * t * (3 - 2 * t)
    # a point at angle a from the axis sees the light at angle a from its normal (cos factor)
    expected = cone * np.cos(np.radians(angles)) / math.pi
    np.testing.assert_allclose(got, expected, rtol=1e-9, atol=1e-15)
    assert got[0] > 0 and got[-1] == 0 and got[-2] == 0
    assert (np.diff(got) <= 1e-15).all()


def test_range_window_is_smooth_and_reaches_zero():
    ls = lights_to_world([PointLight((0.0, 0.0, 0.5), intensity=1.0, range=3.0)], dtype=D64)
    xs = np.array([0.0, 1.0, 2.0, 2.9, 2.95, 3.0, 4.0])  # d = 3 at x = 2.958
    pts = torch.from_numpy(np.stack([xs, np.zeros_like(xs), np.zeros_like(xs)], -1))
    got = direct_lighting(*_floor(pts), ls, specular=0.0)[:, 0].numpy()
    d = np.sqrt(xs ** 2 + 0.25)
    win = np.clip(1 - (d / 3.0) ** 4, 0, 1) ** 2
    np.testing.assert_allclose(got, 1.0 / d ** 2 * (0.5 / d) / math.pi * win, rtol=1e-9, atol=1e-15)
    assert got[-1] == 0 and got[-2] == 0 and got[-3] > 0


def test_culling_gives_the_unculled_result():
    g = torch.Generator().manual_seed(0)
    p = 3000
    pts = torch.rand(p, 3, generator=g, dtype=D64) * torch.tensor([40.0, 20.0, 0.0], dtype=D64) - torch.tensor([20.0, 10.0, 0.0], dtype=D64)
    nrm = torch.nn.functional.normalize(torch.randn(p, 3, generator=g, dtype=D64) * 0.3 + torch.tensor([0, 0, 1.0], dtype=D64), dim=-1)
    wo = torch.nn.functional.normalize(torch.randn(p, 3, generator=g, dtype=D64) + torch.tensor([0, 0, 1.0], dtype=D64), dim=-1)
    a = torch.rand(p, 3, generator=g, dtype=D64)
    r = torch.rand(p, 1, generator=g, dtype=D64)
    m = torch.rand(p, 1, generator=g, dtype=D64)
    lights = [
        PointLight((0.0, 0.0, 5.0), intensity=300.0, range=12.0),
        SpotLight((5.0, 3.0, 4.0), direction=(0.2, 0.0, -1.0), inner_deg=15, outer_deg=35, intensity=800.0, range=30.0),
        SpotLight((-8.0, -2.0, 0.7), direction=(1.0, 0.0, -0.05), inner_deg=10, outer_deg=20, intensity=2e4),  # headlight
        PointLight((100.0, 0.0, 5.0), intensity=1e3, range=5.0),  # reaches nothing
    ]
    ls = lights_to_world(lights, dtype=D64)
    calls = []

    def vis(o, d, t_max):
        calls.append(o.shape[0])
        return torch.sigmoid(o[:, 0] + d[:, 1] - 0.1 * t_max)  # any deterministic function

    st_c, st_u = {}, {}
    culled = direct_lighting(pts, nrm, wo, a, r, m, ls, visibility=vis, cull=True, stats=st_c)
    unculled = direct_lighting(pts, nrm, wo, a, r, m, ls, visibility=vis, cull=False, stats=st_u)
    np.testing.assert_allclose(culled.numpy(), unculled.numpy(), rtol=0, atol=1e-6 * float(unculled.abs().max()))
    assert (culled > 0).any()
    assert st_c["pairs"] == st_u["pairs"] == 4 * p
    assert st_c["evaluated"] < 0.5 * st_u["evaluated"]


def test_lights_attached_to_a_node_move_with_it():
    yaw = math.radians(90.0)
    pose = np.eye(4)
    pose[:3, :3] = [[math.cos(yaw), -math.sin(yaw), 0], [math.sin(yaw), math.cos(yaw), 0], [0, 0, 1]]
    pose[:3, 3] = [10.0, 5.0, 0.0]
    head = SpotLight((2.2, 0.6, 0.7), direction=(1.0, 0.0, 0.0), node="car0", inner_deg=10, outer_deg=25, name="hl")
    world = PointLight((1.0, 2.0, 3.0))
    ls = lights_to_world([head, world], {"car0": pose})
    np.testing.assert_allclose(ls.position[0].numpy(), [10.0 - 0.6, 5.0 + 2.2, 0.7], atol=1e-6)
    np.testing.assert_allclose(ls.axis[0].numpy(), [0.0, 1.0, 0.0], atol=1e-6)
    np.testing.assert_allclose(ls.position[1].numpy(), [1.0, 2.0, 3.0])
    np.testing.assert_allclose(ls.cos_outer[0].item(), math.cos(math.radians(25)), rtol=1e-6)
    with pytest.raises(ConfigError, match="car0"):
        lights_to_world([head], {})
    bad = pose.copy()
    bad[:3, :3] *= 2
    with pytest.raises(ConfigError, match="car0"):
        lights_to_world([head], {"car0": bad})


def test_light_at_the_shading_point_and_huge_intensity_are_finite():
    pts = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.05, 0.0, 0.0]], dtype=torch.float32, requires_grad=True)
    ls = lights_to_world([PointLight((0.0, 0.0, 0.0), intensity=LIGHT_INTENSITY_MAX),
                          PointLight((0.0, 0.0, 1e-7), intensity=LIGHT_INTENSITY_MAX, range=1.0),
                          SpotLight((0.0, 0.0, 1e-3), direction=(0, 0, -1), intensity=LIGHT_INTENSITY_MAX)])
    for rough, metal in ((0.0, 1.0), (1.0, 0.0)):
        args = list(_floor(pts, rough=rough, metal=metal, dtype=torch.float32))
        args[0] = pts
        out = direct_lighting(*args, ls)
        assert torch.isfinite(out).all() and (out >= 0).all()
        out.sum().backward()
        assert torch.isfinite(pts.grad).all()
        pts.grad = None
    with pytest.raises(ConfigError, match="intensity"):
        PointLight((0, 0, 0), intensity=LIGHT_INTENSITY_MAX * 10)
    assert LIGHT_DIST_SQ_MIN > 0


def test_shadow_ray_is_deterministic_and_ends_at_the_light():
    pts = torch.tensor([[0.0, 0.0, 0.0]], dtype=D64)
    ls = lights_to_world([PointLight((0.0, 0.0, 2.0), intensity=4.0)], dtype=D64)
    seen = []

    def vis(o, d, t_max):
        seen.append((o.clone(), d.clone(), t_max.clone()))
        return torch.full((o.shape[0],), 0.25, dtype=o.dtype)

    out = direct_lighting(*_floor(pts), ls, visibility=vis, specular=0.0, normal_offset=0.01)
    assert len(seen) == 1
    o, d, t = seen[0]
    np.testing.assert_allclose(o.numpy(), [[0.0, 0.0, 0.01]])
    np.testing.assert_allclose(d.numpy(), [[0.0, 0.0, 1.0]])
    np.testing.assert_allclose(t.numpy(), [2.0])
    assert float(out[0, 0]) == pytest.approx(0.25 * 4.0 / 4.0 / math.pi)


def test_light_validation_errors_name_the_field():
    with pytest.raises(ConfigError, match="inner_deg"):
        SpotLight((0, 0, 0), inner_deg=40, outer_deg=30)
    with pytest.raises(ConfigError, match="outer_deg"):
        SpotLight((0, 0, 0), outer_deg=200)
    with pytest.raises(ConfigError, match="direction"):
        SpotLight((0, 0, 0), direction=(0, 0, 0))
    with pytest.raises(ConfigError, match="range"):
        PointLight((0, 0, 0), range=0.0)
    with pytest.raises(ConfigError, match="color"):
        PointLight((0, 0, 0), color=(1, -1, 0))
    with pytest.raises(ConfigError, match="position"):
        PointLight((0, float("nan"), 0))
